#!/usr/bin/env python
"""Many fits on one machine: do concurrent fits share the cores fairly, and how does ``elicit batch`` scale?

1. Side by side: one short ``elicit fit`` alone, then two started together, each with nothing set (every
   fit sizes its own thread pools to the CPUs it is given). Fair sharing of N cores by two fits that each
   use them all is at most 2x the time of one alone; the target is <= 2.4x.
2. Batch scaling: the same four small jobs (fit, render, export of four synthetic subjects), one worker per
   CPU (``--cpus-per-fit 1``), with the batch given one core (``taskset -c 0``: one worker) and two cores
   (two workers); throughput in jobs per minute, the target >= 1.7x. For comparison, also one worker
   holding both cores (``--cpus-per-fit 2``): what a single job gains from a second core is what a second
   worker cannot add.

Both are measured in the same run on the same machine. Writes ``docs/benchmarks/batch.{json,md}``.

    python scripts/bench_batch.py [--work runs/bench_batch] [--steps 240]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SEEDS = (0, 1, 2, 3)


def main() -> int:
    from elicit_diffrender.apps.benchtools import machine_info, markdown_table, run, write_report
    from elicit_diffrender.core.device import cpus_given

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=ROOT / "runs" / "bench_batch")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    p.add_argument("--init-steps", type=int, default=60)
    p.add_argument("--steps", type=int, default=240)
    p.add_argument("--size", type=int, default=256, help="synthetic subjects' image size")
    args = p.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONUNBUFFERED"] = "1"
    sets = [f"init_steps={args.init_steps}", f"steps={args.steps}"]
    set_args = [x for kv in sets for x in ("--set", kv)]
    cpus = cpus_given()
    args.work.mkdir(parents=True, exist_ok=True)
    subjects = args.work / "subjects"
    for seed in SEEDS:
        if not (subjects / f"s{seed}" / "subject.json").is_file():
            run([elicit, "synth", "--seed", str(seed), "--size", str(args.size), "--out", str(subjects / f"s{seed}"),
                 "--force"], env, args.work / f"synth{seed}.log")  # fmt: skip

    def fits(n: int) -> list[float]:
        """Wall seconds of ``n`` fits of subject s0 started together."""
        procs, t0 = [], time.perf_counter()
        for k in range(n):
            out = args.work / f"side_{n}_{k}"
            shutil.rmtree(out, ignore_errors=True)
            log = open(args.work / f"side_{n}_{k}.log", "w")
            cmd = [elicit, "fit", str(subjects / "s0"), "--out", str(out), *set_args]
            procs.append((subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log))
        walls = []
        for proc, log in procs:
            if proc.wait() != 0:
                raise RuntimeError(f"a fit failed; see {log.name}")
            walls.append(time.perf_counter() - t0)
            log.close()
        return walls

    print("side by side: one fit alone, then two together", flush=True)
    alone = fits(1)[0]
    pair = fits(2)
    side = {"alone_s": alone, "pair_s": pair, "ratio": max(pair) / alone}

    def batch(cores: int, cpus_per_fit: int) -> dict:
        """The batch given ``cores`` cores (an affinity mask), ``cpus_per_fit`` CPUs per job."""
        out = args.work / f"batch_cores{cores}_cpus{cpus_per_fit}"
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        pin = ["taskset", "-c", ",".join(str(c) for c in sorted(os.sched_getaffinity(0))[:cores])]
        cmd = [*pin, elicit, "batch", str(subjects), "--out", str(out), "--steps", "fit,render,export",
               "--cpus-per-fit", str(cpus_per_fit), *set_args]  # fmt: skip
        run(cmd, env, args.work / f"{out.name}.log")
        wall = time.perf_counter() - t0
        summary = json.loads((out / "summary.json").read_text())
        return {
            "cores": cores,
            "cpus_per_fit": cpus_per_fit,
            "workers": cores // cpus_per_fit,
            "jobs": len(summary["jobs"]),
            "done": summary["counts"]["done"],
            "wall_s": wall,
            "jobs_per_min": 60.0 * summary["counts"]["done"] / wall,
            "mean_fit_s": sum(r["fit_seconds"] for r in summary["jobs"]) / len(summary["jobs"]),
        }

    rows = []
    for cores, cpus_per_fit in ((1, 1), (cpus, 1), (cpus, cpus)):
        print(f"batch of {len(SEEDS)} jobs on {cores} core(s), {cpus_per_fit} CPU(s) per fit", flush=True)
        rows.append(batch(cores, cpus_per_fit))
    scaling = rows[1]["jobs_per_min"] / rows[0]["jobs_per_min"]
    against_one_big = rows[1]["jobs_per_min"] / rows[2]["jobs_per_min"]
    data = {
        "machine": machine_info(__import__("torch").device("cpu")) | {"cpus_given": cpus},
        "fit": {"subject_size": args.size, "sets": sets},
        "side_by_side": side,
        "batch": rows,
        "throughput_ratio": scaling,
        "throughput_ratio_against_one_worker_on_all_cores": against_one_big,
        "targets": {"side_by_side_ratio_max": 2.4, "throughput_ratio_min": 1.7},
    }
    md = (
        "# Many fits on one machine\n\n"
        f"{cpus} CPUs given; short `cpu-fast` fits ({', '.join(sets)}) of synthetic subjects at {args.size} px, "
        "nothing set in the environment: each fit sizes its thread pools to the CPUs it is given.\n\n"
        "## Two fits side by side\n\n"
        f"One fit alone: {alone:.1f} s. Two started together: {pair[0]:.1f} s and {pair[1]:.1f} s, "
        f"**{side['ratio']:.2f}x** the time of one alone (target <= 2.4x; 2x is a fair share).\n\n"
        f"## `elicit batch` of {len(SEEDS)} jobs (fit, render, export)\n\n"
        + markdown_table(
            rows,
            [
                ("cores", "cores given"),
                ("workers", "workers"),
                ("cpus_per_fit", "CPUs per fit"),
                ("done", "jobs done"),
                ("wall_s", "wall (s)"),
                ("jobs_per_min", "jobs/min"),
                ("mean_fit_s", "mean fit (s)"),
            ],
        )  # fmt: skip
        + f"\nThroughput with {rows[1]['workers']} one-CPU workers: **{scaling:.2f}x** that of one worker on one "
        f"core (target >= 1.7x), and {against_one_big:.2f}x that of one worker holding all {cpus} cores (a "
        "single job gains that much less from the second core).\n"
    )
    write_report(args.out, "batch", data, md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
