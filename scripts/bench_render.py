#!/usr/bin/env python
"""Mitsuba render cost per channel per view, against a full path-traced render of the same scene.

The scene is the template-textured Anny body from a ring of cameras. Every channel is rendered on
its own (only what is asked for), then all cameras in one batch-sensor launch are compared with one
launch per camera. The path-traced render (sky + key light, 3 bounces, same spp) is the cost of the
light transport that the body prior's renders skip.

    python scripts/bench_render.py [--views 8] [--spp 16] [--repeats 3] [--variant cuda_ad_rgb] [--name render_cuda]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    p.add_argument("--name", default="render", help="report file name (NAME.json, NAME.md)")
    p.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb on a GPU, else llvm_ad_rgb)")
    args = p.parse_args()
    if args.variant:
        import os

        os.environ["ELICIT_MITSUBA_VARIANT"] = args.variant

    from elicit_diffrender.apps.benchtools import markdown_table, write_report
    from elicit_diffrender.body import load_body
    from elicit_diffrender.body.template import template_colors
    from elicit_diffrender.core.mitsuba_variant import mitsuba
    from elicit_diffrender.data.mesh_render import MeshAppearance, MeshRenderer
    from elicit_diffrender.data.rigs import ring_cameras

    mi = mitsuba()
    body = load_body({"model": "anny"})
    renderer = MeshRenderer(body.faces, MeshAppearance(vertex_colors=template_colors(body)), body.face_parts())
    verts = body.rest_vertices
    rows = []
    start = time.perf_counter()
    for size in (256, 512):
        cams = ring_cameras(n=args.views, focal=650.0 * size / 512, width=size, height=size)
        cases = [
            ("mask", ("mask",)),
            ("depth", ("depth",)),
            ("labels", ("labels",)),
            ("alpha", ("alpha",)),
            ("color", ("color",)),
            ("labels+mask+depth", ("labels", "mask", "depth")),
            ("path traced (reference)", ("shaded",)),
        ]
        timings = {}
        for name, channels in cases:
            renderer.render(verts, cams, channels, spp=args.spp)  # JIT-compile outside the timing
            best = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                renderer.render(verts, cams, channels, spp=args.spp)
                best.append(time.perf_counter() - t0)
            timings[name] = float(np.median(best))
        # Batch sensor (one launch) against one launch per camera, for the mask channel.
        renderer.render(verts, cams[:1], ("mask",))
        t0 = time.perf_counter()
        for cam in cams:
            renderer.render(verts, [cam], ("mask",))
        loop = time.perf_counter() - t0
        ref = timings["path traced (reference)"]
        for name, channels in cases:
            exact = set(channels) <= {"labels", "mask", "depth"}
            rows.append(
                {
                    "size": f"{size}^2",
                    "channel": name,
                    "spp": 1 if exact else args.spp,
                    "ms_per_view": 1e3 * timings[name] / len(cams),
                    "vs_path_traced": timings[name] / ref,
                }
            )
        rows.append(
            {
                "size": f"{size}^2",
                "channel": "mask, one launch per camera",
                "spp": 1,
                "ms_per_view": 1e3 * loop / len(cams),
                "vs_path_traced": loop / ref,
            }
        )
        print(f"{size}^2 done", flush=True)
    elapsed = time.perf_counter() - start
    data = {
        "variant": mi.variant(),
        "views_per_launch": args.views,
        "body_vertices": int(verts.shape[0]),
        "repeats": args.repeats,
        "seconds": elapsed,
        "results": rows,
    }
    md = (
        f"# Mitsuba render cost per channel\n\nVariant `{mi.variant()}`, Anny body ({verts.shape[0]} vertices), "
        f"{args.views} ring cameras per batch-sensor launch, median of {args.repeats}. The reference is a "
        f"path-traced render of the same scene (sky + key light, 3 bounces, {args.spp} spp); `vs path traced` "
        f"is the fraction of its time a channel costs.\n\n"
        + markdown_table(
            rows,
            [
                ("size", "size"),
                ("channel", "channel"),
                ("spp", "spp"),
                ("ms_per_view", "ms / view"),
                ("vs_path_traced", "vs path traced"),
            ],
        )
    )
    json_path, md_path = write_report(args.out, args.name, data, md)
    print(md)
    print(f"wrote {json_path} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
