#!/usr/bin/env python
"""Micro-benchmarks: the Warp ray marcher and skinning warp against pure-torch versions of the same math.

Both sides run in this process, interleaved, so machine noise affects them alike. Each row times
forward + backward (gradients for the grids, or for the bone transforms and the weight volume),
reports the forward alone, peak extra memory, the first call's compile time, and the largest
absolute difference between the two implementations' outputs.

    python scripts/bench_kernels.py            # full sweep
    python scripts/bench_kernels.py --quick    # the default sizes plus one small case, < 2 minutes
    python scripts/bench_kernels.py --device cuda --paper-sizes --name kernels_cuda   # on a GPU
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="default sizes and one small case only")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--repeats", type=int, default=None, help="timed repeats per case (median is reported)")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks", help="output folder")
    p.add_argument("--name", default="kernels", help="report file name (NAME.json, NAME.md)")
    p.add_argument(
        "--paper-sizes",
        action="store_true",
        help="add the paper preset's sizes: a 224x224 crop x 128 samples on a 256^3 grid, 224^2 x 128 points warped",
    )
    p.add_argument(
        "--keep-kernel-cache",
        action="store_true",
        help="reuse Warp's kernel cache (first-call times then exclude compilation)",
    )
    p.add_argument("--memory-case", default=None, help=argparse.SUPPRESS)  # internal: one peak-memory probe
    return p.parse_args()


ARGS = parse_args()
if not ARGS.keep_kernel_cache and not ARGS.memory_case:  # a fresh cache so the first call really compiles
    os.environ["ELICIT_WARP_CACHE"] = tempfile.mkdtemp(prefix="elicit-bench-warp-")

# The package first: it sets OMP_WAIT_POLICY before torch starts, so both implementations run as they do in
# the package's own processes (with torch's idle threads spinning, they took a core from Warp's launches).
import elicit_diffrender  # noqa: E402, F401, I001

import torch  # noqa: E402

from elicit_diffrender.apps.benchtools import (  # noqa: E402
    machine_info,
    markdown_table,
    peak_memory,
    time_interleaved,
    time_once,
    write_report,
)
from elicit_diffrender.core.device import default_device  # noqa: E402
from elicit_diffrender.core.geometry import axis_angle_to_matrix  # noqa: E402
from elicit_diffrender.model.torch_reference import composite_reference, inverse_lbs_reference  # noqa: E402
from elicit_diffrender.model.skinning import inverse_lbs  # noqa: E402
from elicit_diffrender.model.volume import composite, sample_rays  # noqa: E402

BOX = torch.tensor([[-0.9, -1.0, -0.5], [0.9, 1.0, 0.5]])
_FIRST_CALL: set[str] = set()
TARGET_SPEEDUP = 5.0  # forward + backward against the pure-torch reference, at the default sizes


def body_grid(res: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """A body-sized blob: an opaque ellipsoid with soft edges, and smooth random colour."""
    axes = [torch.linspace(float(BOX[0, a]), float(BOX[1, a]), res, device=device) for a in range(3)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    r = ((x / 0.45) ** 2 + (y / 0.85) ** 2 + (z / 0.25) ** 2).sqrt()
    density = (40.0 * (1.0 - r)).contiguous()
    gen = torch.Generator(device="cpu").manual_seed(0)
    coarse = torch.randn(3, 8, 8, 8, generator=gen)
    color = torch.nn.functional.interpolate(coarse[None], size=(res, res, res), mode="trilinear")[0]
    return density, color.permute(1, 2, 3, 0).contiguous().to(device)


def camera_rays(n: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator(device="cpu").manual_seed(1)
    origins = torch.tensor([0.0, 0.0, -3.0]).repeat(n, 1)
    target = (torch.rand(n, 3, generator=gen) - 0.5) * torch.tensor([1.9, 2.1, 0.0])
    dirs = torch.nn.functional.normalize(target - origins, dim=1)
    return origins.to(device), dirs.to(device)


def first_call_seconds(key: str, fn, device: torch.device) -> float | None:
    """Time of the first call of a kernel family in this process (compile + run), once per family."""
    if key in _FIRST_CALL:
        return None
    _FIRST_CALL.add(key)
    return time_once(fn, device)


def raymarch_case(rays: int, samples: int, grid: int, variant: str, device: torch.device) -> dict:
    """Forward and forward+backward callables of both implementations for one ray-marching case."""
    density, color = body_grid(grid, device)
    origins, dirs = camera_rays(rays, device)
    box = BOX.to(device)
    pack = sample_rays(origins, dirs, box, samples)
    outputs = ("alpha",) if variant == "alpha only" else ("rgb", "alpha")
    t_thresh = 1e-4 if variant == "early stop 1e-4" else 0.0
    use_color = "rgb" in outputs
    params = {
        "warp": (density.clone().requires_grad_(), color.clone().requires_grad_()),
        "torch": (density.clone().requires_grad_(), color.clone().requires_grad_()),
    }

    def render(impl: str):
        d, c = params[impl]
        if impl == "warp":
            return composite(pack, d, c if use_color else None, box, outputs=outputs, t_thresh=t_thresh)
        return composite_reference(pack, d, c if use_color else None, box)

    def step(impl: str) -> None:
        d, c = params[impl]
        d.grad = c.grad = None
        out = render(impl)
        (out["alpha"].sum() + (out["rgb"].sum() if use_color else 0.0)).backward()

    def forward(impl: str):
        with torch.no_grad():
            return render(impl)

    def errors() -> tuple[float, float]:
        a, b = forward("warp"), forward("torch")
        err = max(float((a[k] - b[k]).abs().max()) for k in a)
        step("warp"), step("torch")
        gw, gt = params["warp"][0].grad, params["torch"][0].grad
        return err, float((gw - gt).abs().max() / gt.abs().max().clamp(min=1e-30))

    config = {
        "rays": rays,
        "samples_per_ray": samples,
        "grid": grid,
        "variant": variant,
        "packed_samples": pack.n_samples,
    }
    return {"kernel": "raymarch", "config": config, "step": step, "forward": forward, "errors": errors}


def skinning_case(points: int, bones: int, device: torch.device) -> dict:
    """Forward and forward+backward callables of both implementations for one skinning case."""
    gen = torch.Generator(device="cpu").manual_seed(2)
    pts = (torch.randn(points, 3, generator=gen) * torch.tensor([0.3, 0.6, 0.15])).to(device)
    mats = torch.eye(4).repeat(bones, 1, 1)
    mats[:, :3, :3] = axis_angle_to_matrix(0.4 * torch.randn(bones, 3, generator=gen))
    mats[:, :3, 3] = 0.1 * torch.randn(bones, 3, generator=gen)
    logits = 3 * torch.randn(bones + 1, 8, 8, 8, generator=gen)
    weights = torch.softmax(torch.nn.functional.interpolate(logits[None], size=(32, 32, 32), mode="trilinear")[0], 0)
    weights = weights[:-1].contiguous()
    wbox = torch.tensor([[-1.0, -1.2, -0.6], [1.0, 1.2, 0.6]], device=device)
    params = {
        impl: (mats.to(device).clone().requires_grad_(), weights.to(device).clone().requires_grad_())
        for impl in ("warp", "torch")
    }
    fns = {"warp": inverse_lbs, "torch": inverse_lbs_reference}

    def step(impl: str) -> None:
        m, w = params[impl]
        m.grad = w.grad = None
        x, fg = fns[impl](pts, m, w, wbox)
        (x.sum() + fg.sum()).backward()

    def forward(impl: str):
        with torch.no_grad():
            return fns[impl](pts, *params[impl], wbox)

    def errors() -> tuple[float, float]:
        (xa, fa), (xb, fb) = forward("warp"), forward("torch")
        err = max(float((xa - xb).abs().max()), float((fa - fb).abs().max()))
        step("warp"), step("torch")
        gw, gt = params["warp"][0].grad, params["torch"][0].grad
        return err, float((gw - gt).abs().max() / gt.abs().max().clamp(min=1e-30))

    config = {"points": points, "bones": bones, "weight_grid": 32}
    return {"kernel": "skinning", "config": config, "step": step, "forward": forward, "errors": errors}


def make_case(spec: dict, device: torch.device) -> dict:
    if spec["kernel"] == "raymarch":
        return raymarch_case(spec["rays"], spec["samples"], spec["grid"], spec["variant"], device)
    return skinning_case(spec["points"], spec["bones"], device)


def memory_probe(spec: dict, device: torch.device) -> dict:
    """Peak extra memory of one step of each implementation, measured in a child process.

    The child sets MALLOC_MMAP_THRESHOLD_ so that large buffers go straight to the OS and its
    resident size follows what is really live; timings are never taken there.
    """
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--memory-case",
        json.dumps(spec),
        "--device",
        str(device),
        "--keep-kernel-cache",
    ]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_memory_case(spec: dict, device: torch.device) -> None:
    case = make_case(spec, device)
    for impl in ("warp", "torch"):
        case["step"](impl)  # load kernels and warm caches first
    peaks = {
        f"{impl}_peak_mb": peak_memory(lambda i=impl: case["step"](i), device) / 2**20 for impl in ("warp", "torch")
    }
    print(json.dumps(peaks))


def measure(spec: dict, device: torch.device, repeats: int) -> dict:
    case = make_case(spec, device)
    family = case["kernel"] if case["kernel"] == "raymarch" else f"skinning-{spec['bones']}"
    first = first_call_seconds(family, lambda: case["step"]("warp"), device)
    case["step"]("warp"), case["step"]("torch")
    fns = [
        lambda: case["step"]("warp"),
        lambda: case["step"]("torch"),
        lambda: case["forward"]("warp"),
        lambda: case["forward"]("torch"),
    ]
    warp_s, torch_s, warp_f, torch_f = time_interleaved(fns, device, repeats)
    err, grad_err = case["errors"]()
    return {
        "kernel": case["kernel"],
        "config": case["config"],
        "warp_s": warp_s,
        "torch_s": torch_s,
        "speedup": torch_s / warp_s,
        "warp_fwd_s": warp_f,
        "torch_fwd_s": torch_f,
        "max_abs_err": err,
        "grad_max_rel_err": grad_err,
        **memory_probe(spec, device),
        "first_call_s": first,
    }


def main() -> int:
    device = torch.device(ARGS.device) if ARGS.device else default_device()
    if ARGS.memory_case:
        run_memory_case(json.loads(ARGS.memory_case), device)
        return 0
    repeats = ARGS.repeats or (3 if ARGS.quick else 5)
    default_rm = (16384, 64, 128)
    if ARGS.quick:
        rm_cases = [(*default_rm, "full"), (4096, 32, 64, "full")]
        sk_cases = [(100_000, 24), (100_000, 104)]
    else:
        sweep = {(r, 64, 128) for r in (4096, 16384, 65536)} | {(16384, s, 128) for s in (32, 64, 128)}
        sweep |= {(16384, 64, g) for g in (64, 128, 192)}
        rm_cases = [(*c, "full") for c in sorted(sweep)]
        rm_cases += [(*default_rm, "early stop 1e-4"), (*default_rm, "alpha only")]
        sk_cases = [(p, b) for p in (100_000, 1_000_000) for b in (24, 104)]
    if ARGS.paper_sizes:
        rm_cases.append((224 * 224, 128, 256, "full"))
        sk_cases.append((224 * 224 * 128, 24))
    results = []
    start = time.perf_counter()
    for rays, samples, grid, variant in rm_cases:
        spec = {"kernel": "raymarch", "rays": rays, "samples": samples, "grid": grid, "variant": variant}
        row = measure(spec, device, repeats)
        results.append(row)
        print(
            f"raymarch {rays:>6} rays x {samples:>3} samples, grid {grid}^3 [{variant}]: "
            f"warp {row['warp_s'] * 1e3:7.1f} ms, torch {row['torch_s'] * 1e3:7.1f} ms, "
            f"x{row['speedup']:.2f}, err {row['max_abs_err']:.1e}",
            flush=True,
        )
    for points, bones in sk_cases:
        row = measure({"kernel": "skinning", "points": points, "bones": bones}, device, repeats)
        results.append(row)
        print(
            f"skinning {points:>8} points x {bones:>3} bones: warp {row['warp_s'] * 1e3:7.1f} ms, "
            f"torch {row['torch_s'] * 1e3:7.1f} ms, x{row['speedup']:.2f}, err {row['max_abs_err']:.1e}",
            flush=True,
        )
    elapsed = time.perf_counter() - start
    defaults = [
        r
        for r in results
        if (
            r["kernel"] == "raymarch"
            and r["config"]["variant"] == "full"
            and (r["config"]["rays"], r["config"]["samples_per_ray"], r["config"]["grid"]) == default_rm
        )
        or (r["kernel"] == "skinning" and r["config"] == {"points": 100_000, "bones": 24, "weight_grid": 32})
    ]
    target = {
        "speedup_min": TARGET_SPEEDUP,
        "met": all(r["speedup"] >= TARGET_SPEEDUP for r in defaults),
        "default_speedups": {r["kernel"]: r["speedup"] for r in defaults},
    }
    data = {
        "machine": machine_info(device),
        "quick": ARGS.quick,
        "repeats": repeats,
        "seconds": elapsed,
        "target": target,
        "results": results,
    }
    rows = []
    for r in results:
        c = r["config"]
        size = (
            f"{c['rays']} rays x {c['samples_per_ray']} samples, {c['grid']}^3, {c['variant']}"
            if r["kernel"] == "raymarch"
            else f"{c['points']} points x {c['bones']} bones, 32^3 weights"
        )
        rows.append({**r, "size": size})
    columns = [
        ("kernel", "kernel"),
        ("size", "size"),
        ("warp_s", "warp fwd+bwd (s)"),
        ("torch_s", "torch fwd+bwd (s)"),
        ("speedup", "speedup"),
        ("warp_fwd_s", "warp fwd (s)"),
        ("torch_fwd_s", "torch fwd (s)"),
        ("max_abs_err", "max abs err"),
        ("grad_max_rel_err", "grad rel err"),
        ("warp_peak_mb", "warp peak MB"),
        ("torch_peak_mb", "torch peak MB"),
        ("first_call_s", "first call (s)"),
    ]
    md = (
        f"# Kernel micro-benchmarks\n\nDevice: {data['machine']['device']} ({data['machine']['cpu_count']} cores, "
        f"torch {data['machine']['torch']} on {data['machine']['torch_threads']} threads, OMP_WAIT_POLICY "
        f"{data['machine']['omp_wait_policy']} as the package sets it). Median of {repeats} "
        f"interleaved runs; both implementations float32, measured in the same process. "
        f"`first call` is the first launch of a kernel family in a fresh kernel cache (compilation included).\n\n"
        + markdown_table(rows, columns)
        + f"\nTarget: speedup >= {TARGET_SPEEDUP:g} at the default sizes: "
        + ", ".join(f"{k} x{v:.2f}" for k, v in target["default_speedups"].items())
        + f" -> {'met' if target['met'] else 'NOT met'}.\n"
    )
    json_path, md_path = write_report(ARGS.out, ARGS.name, data, md)
    print(md)
    print(f"wrote {json_path} and {md_path} in {elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
