"""The ``elicit`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import ElicitError


def _synth(args: argparse.Namespace) -> None:
    from .synth import synthesize

    out = synthesize(args.seed, args.out, motion_name=args.motion, size=args.size, spp=args.spp)
    print(f"wrote synthetic subject {out} (contact sheet: {out / 'contact_sheet.png'})")


def _rigs(args: argparse.Namespace) -> None:
    from .rigs import orbit_cameras, ring_cameras, write_rig

    if args.kind == "ring":
        cams = ring_cameras(args.n, args.radius, args.elevation, tuple(args.look_at), args.focal, args.size, args.size)
    else:
        cams = orbit_cameras(
            args.n,
            radius=args.radius,
            elevation_deg=args.elevation,
            look_at_point=tuple(args.look_at),
            focal=args.focal,
            width=args.size,
            height=args.size,
        )
    comment = (
        f"elicit {args.kind}: {args.n} cameras, radius {args.radius} m, elevation {args.elevation} deg, "
        f"{args.size}x{args.size}, f = {args.focal} px"
    )
    print(write_rig(args.out, cams, comment))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="elicit", description="ELICIT: one-shot animatable avatars from a single photo")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="write a synthetic clothed subject (elicit-subject/1)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--motion", default="walk_in_place", help="built-in target motion")
    s.add_argument("--size", type=int, default=512, help="image size in pixels")
    s.add_argument("--spp", type=int, default=32, help="path-tracing samples per pixel")
    s.set_defaults(func=_synth)

    r = sub.add_parser("rig", help="write a camera rig as Mitsuba scene XML")
    r.add_argument("kind", choices=["ring", "orbit"])
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--n", type=int, default=23, help="number of cameras (orbit: frames)")
    r.add_argument("--radius", type=float, default=3.0)
    r.add_argument("--elevation", type=float, default=0.0, help="degrees")
    r.add_argument("--look-at", type=float, nargs=3, default=(0.0, 0.0, 0.0))
    r.add_argument("--focal", type=float, default=650.0, help="pixels")
    r.add_argument("--size", type=int, default=512)
    r.set_defaults(func=_rigs)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except ElicitError as exc:
        print(f"elicit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"elicit {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
