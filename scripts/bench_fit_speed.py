#!/usr/bin/env python
"""The demo fit's time and quality against a reference commit, both measured in this run on this machine.

The demo subject (seed 0, ``walk_in_place``) is fitted with ``cpu-fast`` by the reference commit's code
(exported with ``git archive`` into the work folder) and by this checkout's, one after the other with the
same threads, and each avatar is evaluated (novel view, novel pose). Writes
``docs/benchmarks/fit_speed.{json,md}``: fit seconds, their ratio, and the quality differences, with the
target (at most half the time; novel-view PSNR / SSIM / novel-pose PSNR within 0.1 dB / 0.002 / 0.2 dB).
Finished fits are reused, so an interrupted run resumes; the time ratio is judged only when both fits ran in
one go (a reused fit and a new one, or two that finished far apart, mix two states of the machine).

    python scripts/bench_fit_speed.py                  # against REFERENCE
    python scripts/bench_fit_speed.py --reference HEAD~3
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from elicit_diffrender.apps.benchtools import (
    elicit_command,
    export_commit,
    fit_and_eval,
    markdown_table,
    run,
    worker_env,
    write_report,
)

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = "cef11e6"  # main on 2026-12-03, before the baked warp and the fused optimiser
TOLERANCE = {"psnr": 0.1, "ssim": 0.002, "novel_pose_psnr": 0.2}
SAME_RUN_S = 900.0  # two reused fits that finished this close (plus the reference's fit time) ran in one go


def quality(metrics: dict, finished_at: float) -> dict:
    finished = time.strftime("%Y-%m-%d %H:%M", time.localtime(finished_at))
    return {
        "psnr": metrics["novel_view"]["psnr"],
        "ssim": metrics["novel_view"]["ssim"],
        "novel_pose_psnr": metrics["novel_pose"]["psnr"],
        "fit_seconds": metrics["fit_seconds"],
        "finished": finished,
    }


def ran_in_one_go(fitted_now: list[bool], finished_at: list[float], reference_seconds: float) -> bool:
    """Whether the two fits ran in one go: both fitted in this run, or both reused and finished within
    ``SAME_RUN_S`` plus the reference's fit time of each other. The machine's speed drifts over a day, so a time
    ratio means something only then."""
    if all(fitted_now):
        return True
    return not any(fitted_now) and abs(finished_at[0] - finished_at[1]) <= SAME_RUN_S + reference_seconds


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", default=REFERENCE, help=f"commit to compare against (default {REFERENCE})")
    p.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_fit_speed")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = p.parse_args()
    from elicit_diffrender.apps.demo import DEMO_MOTION, DEMO_SEED

    elicit = str(Path(sys.executable).with_name("elicit"))
    env = worker_env(1)  # each fit alone, with every CPU this process is given
    subject = args.work / "subject"
    if not (subject / "subject.json").is_file():
        cmd = [elicit, "synth", "--seed", str(DEMO_SEED), "--motion", DEMO_MOTION, "--out", str(subject)]
        run(cmd, env, args.work / "synth.log")
    sha = export_commit(args.reference, args.work / "reference_code")
    start = time.perf_counter()
    results, fitted_now, finished_at = {}, [], []
    for name, code in (("reference", args.work / "reference_code"), ("this checkout", ROOT)):
        side_env = {**env, "PYTHONPATH": str(code)}
        metrics = args.work / name.replace(" ", "_") / "metrics.json"
        fitted_now.append(not metrics.is_file())
        measured = fit_and_eval(elicit_command(code), subject, metrics.parent, [], side_env)
        finished_at.append(metrics.stat().st_mtime)
        results[name] = quality(measured, finished_at[-1])
    ref, new = results["reference"], results["this checkout"]
    ratio = new["fit_seconds"] / ref["fit_seconds"]
    same_run = ran_in_one_go(fitted_now, finished_at, ref["fit_seconds"])
    delta = {k: new[k] - ref[k] for k in TOLERANCE}
    target = {
        "at_most_half_the_time": ratio <= 0.5 if same_run else None,
        "quality_kept": all(delta[k] >= -tol for k, tol in TOLERANCE.items()),
    }
    data = {
        "reference_commit": sha,
        "subject": {"seed": DEMO_SEED, "motion": DEMO_MOTION},
        "preset": "cpu-fast",
        "results": results,
        "time_ratio": ratio,
        "same_run": same_run,
        "delta": delta,
        "tolerance": TOLERANCE,
        "target": target,
        "seconds": time.perf_counter() - start,
    }
    rows = [{"code": name, **r} for name, r in results.items()]
    columns = [("code", "code"), ("finished", "finished"), ("fit_seconds", "fit, s"), ("psnr", "novel-view PSNR")]
    md = (
        f"# The demo fit against commit `{sha[:10]}`\n\n"
        f"`scripts/bench_fit_speed.py`: the demo subject (seed {DEMO_SEED}, {DEMO_MOTION}) fitted with `cpu-fast` "
        f"by both versions of the code, one after the other on the same machine with nothing else running, then "
        f"evaluated (a finished fit is reused: `finished` says when each ran).\n\n"
        f"{markdown_table(rows, [*columns, ('ssim', 'SSIM'), ('novel_pose_psnr', 'novel-pose PSNR')])}\n"
        + (
            ""
            if same_run
            else f"**The two fits did not run in one go** (finished {ref['finished']} and {new['finished']}): the "
            "time ratio mixes two states of the machine and is not judged; delete both run folders to measure them "
            "together.\n\n"
        )
        + f"Time ratio {ratio:.3f}; quality differences (this checkout minus reference): novel-view PSNR "
        f"{delta['psnr']:+.3f} dB, SSIM {delta['ssim']:+.4f}, novel-pose PSNR {delta['novel_pose_psnr']:+.3f} dB.\n\n"
        f"Targets: {', '.join(f'{k}: {v}' for k, v in target.items())}.\n"
    )
    json_path, md_path = write_report(args.out, "fit_speed", data, md)
    print(md)
    print(f"wrote {json_path} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
