"""``elicit batch``: many avatars, one Ray task per photo or subject folder.

Each input becomes a job folder ``OUT/<name>/`` laid out as the single commands write it:

    subject/            ``elicit prepare`` of a photo (a subject folder input is used where it is)
    run/                ``elicit fit`` (a killed fit resumes from its checkpoint)
    turntable.mp4, animation.mp4, contact_sheet.png     what ``elicit demo`` shows of an avatar
    avatar.glb          ``elicit export``
    job.json            status, error, steps done, prepare IoU, fit seconds, node

and ``OUT/summary.json`` with ``OUT/summary.md`` list every job. A step whose result exists is
skipped, so a rerun does no finished work and retries what failed. Without an address the batch
starts an embedded local Ray; each task asks for ``cpus_per_fit`` CPUs and the memory of one fit,
so Ray runs as many at once as the machine fits, and each sizes its thread pools to its CPUs
(Ray sets ``OMP_NUM_THREADS``, :func:`~elicit_diffrender.core.device.cpus_given` reads it). With an
address it joins that cluster and ships this package in Ray's runtime environment; the nodes
need the dependencies installed and must see the input and output paths (a shared file system).
"""

from __future__ import annotations

import logging
import re
import shutil
import signal
import socket
import tempfile
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from ..core.checks import inside
from ..core.errors import ElicitError, error_line
from ..core.io import read_json, write_json, write_text
from ..inputs.prepare import MASK_SUFFIX, mask_beside

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")
STEPS = ("prepare", "fit", "render", "export")
FIT_MEMORY = 3 * 1024**3  # bytes a cpu-fast fit may need (peak measured 1.9 GB): Ray packs tasks by it
JOB_FILE = "job.json"


class BatchError(ElicitError):
    """Batch inputs or options that cannot run."""


@dataclass(frozen=True)
class Job:
    name: str
    source: Path  # a photo, an elicit-subject/1 folder, or (--per-folder) a folder of photos of one person
    photos: tuple[Path, ...] = ()  # the photos ``prepare`` turns into the job's subject (none: a subject)
    masks: tuple[Path | None, ...] = ()  # each photo's person mask, if one lies beside it

    @property
    def is_photo(self) -> bool:
        return bool(self.photos)

    def stamp(self) -> str:
        """Sizes and modification times of the inputs (a subject's ``subject.json``): it changes when an
        input is replaced."""
        files = self.photos or (self.source / "subject.json",)
        return "+".join(f"{info.st_size}-{info.st_mtime_ns}" for info in (f.stat() for f in files))


def _is_subject(path: Path) -> bool:
    return (path / "subject.json").is_file()


