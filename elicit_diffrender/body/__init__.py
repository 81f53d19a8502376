"""Body models behind one interface (see :mod:`elicit_diffrender.body.base`), and the photo body fit (``fitting``).

May import: ``core``.
"""

from __future__ import annotations

from .base import BACKGROUND, PART_NAMES, SEMANTIC_JOINTS, BodyModel, BodyModelError, PosedBody


def load_body(spec: dict) -> BodyModel:
    """A body model from a subject's ``body`` entry.

    ``{"model": "anny", "phenotype": {...}}`` or
    ``{"model": "smpl" | "smplx", "betas": [...], "gender": "neutral", "model_path": optional}``.
    """
    if not isinstance(spec, dict) or "model" not in spec:
        raise BodyModelError(f"body must be an object with a 'model' field, got {spec!r}")
    model = spec["model"]
    if model == "anny":
        from .anny_model import AnnyBody

        return AnnyBody(spec.get("phenotype"))
    if model in ("smpl", "smplx"):
        from .smpl_model import SmplBody

        return SmplBody(spec.get("betas"), spec.get("gender", "neutral"), model, spec.get("model_path"))
    raise BodyModelError(f"unknown body model {model!r}; use 'anny', 'smpl' or 'smplx'")


__all__ = ["BACKGROUND", "PART_NAMES", "SEMANTIC_JOINTS", "BodyModel", "BodyModelError", "PosedBody", "load_body"]
