#!/usr/bin/env python
"""Where a ``cpu-fast`` fit spends its time: a short fit of the demo subject under cProfile.

Wall time is split into the Warp kernels (inverse-LBS, ray sampling with the baked warp, ray-marching and
total variation, forward and backward), Mitsuba (the body renders, silhouettes and labels), the losses, the
sparsity term, the grid regions the regularisers read, the semantic prior (encoder or mirror completion),
the optimiser, checkpoint files and everything else (Python glue, torch operators outside those, and waits).
Each part is the cumulative time of the functions listed in ``PARTS``, which never call one another. The
set-up (views, body renders, the semantic prior's targets) and the training steps are profiled apart.
Writes ``docs/benchmarks/profile.{json,md}``.

With ``--preset paper`` it profiles the ``paper`` preset's set-up instead, against a reference commit measured in
the same run (``--before`` exported beside this tree, default the commit before the set-up work): set-up seconds and
where they go, then ``--paper-steps`` training steps of each, their seconds and host reads per step (counted by
``core/host_reads.py`` in both trees), and the largest difference between the two avatars after them. Writes
``docs/benchmarks/profile_paper_setup.{json,md}``.

    python scripts/profile_fit.py [--init-steps 60] [--steps 240]
    python scripts/profile_fit.py --preset paper [--before 007e2ec] [--paper-steps 10]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import logging
import os
import pstats
import subprocess
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


# Run in a subprocess with one tree first on sys.path: the set-up of the paper preset under cProfile, then a few
# training steps with the host reads counted per step; writes a JSON summary and the avatar's tensors.
CHILD = r"""
import cProfile, importlib.util, json, logging, pstats, sys, time
tree, counter_file, subject_dir, out, steps = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5])
sys.path.insert(0, tree)
try:  # the tree's own counter, whose on_host marks its host-side reads
    import elicit_diffrender.core.host_reads as probe
except ImportError:  # a tree from before it: this tree's counter, loaded from its file
    spec = importlib.util.spec_from_file_location("host_reads_probe", counter_file)
    probe = importlib.util.module_from_spec(spec)
    sys.modules["host_reads_probe"] = probe
    spec.loader.exec_module(probe)
import torch
from safetensors.torch import save_file
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.fit.config import make_config
from elicit_diffrender.fit.trainer import Trainer
logging.basicConfig(level=logging.WARNING)
subject = load_subject(subject_dir)
sets = [f"init_steps={steps}", "steps=0", "log_every=1000000", "guard_every=1000000", "preview_every=1000000",
        "checkpoint_every=1000000"]
cfg = make_config("paper", None, sets)
profiler = cProfile.Profile()
start = time.perf_counter()
profiler.enable()
trainer = Trainer(subject, cfg, out + "/run")
profiler.disable()
setup = time.perf_counter() - start
stats = pstats.Stats(profiler)
top = sorted(((v[3], k) for k, v in stats.stats.items() if "elicit_diffrender" in k[0]), reverse=True)
per_step, times = [], []
with probe.count_host_reads() as reads:
    step_fn, last = trainer.opt.step, [time.perf_counter()]
    def counted(*a, **k):
        r = step_fn(*a, **k)
        per_step.append(reads.take())
        now = time.perf_counter()
        times.append(now - last[0])
        last[0] = now
        return r
    trainer.opt.step = counted
    last[0] = time.perf_counter()
    trainer.run_stage(1, steps)
state = {k: v.detach().cpu().contiguous() for k, v in trainer.avatar.state_dict().items()}
save_file(state, out + "/avatar.safetensors")
functions = [
    {"function": f"{k[0].split('elicit_diffrender/')[-1]}:{k[2]}", "seconds": round(c, 3)} for c, k in top[:40]
]
sites = {}
for r in per_step[1:]:
    for (kind, site), n in r.items():
        sites[f"{kind} at {site}"] = sites.get(f"{kind} at {site}", 0) + n
json.dump({"setup_s": setup, "functions": functions, "step_s": times, "reads": [sum(r.values()) for r in per_step],
           "sites": sites, "grid": list(trainer.avatar.field.shape)}, open(out + "/child.json", "w"))
