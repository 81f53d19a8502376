"""Helpers for the benchmark scripts: timing, peak memory, fit-and-eval jobs, JSON + markdown reports."""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import statistics
import subprocess
import tarfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from ..core.io import write_json, write_text

ROOT_DIR = Path(__file__).resolve().parents[2]  # the project's checkout
# The synthetic subjects of the quality benchmarks: (seed, training motion).
SYNTHETIC_SUBJECTS = [(1, "walk_in_place"), (2, "wave"), (3, "squat")]
# Beside the seeds, the photo-path benchmark's people: clothes and postures of real people (``inputs/people.py``),
# and the openly licensed scans of ``../shared/scans`` (CC BY 4.0), each (its file there, ``to_obj.py`` options).
PHOTO_PEOPLE = (
    "open_jacket_tie", "front_details", "held_folder", "arms_crossed", "hands_in_pockets", "short_dark_hair",
    "long_hair", "dark_suit", "seated", "legs_crossed", "arms_raised", "arms_forward",
)  # fmt: skip
SCANS = {
    "carla": ("carla/carla.idle.opt.glb", []),
    "f3": ("f3/f3.idle.opt.glb", []),
    "man_in_suit": ("man_in_suit/scene.gltf", ["--hide", "high-poly:0.85,0,1,0.15"]),
}
SCAN_CREDITS = {  # the credit lines the licence asks for wherever their renders or results are shown
    "carla": '"Carla Rigged 001" by renderpeople, CC BY 4.0 (sketchfab.com/3d-models/carla-rigged-001-rigged-3d-'
    "business-women-acf520f450d14dd799f98a6fede3edf5)",
    "f3": '"Rigged Standing Asian Female Character Idle Pose" by florah, CC BY 4.0 (sketchfab.com/3d-models/rigged-'
    "standing-asian-female-character-idle-pose-b31b024797194829af4637fbfb6838b7)",
    "man_in_suit": '"Man Dressed In Suit" by 3d-character-br, CC BY 4.0 (sketchfab.com/3d-models/man-dressed-in-suit-'
    "ae103052b58a450397f42a189aa726b7)",
}
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
    elicit: str | list[str],
    subject: Path,
    run_dir: Path,
    overrides: list[str],
    env: dict,
    truth: Path | None = None,
    eval_args: Sequence[str] = (),
) -> dict:
    """``elicit fit`` on ``subject`` and ``elicit eval`` against ``truth`` (default: the same subject);
    a finished job (its ``metrics.json``) is reused and a killed fit resumed. ``elicit`` is the command (a path,
    or a list such as :func:`elicit_command`'s)."""
    from ..fit.checkpoint import CHECKPOINT
    from ..model.avatar import AVATAR_FILE

    metrics = run_dir / "metrics.json"
    elicit = [elicit] if isinstance(elicit, str) else list(elicit)
    if not metrics.is_file():
        sets = [x for kv in overrides for x in ("--set", kv)]
        resume = ["--resume"] if (run_dir / CHECKPOINT).is_file() else []
        if not (run_dir / AVATAR_FILE).is_file():
            run([*elicit, "fit", str(subject), "--out", str(run_dir), *sets, *resume], env, run_dir / "fit.log")
        target = str(truth or subject)
        run([*elicit, "eval", str(run_dir), target, "--out", str(metrics), *eval_args], env, run_dir / "eval.log")
    return json.loads(metrics.read_text())


def mean(values: list) -> float | None:
    """The mean of the values that are not None (None if there are none)."""
    values = [v for v in values if v is not None]
    return sum(values) / len(values) if values else None


def add_job_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """The options every fit-and-eval benchmark takes: --quick, --jobs, --work (``runs/NAME``), --out, --set."""
    root = ROOT_DIR
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


def benchmark_people(scans: Path | None, quick: bool = False) -> list[str]:
    """The photo-path subjects beyond the seeds: the named people, then the scans found under ``scans``."""
    found = [name for name, (path, _) in SCANS.items() if scans is not None and (scans / path).is_file()]
    return [PHOTO_PEOPLE[0], *found[:1]] if quick else [*PHOTO_PEOPLE, *found]


def synthesize_person(elicit: str, work: Path, name: str, motion: str, env: dict, scans: Path | None) -> Path:
    """``work/subject_NAME``: ``elicit synth --person NAME``, or a scan converted to OBJ by the scans' own
    ``to_obj.py`` and rendered with ``elicit synth --mesh``; kept when it is already there."""
    import sys

    path = work / f"subject_{name}"
    if (path / "subject.json").is_file():
        return path
    if name in SCANS:
        if scans is None:
            raise RuntimeError(f"{name} is a scan: pass --scans (the folder of ../shared/scans)")
        source, options = SCANS[name]
        mesh = work / "scans" / name
        if not (mesh / "scan.obj").is_file():
            run([sys.executable, str(scans / "to_obj.py"), str(scans / source), str(mesh), *options], env,
                work / f"to_obj_{name}.log")  # fmt: skip
        cmd = [elicit, "synth", "--mesh", str(mesh / "scan.obj"), "--motion", motion, "--out", str(path)]
    else:
        cmd = [elicit, "synth", "--person", name, "--motion", motion, "--out", str(path)]
    run(cmd, env, work / f"synth_{name}.log")
    return path


