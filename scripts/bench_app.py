#!/usr/bin/env python
"""``elicit app`` against the command line: the same avatar, and the wall time of one job from upload to viewer.

On the demo subject's input photo and mask (what ``elicit demo`` synthesises), with the default preset and
nothing set:
1. the app: ``elicit app`` on a free port, driven by Playwright in the system's Chromium; the clock runs from the
   upload to the 3D viewer showing the avatar (progress phases recorded on the way);
2. the command line: ``elicit prepare PHOTO --mask MASK`` then ``elicit fit`` (the same seed, the default one),
   twice, since ``prepare``'s body fit is not bit-reproducible (measured; the likely cause is its Mitsuba
   silhouettes on Dr.Jit's thread pool), and ``elicit fit`` on the app's own prepared subject (the fit is).

The avatars are compared tensor by tensor and evaluated with ``elicit eval --align`` against the demo subject.
Writes ``docs/benchmarks/app.{json,md}`` and ``app_viewer.png`` (the viewer's canvas at the end).

    python scripts/bench_app.py [--work runs/bench_app]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    from playwright.sync_api import sync_playwright
    from safetensors.numpy import load_file

    from elicit_diffrender.apps.benchtools import (
        app_job_in_page,
        chromium_page,
        free_port,
        machine_info,
        markdown_table,
        run,
        start_app,
        viewer_coverage,
        write_report,
    )
    from elicit_diffrender.apps.demo import DEMO_MOTION, DEMO_SEED
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.inputs.synth import synthesize
    from elicit_diffrender.model.avatar import AVATAR_FILE

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_app")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = p.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    env = None
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    truth = synthesize(DEMO_SEED, args.work / "demo_subject", motion_name=DEMO_MOTION)
    subject = load_subject(truth)
    photo = subject.image_path(subject.input_camera, subject.input_frame)
    mask = subject.mask_path(subject.input_camera, subject.input_frame)

    # 1. The app, in a browser.
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    jobs = args.work / "app_jobs"
    server = start_app([elicit, "app", "--port", str(port), "--out", str(jobs)], url, args.work / "app.log")
    try:
        with sync_playwright() as playwright:
            page = chromium_page(playwright)
            t0 = time.perf_counter()
            job = app_job_in_page(page, url, photo, mask)
            coverage = viewer_coverage(page, args.out / "app_viewer.png")
            upload_to_viewer = time.perf_counter() - t0
    finally:
        server.terminate()
        server.wait(timeout=60)
    if job["phase"] != "done" or coverage < 0.05:
        raise SystemExit(f"the app's job did not finish (phase {job['phase']}, viewer coverage {coverage:.3f})")
    (app_job,) = [d for d in jobs.iterdir() if (d / "job.json").is_file()]
    record = json.loads((app_job / "job.json").read_text())

    # 2. The command line, twice (``prepare``'s body fit is not bit-reproducible), and ``elicit fit`` on the
    # app's own prepared subject.
    runs, cli_seconds = {"app": app_job / "run"}, []
    for name in ("command line A", "command line B"):
        t0 = time.perf_counter()
        folder = args.work / name.replace(" ", "_")
        run([elicit, "prepare", str(photo), "--mask", str(mask), "--out", str(folder)], env, folder.with_suffix(".log"))
        run([elicit, "fit", str(folder), "--out", str(folder / "run")], env, folder.with_suffix(".fit.log"))
        cli_seconds.append(time.perf_counter() - t0)
        runs[name] = folder / "run"
    runs["fit of the app's subject"] = args.work / "fit_of_app_subject"
    run([elicit, "fit", str(app_job / "subject"), "--out", str(runs["fit of the app's subject"])], env,
        args.work / "fit_of_app_subject.log")  # fmt: skip

    def largest_difference(x: Path, y: Path) -> float | None:
        """The largest absolute difference between two avatars' tensors (None if they hold different tensors)."""
        a, b = load_file(x / AVATAR_FILE), load_file(y / AVATAR_FILE)
        if sorted(a) != sorted(b) or any(a[k].shape != b[k].shape for k in a):
            return None
        return max(float(np.abs(a[k].astype(np.float64) - b[k]).max(initial=0.0)) for k in a)

    differences = {
        "app vs fit of the app's subject": largest_difference(runs["app"], runs["fit of the app's subject"]),
        "app vs command line A": largest_difference(runs["app"], runs["command line A"]),
        "command line A vs B": largest_difference(runs["command line A"], runs["command line B"]),
    }
    metrics = {}
    for name, run_dir in runs.items():
        out = args.work / f"eval_{name.replace(' ', '_').replace(chr(39), '')}.json"
        run([elicit, "eval", str(run_dir), str(truth), "--align", "--out", str(out)], env, out.with_suffix(".log"))
        nv = json.loads(out.read_text())["novel_view"]
        metrics[name] = {"psnr": nv["psnr"], "ssim": nv["ssim"], "rear_psnr": nv["rear"]["psnr"]}

    cli = [metrics["command line A"], metrics["command line B"]]
    spread = {k: abs(cli[0][k] - cli[1][k]) for k in cli[0]}
    app_gap = {k: min(abs(metrics["app"][k] - c[k]) for c in cli) for k in cli[0]}
    data = {
        "machine": machine_info(__import__("torch").device("cpu")),
        "subject": f"the demo subject (seed {DEMO_SEED})'s input photo {photo.name} with its mask, preset cpu-fast",
        "app": {
            "upload_to_viewer_s": upload_to_viewer,
            "job_s": record.get("seconds"),
            "fit_s": record.get("fit_seconds"),
            "prepare_iou": record.get("prepare_iou"),
            "progress_fractions": job["fractions"],
            "viewer_coverage": coverage,
        },
        "command_line_prepare_and_fit_s": cli_seconds,
        "largest_tensor_difference": differences,
        "metrics": metrics,
        "command_line_spread": spread,
        "app_to_nearest_command_line": app_gap,
    }
    rows = [{"avatar": name, **m} for name, m in metrics.items()]
    md = "\n".join(
        [
            "# `elicit app` against `elicit prepare` + `elicit fit`",
            "",
            f"{data['subject']}; one job at a time on this machine ({data['machine']['cpu_count']} CPUs).",
            "",
            f"- Upload to the avatar in the page's 3D viewer: **{upload_to_viewer:.0f} s** (the job itself "
            f"{record.get('seconds', 0):.0f} s: prepare, fit {record.get('fit_seconds') or 0:.0f} s, turntable and "
            "animation, textured GLB).",
            f"- Command line, prepare + fit only: {cli_seconds[0]:.0f} s and {cli_seconds[1]:.0f} s.",
            "- Largest absolute difference between the avatars' tensors: "
            + "; ".join(f"{k}: {'different tensors' if v is None else f'{v:.3g}'}" for k, v in differences.items()),
            f"- Metrics: the app's avatar is within {max(app_gap.values()):.3g} of the nearer command-line run; "
            f"the two command-line runs differ by up to {max(spread.values()):.3g} (PSNR in dB, SSIM, rear PSNR).",
            "",
            markdown_table(
                rows,
                [("avatar", "avatar"), ("psnr", "novel-view PSNR"), ("ssim", "SSIM"), ("rear_psnr", "rear PSNR")],
            ),
            "",
        ]
    )
    write_report(args.out, "app", data, md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
