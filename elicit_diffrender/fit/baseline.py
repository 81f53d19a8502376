"""The paper's "body mesh with explicit texture" baseline as a fit: a closed-form fit, saved like an avatar."""

from __future__ import annotations

import logging
import resource
import time
from pathlib import Path

from ..core.io import write_json
from ..data.subject import Subject
from ..model.avatar import AVATAR_FILE
from ..model.textured_body import TexturedBody
from .config import FitConfig, config_dict


def fit_baseline(subject: Subject, cfg: FitConfig, run_dir: Path) -> dict:
    """Fit the baseline to ``subject``, save it in ``run_dir``; returns the run report (also run.json)."""
    t0 = time.perf_counter()
    path = TexturedBody.fit(subject).save(run_dir / AVATAR_FILE)
    logging.getLogger("elicit.fit").info("baseline explicit_texture: per-vertex colours from the input view")
    report = {
        "subject": str(subject.root),
        "avatar": str(path),
        "config": config_dict(cfg),
        "encoder": None,
        "perceptual": {"name": "none (closed-form fit)", "reason": ""},
        "seconds": {"total": time.perf_counter() - t0},
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    write_json(run_dir / "run.json", report)
    return report