def export_commit(commit: str, dest: Path) -> str:
    """The commit's tree in ``dest`` (with the package's ``kernels`` and ``scenes`` linked in); its full hash."""
    full = subprocess.run(["git", "rev-parse", commit], cwd=ROOT_DIR, capture_output=True, text=True, check=True)
    sha = full.stdout.strip()
    stamp = dest / ".commit"
    if not (stamp.is_file() and stamp.read_text() == sha):
        archive = subprocess.run(["git", "archive", sha], cwd=ROOT_DIR, capture_output=True, check=True).stdout
        dest.mkdir(parents=True, exist_ok=True)
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(dest, filter="data")
        for name in ("kernels", "scenes"):
            link = dest / "elicit_diffrender" / name
            if not link.exists():
                link.symlink_to(Path("..") / name)
        stamp.write_text(sha)
    return sha


def elicit_command(code: Path) -> list[str]:
    """The ``elicit`` command of the code in ``code`` (run it with ``PYTHONPATH=code``): the command line moved
    from ``elicit_diffrender/cli.py`` to ``apps/cli.py`` when the package was grouped by layer. ``-P`` keeps the
    working folder (a checkout of other code) off the module path."""
    import sys

    layered = (code / "elicit_diffrender" / "apps" / "cli.py").is_file()
    return [sys.executable, "-P", "-m", "elicit_diffrender.apps.cli" if layered else "elicit_diffrender.cli"]


# ---- ``elicit app`` in a browser (its test and its benchmark) ---------------------------------------------------
def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_app(cmd: list[str], url: str, log: Path, timeout: float = 180.0) -> subprocess.Popen:
    """Start ``elicit app`` (``cmd``) with its output in ``log`` and wait until ``url`` answers."""
    import urllib.request

    with open(log, "w") as stream:
        server = subprocess.Popen(cmd, stdout=stream, stderr=subprocess.STDOUT)
    deadline = time.time() + timeout
    while True:
        try:
            urllib.request.urlopen(url, timeout=2).read()
            return server
        except OSError:
            if server.poll() is not None or time.time() > deadline:
                server.kill()
                raise RuntimeError(f"elicit app did not start: {log.read_text()[-2000:]}") from None
            time.sleep(1)


def chromium_page(playwright, viewport: tuple[int, int] = (1400, 1300)):
    """A page in the system's Chromium (software WebGL), for Playwright (which downloads no browser here)."""
    import shutil

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise RuntimeError("chromium is missing: run scripts/setup.sh (it installs Debian's chromium)")
    args = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    launched = playwright.chromium.launch(executable_path=browser, args=args)
    return launched.new_page(viewport={"width": viewport[0], "height": viewport[1]}, accept_downloads=True)


def app_job_in_page(page, url: str, photo: Path, mask: Path | None, timeout: float = 900.0) -> dict:
    """Upload a photo (and its mask) on the app's page, start the job and follow its progress bar to the end;
    returns the bar's fractions as they changed, the last phase, the status line and the seconds from upload."""
    t0 = time.perf_counter()
    page.goto(url)
    page.locator("#photos input[type=file]").set_input_files(str(photo))
    if mask is not None:
        page.locator("#masks input[type=file]").set_input_files(str(mask))
        page.locator(f"#masks td.filename[aria-label='{mask.name}']").wait_for()
    page.locator(f"#photos td.filename[aria-label='{photo.name}']").wait_for()
    page.locator("#start").click()
    fractions: list[float] = []
    phase = ""
    while time.perf_counter() - t0 < timeout and phase not in ("done", "failed", "not started"):
        bar = page.locator("#job-progress")
        fraction, phase = float(bar.get_attribute("data-fraction")), bar.get_attribute("data-phase")
        if not fractions or fraction != fractions[-1]:
            fractions.append(fraction)
        time.sleep(0.5)
    return {"fractions": fractions, "phase": phase, "seconds": time.perf_counter() - t0}


def viewer_coverage(page, shot: Path, timeout: float = 120.0) -> float:
    """Wait until the app's 3D viewer draws something in the middle of its canvas; the share of pixels there that
    differ from the background (0 if nothing shows within ``timeout``). Saves the canvas to ``shot``."""
    import imageio.v3 as iio
    import numpy as np

    from .webapp import VIEWER_BACKGROUND

    background = np.round(255 * np.array(VIEWER_BACKGROUND[:3]))
    canvas = page.locator("#viewer canvas")
    canvas.wait_for(timeout=timeout * 1000)
    deadline, coverage = time.time() + timeout, 0.0
    while time.time() < deadline and coverage < 0.05:
        image = iio.imread(canvas.screenshot(path=str(shot)))[..., :3].astype(int)
        h, w = image.shape[:2]
        centre = image[h // 4 : 3 * h // 4, w // 3 : 2 * w // 3]
        coverage = float((np.abs(centre - background).max(-1) > 30).mean())
        time.sleep(0.5)
    return coverage
