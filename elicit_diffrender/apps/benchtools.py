"""Helpers for the benchmark scripts: timing, peak memory, fit-and-eval jobs, JSON + markdown reports."""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from ..core.io import write_json, write_text

# The synthetic subjects of the quality benchmarks: (seed, training motion).
SYNTHETIC_SUBJECTS = [(1, "walk_in_place"), (2, "wave"), (3, "squat")]
# PSNR differences below this are ties in the benchmark reports: settings that should not change the
# images (occupancy skipping, early stopping) move novel-view PSNR by about this much.
PSNR_TIE_DB = 0.05


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_once(fn: Callable[[], Any], device: torch.device) -> float:
    _sync(device)
    start = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - start


def time_interleaved(fns: Sequence[Callable[[], Any]], device: torch.device, repeats: int = 5) -> list[float]:
    """Median seconds of each function, run in turns so machine noise hits all of them alike."""
    samples: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for i, fn in enumerate(fns):
            samples[i].append(time_once(fn, device))
    return [statistics.median(s) for s in samples]


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def peak_memory(fn: Callable[[], Any], device: torch.device) -> int:
    """Peak extra memory (bytes) while ``fn`` runs: CUDA allocator peak, or sampled RSS on CPU."""
    if device.type == "cuda":
        _sync(device)
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        _sync(device)
        return torch.cuda.max_memory_allocated(device) - base
    base = _rss_bytes()
    peak = [base]
    done = threading.Event()

    def poll() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _rss_bytes())
            time.sleep(0.0005)

    watcher = threading.Thread(target=poll, daemon=True)
    watcher.start()
    try:
        fn()
    finally:
        done.set()
        watcher.join()
    peak[0] = max(peak[0], _rss_bytes())
    return peak[0] - base


def machine_info(device: torch.device) -> dict[str, Any]:
    info = {
        "device": str(device),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),  # the package sets PASSIVE unless the user set it
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str]]) -> str:
    """A markdown table of ``rows`` with (key, header) ``columns``; floats get 4 significant digits."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    lines = ["| " + " | ".join(h for _, h in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(k)) for k, _ in columns) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write_report(out_dir: Path, name: str, data: dict[str, Any], markdown: str) -> tuple[Path, Path]:
    """Write ``name.json`` and ``name.md`` atomically under ``out_dir``."""
    return write_json(out_dir / f"{name}.json", data), write_text(out_dir / f"{name}.md", markdown)


def run(cmd: list[str], env: dict, log: Path) -> None:
    """Run a command with its output in ``log``; raises naming the log when it fails."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        done = subprocess.run(cmd, env=env, stdout=f, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed; see {log}")


def fit_and_eval(
    elicit: str,
    subject: Path,
    run_dir: Path,
    overrides: list[str],
    env: dict,
    truth: Path | None = None,
    eval_args: Sequence[str] = (),
) -> dict:
    """``elicit fit`` on ``subject`` and ``elicit eval`` against ``truth`` (default: the same subject);
    a finished job (its ``metrics.json``) is reused and a killed fit resumed."""
    from ..fit.checkpoint import CHECKPOINT
    from ..model.avatar import AVATAR_FILE

    metrics = run_dir / "metrics.json"
    if not metrics.is_file():
        sets = [x for kv in overrides for x in ("--set", kv)]
        resume = ["--resume"] if (run_dir / CHECKPOINT).is_file() else []
        if not (run_dir / AVATAR_FILE).is_file():
            run([elicit, "fit", str(subject), "--out", str(run_dir), *sets, *resume], env, run_dir / "fit.log")
        target = str(truth or subject)
        run([elicit, "eval", str(run_dir), target, "--out", str(metrics), *eval_args], env, run_dir / "eval.log")
    return json.loads(metrics.read_text())


def mean(values: list) -> float | None:
    """The mean of the values that are not None (None if there are none)."""
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def add_job_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """The options every fit-and-eval benchmark takes: --quick, --jobs, --work (``runs/NAME``), --out, --set."""
    root = Path(__file__).resolve().parents[2]
    parser.add_argument("--quick", action="store_true", help="one subject only")
    parser.add_argument("--jobs", type=int, default=2, help="parallel fits (each single-threaded)")
    parser.add_argument("--work", type=Path, default=root / "runs" / name)
    parser.add_argument("--out", type=Path, default=root / "docs" / "benchmarks")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra overrides for every fit")


def worker_env(jobs: int) -> dict:
    """The environment of benchmark jobs: one CPU thread each when ``jobs`` run side by side."""
    if jobs == 1:
        return dict(os.environ, PYTHONUNBUFFERED="1")
    return dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def synthesize_subjects(elicit: str, work: Path, subjects: Sequence[tuple[int, str]], env: dict) -> None:
    """``elicit synth`` each (seed, motion) into ``work/subject_SEED`` unless it is already there."""
    for seed, motion in subjects:
        path = work / f"subject_{seed}"
        if not (path / "subject.json").is_file():
            cmd = [elicit, "synth", "--seed", str(seed), "--motion", motion, "--out", str(path)]
            run(cmd, env, work / f"synth_{seed}.log")