"""


def run_child(tree: Path, subject_dir: Path, out: Path, steps: int) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    counter = ROOT / "elicit_diffrender" / "core" / "host_reads.py"
    cmd = [sys.executable, "-c", CHILD, str(tree), str(counter), str(subject_dir), str(out), str(steps)]
    subprocess.run(cmd, check=True, cwd=out)
    return json.loads((out / "child.json").read_text())


def paper_setup(args: argparse.Namespace) -> int:
    """Before/after of the paper preset's set-up and its first steps (see the module docstring)."""
    from safetensors.torch import load_file

    from elicit_diffrender.apps.benchtools import export_commit, machine_info, markdown_table, write_report
    from elicit_diffrender.core.device import default_device
    from elicit_diffrender.inputs.synth import synthesize

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        export_commit(args.before, tmp / "before")
        synthesize(0, tmp / "subject")
        runs = {
            "before": run_child(tmp / "before", tmp / "subject", tmp / "b", args.paper_steps),
            "after": run_child(ROOT, tmp / "subject", tmp / "a", args.paper_steps),
        }
        a, b = load_file(tmp / "a" / "avatar.safetensors"), load_file(tmp / "b" / "avatar.safetensors")
    diff = {k: float((a[k].double() - b[k].double()).abs().max()) if a[k].numel() else 0.0 for k in a}
    equal = all(bool((a[k] == b[k]).all()) for k in a)
    data = {
        "preset": "paper",
        "subject": "demo (synth seed 0)",
        "before_commit": args.before,
        "before_s": round(runs["before"]["setup_s"], 2),
        "after_s": round(runs["after"]["setup_s"], 2),
        "speedup": round(runs["before"]["setup_s"] / runs["after"]["setup_s"], 2),
        "grid": runs["after"]["grid"],
        "steps": args.paper_steps,
        "avatar_after_steps_bitwise_equal": equal,
        "avatar_max_abs_difference": diff,
        "machine": machine_info(default_device()),
    }
    for name, run in runs.items():
        steady = run["step_s"][1:]  # the first step builds what the later ones reuse
        data[name] = {
            "setup_s": round(run["setup_s"], 2),
            "functions": run["functions"],
            "step_ms_median": round(1000 * sorted(steady)[len(steady) // 2], 1),
            "host_reads_per_step": run["reads"],
            "host_read_sites_after_the_first_step": run["sites"],
        }
    rows = []
    for name in ("before", "after"):
        d = data[name]
        reads = d["host_reads_per_step"][1:]
        rows.append(
            {
                "tree": f"{name} ({args.before})" if name == "before" else "after (this tree)",
                "set-up s": d["setup_s"],
                "step ms (median)": d["step_ms_median"],
                "host reads per step (steps 2+)": f"{min(reads)}-{max(reads)}",
            }
        )
    cols = [(c, c) for c in rows[0]]
    md = [
        "# The paper preset's set-up, before and after",
        "",
        f"`scripts/profile_fit.py --preset paper`: the demo subject (synth seed 0), the `paper` preset (grid "
        f"{' x '.join(map(str, data['grid']))} nodes), set-up (the `Trainer`'s construction) under cProfile, then "
        f"{args.paper_steps} stage-1 steps, in one subprocess per tree, one after the other on this machine. "
        f"Host reads are counted per step by `elicit_diffrender/core/host_reads.py` in both trees (each one is a "
        "host sync on CUDA).",
        "",
        f"**Set-up: {data['before_s']} s before, {data['after_s']} s after ({data['speedup']}x).** "
        f"The avatar after {args.paper_steps} steps is "
        + ("bitwise equal." if equal else f"not bitwise equal: largest difference {max(diff.values()):.3g}."),
        "",
        markdown_table(rows, cols),
        "",
    ]
    for name in ("before", "after"):
        md += [f"## Set-up functions, {name} (cumulative seconds, nested: a caller includes its callees)", ""]
        md += [markdown_table(data[name]["functions"][:15], [("function", "function"), ("seconds", "seconds")]), ""]
        sites = data[name]["host_read_sites_after_the_first_step"]
        md += [
            f"Host reads in steps 2 to {args.paper_steps}, by site: "
            + (", ".join(f"{k} x{v}" for k, v in sites.items()) or "none"),
            "",
        ]
    write_report(args.out, "profile_paper_setup", data, "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--init-steps", type=int, default=60)
    ap.add_argument("--steps", type=int, default=240)
    ap.add_argument("--preset", choices=("cpu-fast", "paper"), default="cpu-fast")
    ap.add_argument("--before", default="007e2ec", help="the reference commit of --preset paper")
    ap.add_argument("--paper-steps", type=int, default=10)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    args = ap.parse_args()
    if args.preset == "paper":
        return paper_setup(args)
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
