"""``elicit fit``: ELICIT's one-shot optimisation of an avatar (or the paper's textured-body baseline).

Modules, one job each: ``views`` (what the fit looks at), ``render`` (the avatar at the training
poses), ``objective`` (the loss terms and their weights), ``guard`` (empty-render recovery),
``checkpoint`` (resumable state), ``streams`` (random generators), ``trainer`` (the loop). A run
folder holds ``checkpoint.safetensors`` (resumable), ``avatar.pt`` (the result), ``run.json``,
``log.txt`` and ``previews/``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..config import FitConfig
from ..subject import Subject
from .checkpoint import FitError
from .trainer import Trainer

__all__ = ["FitError", "Trainer", "fit"]


def setup_logging(run_dir: Path) -> None:
    """Log to ``run_dir/log.txt`` and the terminal."""
    run_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(run_dir / "log.txt")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("elicit")
    root.setLevel(logging.INFO)
    root.handlers = [handler, logging.StreamHandler()]


def fit(subject: Subject, cfg: FitConfig, run_dir: str | Path, resume: bool = False) -> dict:
    """Fit an avatar to ``subject`` (or the baseline that ``cfg.baseline`` names); returns the run report
    (also written to ``run_dir/run.json``)."""
    setup_logging(Path(run_dir))
    if cfg.baseline == "explicit_texture":
        from ..baseline import fit_baseline

        return fit_baseline(subject, cfg, Path(run_dir))
    return Trainer(subject, cfg, run_dir).run(resume)
