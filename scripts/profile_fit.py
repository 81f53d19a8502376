#!/usr/bin/env python
"""Where a ``cpu-fast`` fit spends its time: a short fit of the demo subject under cProfile.

Wall time is split into the Warp kernels (inverse-LBS, ray sampling with the baked warp, ray-marching and
total variation, forward and backward), Mitsuba (the body renders, silhouettes and labels), the losses, the
sparsity term, the grid regions the regularisers read, the semantic prior (encoder or mirror completion),
the optimiser, checkpoint files and everything else (Python glue, torch operators outside those, and waits).
Each part is the cumulative time of the functions listed in ``PARTS``, which never call one another. The
set-up (views, body renders, the semantic prior's targets) and the training steps are profiled apart.
Writes ``docs/benchmarks/profile.{json,md}``.

    python scripts/profile_fit.py [--init-steps 60] [--steps 240]
"""

from __future__ import annotations

import argparse
import cProfile
import logging
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# part -> (file suffix, function name; "" for every function of the file) of the functions whose cumulative
# time it owns. The parts never call one another, so their times add up without double counting.
PARTS: dict[str, list[tuple[str, str]]] = {
    "inverse LBS forward (Warp)": [("elicit_diffrender/model/skinning.py", "forward")],
    "inverse LBS backward (Warp)": [("elicit_diffrender/model/skinning.py", "backward")],
    "ray marching forward (Warp)": [("elicit_diffrender/model/volume.py", "forward")],
    "ray marching backward (Warp)": [("elicit_diffrender/model/volume.py", "backward")],
    "ray sampling, occupancy and baked warp (Warp)": [("elicit_diffrender/model/volume.py", "sample_rays")],
    "total variation (Warp)": [
        ("elicit_diffrender/model/total_variation.py", "forward"),
        ("elicit_diffrender/model/total_variation.py", "backward"),
    ],
    "sparsity": [("elicit_diffrender/model/field.py", "sparsity_loss")],
    "grid regions (leaf copies, gradient adds)": [("elicit_diffrender/fit/regions.py", "")],
    "Mitsuba body renders": [
        ("elicit_diffrender/data/mesh_render.py", "render"),
        ("elicit_diffrender/data/mesh_render.py", "__call__"),
    ],
    "semantic prior": [
        ("elicit_diffrender/fit/completion.py", "loss"),
        ("elicit_diffrender/fit/completion.py", "build"),
        ("elicit_diffrender/model/encoders.py", "forward"),
    ],
    "losses": [("elicit_diffrender/model/losses.py", "")],
    "optimiser step": [("torch/optim/adam.py", "step")],
    "checkpoint files": [("elicit_diffrender/fit/checkpoint.py", "save_checkpoint")],
}


def part_seconds(stats: pstats.Stats) -> dict[str, float]:
    """Cumulative seconds per part: each owned function's time from callers that no part owns (recursion and
    a part's own helpers are not counted twice)."""
    raw = stats.stats  # (file, line, name) -> (primitive calls, calls, own time, cumulative time, callers)
    owner: dict[tuple, str] = {}
    for part, patterns in PARTS.items():
        for key in raw:
            file, _, name = key
            if any(file.endswith(suffix) and (not fn or name == fn) for suffix, fn in patterns):
                owner.setdefault(key, part)
    seconds = dict.fromkeys(PARTS, 0.0)
    for key, part in owner.items():
        callers = raw[key][4]
        seconds[part] += sum(v[3] for caller, v in callers.items() if caller not in owner) if callers else raw[key][3]
    return seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--init-steps", type=int, default=60)
    ap.add_argument("--steps", type=int, default=240)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = ap.parse_args()
    from elicit_diffrender.apps.benchtools import machine_info, markdown_table, write_report
    from elicit_diffrender.core.device import default_device
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.fit.config import make_config
    from elicit_diffrender.fit.trainer import Trainer
    from elicit_diffrender.inputs.synth import synthesize

    logging.basicConfig(level=logging.WARNING)
    phases: dict[str, tuple[float, pstats.Stats]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        subject_dir = Path(tmp) / "subject"
        synthesize(0, subject_dir)
        subject = load_subject(subject_dir)
        sets = [f"init_steps={args.init_steps}", f"steps={args.steps}"]
        cfg = make_config("cpu-fast", overrides=[*sets, "preview_every=1000000", "checkpoint_every=1000000"])
        holder: dict = {}
        for phase, work in (
            ("set-up", lambda: holder.setdefault("trainer", Trainer(subject, cfg, Path(tmp) / "run"))),
            ("training steps", lambda: holder["trainer"].run()),
        ):
            profiler = cProfile.Profile()
            start = time.perf_counter()
            profiler.enable()
            work()
            profiler.disable()
            phases[phase] = (time.perf_counter() - start, pstats.Stats(profiler))
    steps = args.init_steps + args.steps
    tables, data = [], {"steps": {"stage1": args.init_steps, "stage2": args.steps}}
    for phase, (wall, stats) in phases.items():
        seconds = part_seconds(stats)
        seconds["other (Python glue, torch outside these, waits)"] = max(0.0, wall - sum(seconds.values()))
        rows = [
            {
                "part": k,
                "seconds": round(v, 2),
                "ms per step": round(1000 * v / steps, 1),
                "share %": round(100 * v / wall, 1),
            }
            for k, v in sorted(seconds.items(), key=lambda kv: -kv[1])
            if round(v, 2) > 0
        ]
        data[phase] = {"wall_s": round(wall, 2), "parts": rows}
        cols = [("part", "part"), ("seconds", "seconds"), ("share %", "share %")]
        if phase == "training steps":
            cols.insert(2, ("ms per step", "ms per step"))
        tables += [f"## {phase}: {wall:.1f} s", "", markdown_table(rows, cols)]
    data["omp_num_threads_env"] = os.environ.get("OMP_NUM_THREADS")
    data["machine"] = machine_info(default_device())
    train = phases["training steps"][0]
    md = [
        "# Where a cpu-fast fit spends its time",
        "",
        f"`scripts/profile_fit.py`: the demo subject (seed 0), `cpu-fast` with {args.init_steps} stage-1 and "
        f"{args.steps} stage-2 steps (previews and checkpoints only at the end), under cProfile, which adds its "
        f"own overhead to Python-heavy parts. Set-up and training are profiled apart; training took "
        f"{1000 * train / steps:.0f} ms per step (the end-of-stage previews and checkpoints included).",
        "",
        *tables,
    ]
    write_report(args.out, "profile", data, "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
