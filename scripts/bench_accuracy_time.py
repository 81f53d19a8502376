#!/usr/bin/env python
"""What accuracy costs in time: sweep the knobs of the fit, and of the ray-marching kernel.

Fit sweep: one knob at a time around ``cpu-fast`` (grid resolution, samples per ray, early
termination, occupancy skipping, crop resolution, stage-2 iterations, semantic encoder), plus the
``paper`` preset on a reduced budget. Each point is a full ``elicit fit`` on the demo subject (seed 0),
measured by novel-view PSNR/SSIM against fit wall time and render time per 256x256 frame. Runs
are sequential (fit times are wall times on this machine) and resumable.

Kernel sweep: float32 ray marching (samples per ray x early-termination threshold) against a float64
reference with 1024 samples and no early stop, versus time per forward pass.

Writes ``docs/benchmarks/accuracy_time.{json,md,png}`` with the Pareto front and the presets marked.

    python scripts/bench_accuracy_time.py [--quick]   # --quick: kernel sweep + 4 fit points
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from elicit_diffrender.apps.benchtools import PSNR_TIE_DB
from elicit_diffrender.fit.checkpoint import CHECKPOINT
from elicit_diffrender.model.avatar import AVATAR_FILE

ROOT = Path(__file__).resolve().parents[1]
BASE = "cpu-fast"
SWEEP: dict[str, list[str]] = {  # the most telling points first
    "cpu-fast": [],
    "24 samples": ["samples_per_ray=24"],
    "1000 steps": ["steps=1000"],
    "voxel 2.4 cm": ["voxel_size=0.024"],
    "no occupancy skipping": ["occupancy_cell=0"],
    "no early stop": ["t_thresh=0"],
    "crop 64": ["crop_size=64"],
    "crop 32": ["crop_size=32"],
    "no semantic encoder": ["w_semantic=0"],
    "96 samples": ["samples_per_ray=96"],
    "voxel 1.2 cm": ["voxel_size=0.012"],
    "early stop 1e-2": ["t_thresh=0.01"],
    "6000 steps": ["steps=6000"],
    "paper preset, reduced budget": [
        "@paper",
        "init_steps=150",
        "steps=300",
        "checkpoint_every=100",
        "preview_every=100",
        "guard_every=100",
    ],
}
QUICK = ("cpu-fast", "24 samples", "1000 steps", "voxel 2.4 cm")
DROPS_A_PRIOR = ("no semantic encoder",)  # points that leave out one of the method's two priors
ALL_METRICS = ("psnr", "ssim", "pose_psnr")  # novel-view PSNR and SSIM, novel-pose PSNR
# Differences smaller than these are ties. The report checks them against the points that should not
# change the result (2026-11-23: up to 0.034 dB, 0.0004 and 0.05 dB from cpu-fast).
TOLERANCE = {"psnr": PSNR_TIE_DB, "ssim": 0.001, "pose_psnr": 0.1}
NULL_CHANGES = ("no occupancy skipping", "no early stop")  # speed knobs that should not change the images


def run(cmd: list[str], log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        if subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed; see {log}")


def fit_point(elicit: str, subject: Path, run_dir: Path, overrides: list[str]) -> dict:
    preset = BASE
    sets = []
    for kv in overrides:
        if kv.startswith("@"):
            preset = kv[1:]
        else:
            sets += ["--set", kv]
    metrics = run_dir / "metrics.json"
    if not metrics.is_file():
        if not (run_dir / AVATAR_FILE).is_file():
            resume = ["--resume"] if (run_dir / CHECKPOINT).is_file() else []
            run(
                [elicit, "fit", str(subject), "--out", str(run_dir), "--preset", preset, *sets, *resume],
                run_dir / "fit.log",
            )
        run([elicit, "eval", str(run_dir), str(subject), "--out", str(metrics)], run_dir / "eval.log")
    m = json.loads(metrics.read_text())
    timing = run_dir / "render_time.json"
    if not timing.is_file():
        from elicit_diffrender.data.subject import load_subject
        from elicit_diffrender.model.load import load_avatar

        s = load_subject(subject)
        avatar = load_avatar(run_dir)
        cam = s.cameras["cam06"].scaled(0.5)
        cfg = json.loads((run_dir / "run.json").read_text())["config"]
        avatar.render_pose(cam, *s.motion.frame(5), cfg["samples_per_ray"])
        t0 = time.perf_counter()
        for _ in range(3):
            avatar.render_pose(cam, *s.motion.frame(5), cfg["samples_per_ray"])
        timing.write_text(json.dumps({"render_s": (time.perf_counter() - t0) / 3}))
    return {
        "psnr": m["novel_view"]["psnr"],
        "ssim": m["novel_view"]["ssim"],
        "pose_psnr": m["novel_pose"]["psnr"],
        "fit_s": m["fit_seconds"],
        "render_s": json.loads(timing.read_text())["render_s"],
    }


def kernel_sweep() -> list[dict]:
    """Float32 ray marching error against a float64, 1024-sample, no-early-stop reference, and its time."""
    import torch

    from elicit_diffrender.apps.benchtools import time_interleaved
    from elicit_diffrender.model.volume import composite, sample_rays

    torch.manual_seed(0)
    res, n_rays = 96, 8192
    box = torch.tensor([[-0.9, -1.0, -0.5], [0.9, 1.0, 0.5]], dtype=torch.float64)
    axes = [torch.linspace(float(box[0, a]), float(box[1, a]), res, dtype=torch.float64) for a in range(3)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    r = ((x / 0.45) ** 2 + (y / 0.85) ** 2 + (z / 0.25) ** 2).sqrt()
    density = (8.0 * (1.0 - r)).contiguous()
    coarse = torch.randn(3, 6, 6, 6, dtype=torch.float64)
    color = torch.nn.functional.interpolate(coarse[None], size=(res,) * 3, mode="trilinear")[0].permute(1, 2, 3, 0)
    color = color.contiguous()
    origins = torch.tensor([0.0, 0.0, -3.0], dtype=torch.float64).repeat(n_rays, 1)
    target = (torch.rand(n_rays, 3, dtype=torch.float64) - 0.5) * torch.tensor([1.9, 2.1, 0.0], dtype=torch.float64)
    dirs = torch.nn.functional.normalize(target - origins, dim=1)
    ref = composite(sample_rays(origins, dirs, box, 1024), density, color, box, t_thresh=0.0)["rgb"]
    rows = []
    d32, c32, o32, v32, b32 = density.float(), color.float(), origins.float(), dirs.float(), box.float()
    for n in (16, 32, 64, 128, 256):
        samples = sample_rays(o32, v32, b32, n)
        for thresh in (0.0, 1e-4, 1e-3, 1e-2):

            def fwd(samples=samples, thresh=thresh):
                with torch.no_grad():
                    return composite(samples, d32, c32, b32, t_thresh=thresh)["rgb"]

            (seconds,) = time_interleaved([fwd], torch.device("cpu"), 5)
            err = (fwd().double() - ref).abs()
            rows.append(
                {
                    "samples": n,
                    "t_thresh": thresh,
                    "forward_ms": seconds * 1e3,
                    "mean_abs_err": float(err.mean()),
                    "max_abs_err": float(err.max()),
                }
            )
    return rows


def pareto(points: list[dict], quality: tuple[str, ...] = ("psnr",)) -> list[str]:
    """Names of the points that no other point beats. ``q`` beats ``p`` when it is no slower, no worse
    than ``p`` by more than the tolerance on any ``quality`` key, and faster or better by more than
    the tolerance on one of them."""

    def beats(q: dict, p: dict) -> bool:
        no_worse = q["fit_s"] <= p["fit_s"] and all(q[k] >= p[k] - TOLERANCE[k] for k in quality)
        return no_worse and (q["fit_s"] < p["fit_s"] or any(q[k] > p[k] + TOLERANCE[k] for k in quality))

    return [p["name"] for p in points if not any(beats(q, p) for q in points)]


def plot(points: list[dict], front: list[str], ringed: list[str], path: Path) -> None:
    """PSNR against fit time; ``front`` joined by a line, ``ringed`` points circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elicit_diffrender.core.io import atomic_write

    fig, ax = plt.subplots(figsize=(10, 5))
    for i, p in enumerate(points, 1):  # numbered points, named in the legend: the cluster stays legible
        on = p["name"] in front
        preset = p["name"] in ("cpu-fast", "paper preset, reduced budget")
        ax.scatter(
            p["fit_s"] / 60,
            p["psnr"],
            s=110 if preset else 45,
            marker="*" if preset else "o",
            color="tab:red" if preset else ("tab:blue" if on else "tab:gray"),
            zorder=3,
            label=f"{i}: {p['name']}",
        )
        if p["name"] in ringed:
            ax.scatter(p["fit_s"] / 60, p["psnr"], s=260, facecolors="none", edgecolors="black", zorder=2)
        ax.annotate(str(i), (p["fit_s"] / 60, p["psnr"]), fontsize=8, xytext=(4, 4), textcoords="offset points")
    fr = sorted([p for p in points if p["name"] in front], key=lambda p: p["fit_s"])
    ax.plot(
        [p["fit_s"] / 60 for p in fr], [p["psnr"] for p in fr], "-", color="tab:blue", label="Pareto front (PSNR, time)"
    )
    ax.set_xlabel("fit wall time on this CPU (min)")
    ax.set_ylabel("novel-view PSNR (dB)")
    ax.scatter(
        [], [], s=260, facecolors="none", edgecolors="black", label="front over all metrics and time (both priors)"
    )
    ax.set_title("What accuracy costs in time (stars: presets)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, dpi=120, format="png"))
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--points", nargs="+", choices=tuple(SWEEP), metavar="NAME", help="only these fit points")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "accuracy_time")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = ap.parse_args()
    from elicit_diffrender.apps.benchtools import markdown_table, write_report

    elicit = str(Path(sys.executable).with_name("elicit"))
    start = time.perf_counter()
    kernel_rows = kernel_sweep()
    subject = args.work / "subject_0"
    if not (subject / "subject.json").is_file():
        run([elicit, "synth", "--seed", "0", "--out", str(subject)], args.work / "synth.log")
    names = args.points or (QUICK if args.quick else tuple(SWEEP))
    points = []
    for name in names:
        print(f"fit point: {name}", flush=True)
        point = fit_point(elicit, subject, args.work / name.replace(" ", "_").replace(",", ""), SWEEP[name])
        points.append({"name": name, "overrides": SWEEP[name], **point})
    method = [p for p in points if p["name"] not in DROPS_A_PRIOR]
    fronts = {  # column -> names on that front
        "front_psnr": pareto(points),
        "front_all_metrics": pareto(points, ALL_METRICS),
        "method_front_psnr": pareto(method),
        "method_front_all_metrics": pareto(method, ALL_METRICS),
    }
    for p in points:
        p.update({col: p["name"] in names for col, names in fronts.items()})
    front = fronts["front_psnr"]
    plot(points, front, fronts["method_front_all_metrics"], args.out / "accuracy_time.png")
    data = {
        "subject": "synthetic seed 0 (the demo subject)",
        "points": points,
        "fronts": fronts,
        "cpu_fast_on": {col: "cpu-fast" in names for col, names in fronts.items()},
        "kernel": kernel_rows,
        "seconds": time.perf_counter() - start,
        "quick": args.quick,
    }
    on_front = [p for p in sorted(points, key=lambda p: p["fit_s"]) if p["front_psnr"]]
    recommend = ", ".join(f"{p['name']} ({p['fit_s'] / 60:.1f} min, {p['psnr']:.2f} dB)" for p in on_front)
    base = next((p for p in points if p["name"] == "cpu-fast"), None)
    nulls = [p for p in points if p["name"] in NULL_CHANGES]
    null_note = (
        f"In this run {' and '.join(p['name'] for p in nulls)}, which should leave the images unchanged, moved "
        + ", ".join(f"{k} by up to {max(abs(p[k] - base[k]) for p in nulls):.4g}" for k in ALL_METRICS)
        + " from cpu-fast."
        if base and nulls
        else ""
    )
    where = ", ".join(f"{col}: {'yes' if on else 'no'}" for col, on in data["cpu_fast_on"].items())
    md = (
        "# Accuracy against time\n\n![PSNR against fit time](accuracy_time.png)\n\n"
        "## Fit sweep (novel-view metrics on the demo subject; one knob at a time around cpu-fast)\n\n"
        "Four Pareto fronts: over all points or only those that keep both of the method's priors (all but "
        f"{', '.join(DROPS_A_PRIOR)}); trading fit time against novel-view PSNR, or against all three "
        "metrics, novel-view PSNR and SSIM and novel-pose PSNR (a point is then beaten only by one that is no "
        "slower and no worse on any of them). Differences within the tolerance "
        f"{TOLERANCE} count as ties. {null_note}\n\n"
        + markdown_table(
            points,
            [
                ("name", "point"),
                ("psnr", "PSNR"),
                ("ssim", "SSIM"),
                ("pose_psnr", "novel-pose PSNR"),
                ("fit_s", "fit s"),
                ("render_s", "render s / 256^2 frame"),
                ("front_psnr", "front: PSNR"),
                ("front_all_metrics", "front: all metrics"),
                ("method_front_psnr", "both priors: PSNR"),
                ("method_front_all_metrics", "both priors: all metrics"),
            ],
        )
        + f"\nPSNR front, fastest first: {recommend}. cpu-fast on each front: {where}.\n\n"
        "## Kernel accuracy against speed (float32 vs float64 reference, 8192 rays, 96^3 grid)\n\n"
        + markdown_table(
            kernel_rows,
            [
                ("samples", "samples/ray"),
                ("t_thresh", "early stop"),
                ("forward_ms", "forward ms"),
                ("mean_abs_err", "mean abs err"),
                ("max_abs_err", "max abs err"),
            ],
        )
    )
    json_path, md_path = write_report(args.out, "accuracy_time", data, md)
    print(md)
    print(f"wrote {json_path}, {md_path} and accuracy_time.png")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main())
