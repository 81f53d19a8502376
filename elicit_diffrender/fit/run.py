"""A fit run: the run folder (continue, replace or refuse), its log, and the trainer or the baseline."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from ..core.device import size_thread_pools
from ..data.subject import Subject
from ..model.avatar import AVATAR_FILE, LEGACY_FILE
from .baseline import fit_baseline
from .checkpoint import CHECKPOINT, FitError
from .config import FitConfig
from .trainer import Trainer


def setup_logging(run_dir: Path) -> None:
    """Log to ``run_dir/log.txt`` and the terminal."""
    run_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(run_dir / "log.txt")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger("elicit")
    root.setLevel(logging.INFO)
    root.handlers = [handler, logging.StreamHandler()]


RESULTS = (CHECKPOINT, AVATAR_FILE, LEGACY_FILE, "run.json")  # what marks a folder as holding a fit
LEFTOVERS = ("log.txt", "previews")  # what a fit writes besides


def prepare_run_folder(run_dir: Path, resume: bool, force: bool) -> None:
    """Check (or, with ``force``, clear) the run folder: a folder that holds an earlier fit is continued only
    with ``resume`` and overwritten only with ``force``; temporary files of a killed save are removed."""
    held = [name for name in RESULTS if (run_dir / name).exists()]
    if force and not resume:
        for path in (run_dir / name for name in RESULTS + LEFTOVERS):
            if path.is_dir():
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
    elif held and not resume:
        raise FitError(
            f"{run_dir} holds an earlier fit ({', '.join(held)}): pass --resume to continue it, "
            "--force to replace it, or use a new --out"
        )
    for stale in run_dir.glob(f".{CHECKPOINT}.*") if run_dir.is_dir() else []:  # a save killed midway
        stale.unlink()


def fit(subject: Subject, cfg: FitConfig, run_dir: str | Path, resume: bool = False, force: bool = False) -> dict:
    """Fit an avatar to ``subject`` (or the baseline that ``cfg.baseline`` names); returns the run report
    (also written to ``run_dir/run.json``). See :func:`prepare_run_folder` for ``resume`` and ``force``."""
    prepare_run_folder(Path(run_dir), resume, force)
    setup_logging(Path(run_dir))
    logging.getLogger("elicit.fit").info("thread pools sized to %d CPUs", size_thread_pools())
    if cfg.baseline == "explicit_texture":
        return fit_baseline(subject, cfg, Path(run_dir))
    return Trainer(subject, cfg, run_dir).run(resume)
