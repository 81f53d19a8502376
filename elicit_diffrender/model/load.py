"""A fitted model from a run folder or its avatar file, whichever kind the fit wrote, never running code from it."""

from __future__ import annotations

from pathlib import Path

from ..core.device import default_device
from ..core.errors import ElicitError
from .avatar import Avatar


def load_avatar(run: str | Path):
    """The fitted model of a run folder (or its avatar file): an :class:`Avatar`, or the explicit-texture
    baseline's :class:`TexturedBody`. Both render with ``render_pose(camera, pose, orient, transl)``.

    ``avatar.safetensors`` holds tensors and JSON only; an ``avatar.pt`` of earlier versions is read with
    ``torch.load(weights_only=True)``, which builds tensors and containers and nothing else."""
    from .avatar import AVATAR_FILE, LEGACY_FILE, AvatarError
    from .textured_body import FORMAT as TEXTURED
    from .textured_body import LEGACY_FORMAT as LEGACY_TEXTURED
    from .textured_body import TexturedBody

    path = Path(run)
    if path.is_dir():
        path = path / (
            LEGACY_FILE if (path / LEGACY_FILE).is_file() and not (path / AVATAR_FILE).exists() else AVATAR_FILE
        )
    if not path.is_file():
        raise AvatarError(f"{path}: avatar file not found (did the fit finish?)")
    data = read_model_file(path)
    try:
        if isinstance(data, dict) and data.get("format") in (TEXTURED, LEGACY_TEXTURED):
            return TexturedBody.from_state(data)
        return Avatar.from_state(data).to(default_device())
    except ElicitError as exc:
        raise AvatarError(f"{path}: {exc}") from None


def read_model_file(path: Path) -> dict:
    """The state in an avatar file (``.safetensors``, or a legacy ``.pt``), never running code from it."""
    from ..core.io import read_tensors
    from .avatar import AvatarError

    if path.suffix == ".safetensors":
        try:
            return read_tensors(path)
        except ValueError as exc:
            raise AvatarError(f"{path}: unreadable avatar file ({exc})") from None
    if path.suffix != ".pt":
        raise AvatarError(f"{path}: not an avatar file (expected avatar.safetensors, or avatar.pt of earlier versions)")
    import pickle

    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:
        raise AvatarError(
            f"{path}: unreadable avatar file ({type(exc).__name__}); avatar files of every elicit version hold "
            "only tensors, numbers, strings, lists and dicts, so this one is damaged or was not written by elicit"
        ) from None