def _is_photo(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in PHOTO_SUFFIXES and not path.stem.endswith(MASK_SUFFIX)


def job_name(stem: str) -> str:
    """A job folder's name from an input's name: letters, digits, '.', '_' and '-' kept, anything else '_', no
    leading dots (a photo named ``...png`` must not become the job ``..``, the folder above ``--out``)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip(".") or "job"


def _photo_job(path: Path) -> Job:
    return Job(job_name(path.stem), path, (path,), (mask_beside(path),))


def find_jobs(inputs: list[Path], per_folder: bool = False) -> list[Job]:
    """One job per photo or subject folder; a folder of them gives one job for each (not recursive). With
    ``per_folder``, a folder of photos is one person: one job prepares them all into one multi-photo subject."""
    jobs: list[Job] = []
    for path in inputs:
        if _is_photo(path):
            jobs.append(_photo_job(path))
        elif path.is_dir() and _is_subject(path):
            jobs.append(Job(job_name(path.name), path))
        elif per_folder and path.is_dir() and (photos := sorted(p for p in path.iterdir() if _is_photo(p))):
            jobs.append(Job(job_name(path.name), path, tuple(photos), tuple(mask_beside(p) for p in photos)))
        elif path.is_dir():
            found = [
                _photo_job(p) if p.is_file() else Job(job_name(p.name), p)
                for p in sorted(path.iterdir())
                if _is_photo(p) or (p.is_dir() and _is_subject(p))
            ]
            if not found:
                raise BatchError(f"{path}: no photos ({', '.join(PHOTO_SUFFIXES)}) or subject folders in it")
            jobs += found
        elif not path.exists():
            raise BatchError(f"{path}: no such file or folder")
        else:
            raise BatchError(f"{path}: not a photo ({', '.join(PHOTO_SUFFIXES)}), a subject folder or a folder of them")
    seen: dict[str, Path] = {}
    for job in jobs:
        if job.name in seen:
            raise BatchError(f"{job.source} and {seen[job.name]} would share the job folder {job.name!r}: rename one")
        seen[job.name] = job.source
    return jobs


def _read_json(path: Path) -> dict:
    """A job's own JSON file ({} when it is missing or damaged: the step that writes it runs again)."""
    try:
        data = read_json(path)
    except ElicitError:
        return {}
    return data if isinstance(data, dict) else {}


def parse_steps(text: str) -> tuple[str, ...]:
    steps = tuple(s.strip() for s in text.split(",") if s.strip())
    unknown = [s for s in steps if s not in STEPS]
    if unknown or not steps:
        raise BatchError(f"--steps: expected a comma-separated subset of {','.join(STEPS)}, got {text!r}")
    return tuple(s for s in STEPS if s in steps)


def read_record(job_dir: Path) -> dict:
    """A job folder's ``job.json`` ({} when there is none yet)."""
    return _read_json(job_dir / JOB_FILE)


def is_finished(job: Job, job_dir: Path, steps: tuple[str, ...]) -> bool:
    """Done with these steps, or failed on this very input (a bad photo fails again until it is replaced;
    a job whose worker died has no stamp and runs again)."""
    record = read_record(job_dir)
    if record.get("status") == "done":
        wanted = set(steps) - (set() if job.is_photo else {"prepare"})
        return wanted <= set(record.get("steps_done", []))
    return record.get("status") == "failed" and record.get("input_stamp") == job.stamp()


def run_job(job: Job, job_dir: Path, steps: tuple[str, ...], config: dict, render_size: int) -> dict:
    """Run one job's steps in this process, skipping those whose results exist; never raises: a failure
    is the job's ``status`` and one-line ``error`` (the traceback of an unexpected one in ``error.txt``)."""
    from ..data.subject import load_subject
    from ..fit.checkpoint import CHECKPOINT
    from ..fit.config import FitConfig
    from ..fit.run import fit
    from ..inputs.prepare import prepare
    from ..model.avatar import AVATAR_FILE
    from ..model.load import load_avatar
    from ..outputs.export import export_run
    from ..outputs.video import write_showcase

    job_dir.mkdir(parents=True, exist_ok=True)
    record = read_record(job_dir)
    done = [s for s in record.get("steps_done", []) if s in STEPS]
    record.update(name=job.name, source=str(job.source), status="running", error=None, node=socket.gethostname())
    record["input_stamp"] = job.stamp()
    write_json(job_dir / JOB_FILE, record)  # a job killed from here on reads "running" and runs again
    subject_dir = job_dir / "subject" if job.is_photo else job.source
    run_dir = job_dir / "run"
    t0 = time.perf_counter()
    try:
        if job.is_photo and not (subject_dir / "subject.json").is_file():
            if "prepare" not in steps:
                raise BatchError(f"{job.source}: a photo needs the prepare step (no {subject_dir} yet)")
            prepare(list(job.photos), subject_dir, list(job.masks), force=True)
        if job.is_photo:
            record["prepare_iou"] = _read_json(subject_dir / "fit_report.json").get("silhouette_iou")
            done.append("prepare")
        subject = None
        if "fit" in steps:
            if not (run_dir / AVATAR_FILE).is_file():
                subject = load_subject(subject_dir)
                fit(subject, FitConfig(**config).validate(), run_dir, resume=(run_dir / CHECKPOINT).is_file())
            seconds = _read_json(run_dir / "run.json").get("seconds")
            record["fit_seconds"] = seconds.get("total") if isinstance(seconds, dict) else None
            done.append("fit")
        if "render" in steps:
            if not (job_dir / "contact_sheet.png").is_file():
                write_showcase(load_avatar(run_dir), subject or load_subject(subject_dir), job_dir, render_size)
            done.append("render")
        if "export" in steps:
            if not (job_dir / "avatar.glb").is_file():
                export_run(run_dir, job_dir / "avatar.glb")
            done.append("export")
        record["status"] = "done"
    except (ElicitError, OSError) as exc:
        record.update(status="failed", error=error_line(exc))
    except Exception as exc:  # noqa: BLE001 - an unexpected failure ends this job, not the batch
        record.update(status="failed", error=f"{type(exc).__name__}: {error_line(exc)} (traceback in error.txt)")
        write_text(job_dir / "error.txt", traceback.format_exc())
    record["steps_done"] = [s for s in STEPS if s in done]
    record["seconds"] = time.perf_counter() - t0
    write_json(job_dir / JOB_FILE, record)
    return record


def stage_package(into: Path) -> Path:
    """A copy of this package as imported (kernels and scenes inside it, whatever the install layout),
    for Ray's ``py_modules``."""
    import importlib

    import elicit_diffrender

    dest = into / "elicit_diffrender"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(Path(elicit_diffrender.__file__).parent, dest, ignore=ignore)
    for sub in ("kernels", "scenes"):
        src = Path(importlib.import_module(f"elicit_diffrender.{sub}").__file__).parent
        shutil.copytree(src, dest / sub, ignore=ignore, dirs_exist_ok=True)
    return dest


def start_ray(address: str | None, stage_dir: Path) -> None:
    """An embedded local Ray sized to this process's CPUs, or a connection to the cluster at ``address``
    with this package shipped in the runtime environment."""
    import ray

    from ..core.device import cpus_given

    quiet = {"log_to_driver": False, "logging_level": logging.ERROR}
    on_sigterm = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    if address is None:
        ray.init(
            address="local", num_cpus=cpus_given(), include_dashboard=False, object_store_memory=256 * 1024**2, **quiet
        )
    else:
        ray.init(address=address, runtime_env={"py_modules": [str(stage_package(stage_dir))]}, **quiet)
    if callable(on_sigterm):  # Ray's own handler would end the driver without stopping its agents
        signal.signal(signal.SIGTERM, on_sigterm)


def job_task(cpus_per_fit: int):
    """:func:`run_job` as a Ray task (Ray started) that asks for ``cpus_per_fit`` CPUs and the memory of one fit."""
    import ray

    memory = min(FIT_MEMORY, int(ray.cluster_resources().get("memory", FIT_MEMORY)))
    return ray.remote(run_job).options(num_cpus=cpus_per_fit, memory=memory, max_retries=1)


def finish_task(ref, job_dir: Path) -> dict:
    """The record of a job whose task ended; a worker that died (killed, out of memory) fails its job here."""
    import ray

    try:
        ray.get(ref)
    except ray.exceptions.RayError as exc:
        record = read_record(job_dir) | {"status": "failed", "error": error_line(exc)}
        record.pop("input_stamp", None)
        write_json(job_dir / JOB_FILE, record)
    return read_record(job_dir)


def job_row(job: Job, job_dir: Path, out: Path) -> dict:
    """A job's line in the summary: its record, and links (relative to ``out``) to what exists."""
    record = read_record(job_dir)
    row = {
        "name": job.name,
        "source": str(job.source),
        "status": record.get("status", "pending"),
        "error": record.get("error"),
        "prepare_iou": record.get("prepare_iou"),
        "fit_seconds": record.get("fit_seconds"),
        "node": record.get("node"),
    }
    for key, name in (("video", "turntable.mp4"), ("contact_sheet", "contact_sheet.png"), ("avatar", "avatar.glb")):
        row[key] = str((job_dir / name).relative_to(out)) if (job_dir / name).is_file() else None
    return row


def write_summary(out: Path, rows: list[dict], seconds: float) -> dict:
    """``summary.json`` and ``summary.md`` of a batch."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "failed", "pending", "running")}
    summary = {"jobs": rows, "counts": counts, "seconds": seconds}
    write_json(out / "summary.json", summary)

    def cell(value, fmt="{}"):
        return "" if value is None else fmt.format(value)

    lines = [
        f"# Batch: {counts['done']} done, {counts['failed']} failed of {len(rows)}",
        "",
        "| job | status | prepare IoU | fit (s) | video | contact sheet | avatar | error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        links = [f"[{k}]({r[k]})" if r[k] else "" for k in ("video", "contact_sheet", "avatar")]
        error = cell(r["error"]).replace("|", "\\|")
        lines.append(
            f"| {r['name']} | {r['status']} | {cell(r['prepare_iou'], '{:.3f}')} | {cell(r['fit_seconds'], '{:.0f}')} "
            f"| {' | '.join(links)} | {error} |"
        )
    write_text(out / "summary.md", "\n".join(lines) + "\n")
    return summary


def show(bar, rows: dict[str, dict], running: int) -> None:
    """The progress bar's done / failed / running counts."""
    count = {s: sum(r["status"] == s for r in rows.values()) for s in ("done", "failed")}
    bar.set_postfix(done=count["done"], failed=count["failed"], running=running)


def run_batch(
    inputs: list[Path],
    out: Path,
    steps: tuple[str, ...],
    config: dict,
    address: str | None = None,
    cpus_per_fit: int = 1,
    render_size: int = 256,
    per_folder: bool = False,
) -> dict:
    """Run every job that is not finished on Ray, with a progress bar; returns the summary (``per_folder``: a
    folder of photos is one person's, see :func:`find_jobs`)."""
    from tqdm import tqdm

    from ..core.device import cpus_given

    t0 = time.perf_counter()
    try:
        jobs, out = find_jobs([p.resolve() for p in inputs], per_folder), out.resolve()  # the same paths on every node
    except (RuntimeError, OSError) as exc:  # a symbolic link loop, an unreadable folder
        raise BatchError(f"cannot read the inputs or --out ({exc})") from None
    for job in jobs:  # every job folder lies strictly inside --out
        inside(out, job.name, f"job {job.name!r} ({job.source})", BatchError)
    if address is None and cpus_per_fit > cpus_given():
        raise BatchError(f"--cpus-per-fit {cpus_per_fit}: this machine gives this process {cpus_given()} CPUs")
    out.mkdir(parents=True, exist_ok=True)
    todo = [job for job in jobs if not is_finished(job, out / job.name, steps)]
    rows = {job.name: job_row(job, out / job.name, out) for job in jobs}
    for job in todo:
        rows[job.name].update(status="pending", error=None)
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="batch", unit="job")
    if todo:
        import ray

        with tempfile.TemporaryDirectory() as stage:
            start_ray(address, Path(stage))
            try:
                slots = max(1, int(ray.cluster_resources().get("CPU", 1) // cpus_per_fit))
                task = job_task(cpus_per_fit)
                pending = {task.remote(job, out / job.name, steps, config, render_size): job for job in todo}
                show(bar, rows, min(len(pending), slots))
                while pending:
                    ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)  # a signal is handled between
                    if not ready:
                        continue
                    (ref,) = ready
                    job = pending.pop(ref)
                    finish_task(ref, out / job.name)
                    rows[job.name] = job_row(job, out / job.name, out)
                    show(bar, rows, min(len(pending), slots))
                    bar.update(1)
                    write_summary(out, list(rows.values()), time.perf_counter() - t0)
            finally:
                ray.shutdown()
    show(bar, rows, 0)
    bar.close()
    return write_summary(out, list(rows.values()), time.perf_counter() - t0)
