"""A fit run: the run folder (continue, replace or refuse), its log, and the trainer or the baseline."""

from __future__ import annotations

import fcntl
import logging
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..core.device import size_thread_pools
from ..data.subject import Subject
from ..model.avatar import AVATAR_FILE, LEGACY_FILE
from .baseline import fit_baseline
from .checkpoint import CHECKPOINT, FitError
from .config import FitConfig
from .trainer import PROGRESS_FILE, Trainer


def setup_logging(run_dir: Path) -> None:
    """Log to ``run_dir/log.txt``; the terminal gets warnings only (every line with ``elicit --verbose``, which sets
    ``ELICIT_WARP_VERBOSE``), so an error stays one line under the progress bar."""
    run_dir.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(run_dir / "log.txt")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    terminal = logging.StreamHandler()
    terminal.setLevel(logging.INFO if os.environ.get("ELICIT_WARP_VERBOSE") else logging.WARNING)
    root = logging.getLogger("elicit")
    root.setLevel(logging.INFO)
    root.handlers = [handler, terminal]


RESULTS = (CHECKPOINT, AVATAR_FILE, LEGACY_FILE, "run.json")  # what marks a folder as holding a fit
LEFTOVERS = ("log.txt", "previews", PROGRESS_FILE)  # what a fit writes besides
SAFETENSORS_TEMP = re.compile(r"\.tmp[A-Za-z0-9]{6}")  # what safetensors writes before renaming it into place
LOCK_FILE = ".lock"  # held (flock) by the fit writing the folder, and holding its process id


@contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold the run folder for one fit: a second fit into it (``--force`` or not) stops with one line naming the
    process that holds it. The lock goes with the process, however it ends."""
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            raise FitError(
                f"{run_dir}: another fit (process {holder}) is writing this folder; wait for it to end or use another "
                "--out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def prepare_run_folder(run_dir: Path, resume: bool, force: bool) -> None:
    """Check (or, with ``force``, clear) the run folder: a folder that holds an earlier fit is continued only
    with ``resume`` and overwritten only with ``force``; temporary files of a killed save are removed."""
    held = [name for name in RESULTS if (run_dir / name).exists()]
    if resume and not (run_dir / CHECKPOINT).is_file():
        raise FitError(f"{run_dir}: nothing to resume (no {CHECKPOINT}); run without --resume to start a fit")
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
    for path in run_dir.iterdir() if run_dir.is_dir() else []:  # the temporary files of a save killed midway
        ours = any(path.name.startswith(f".{name}.") for name in RESULTS)
        if (ours or SAFETENSORS_TEMP.fullmatch(path.name)) and path.is_file() and not path.is_symlink():
            path.unlink()


def fit(subject: Subject, cfg: FitConfig, run_dir: str | Path, resume: bool = False, force: bool = False) -> dict:
    """Fit an avatar to ``subject`` (or the baseline that ``cfg.baseline`` names); returns the run report
    (also written to ``run_dir/run.json``). See :func:`prepare_run_folder` for ``resume`` and ``force``; the folder
    is held (:func:`run_lock`) for the whole fit."""
    with run_lock(Path(run_dir)):
        prepare_run_folder(Path(run_dir), resume, force)
        setup_logging(Path(run_dir))
        logging.getLogger("elicit.fit").info("thread pools sized to %d CPUs", size_thread_pools())
        if cfg.baseline == "explicit_texture":
            return fit_baseline(subject, cfg, Path(run_dir))
        return Trainer(subject, cfg, run_dir).run(resume)
