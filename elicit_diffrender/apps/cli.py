"""The ``elicit`` command line."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

from ..core.checks import MAX_MEGAPIXELS, float_between, int_between, positive_float, positive_int, unit_fraction
from ..core.errors import ElicitError, error_line
from ..fit.config import PRESETS, FitConfig
from ..inputs.people import PEOPLE

MAX_IMAGE_SIZE = 8192  # pixels on a side of anything rendered


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit code 2), like every other bad input."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _synth(args: argparse.Namespace) -> None:
    if args.mesh is not None and args.photos:
        raise ElicitError("--photos renders procedural people only; it cannot be used with --mesh")
    if args.mesh is not None:
        from ..inputs.scan import synthesize_scan

        out = synthesize_scan(args.mesh, args.out, args.motion, size=args.size, spp=args.spp, force=args.force)
    else:
        from ..inputs.synth import synthesize

        seed = 0 if args.seed is None else args.seed
        out = synthesize(
            seed,
            args.out,
            args.motion,
            size=args.size,
            spp=args.spp,
            force=args.force,
            person=args.person,
            photos=args.photos,
        )
    print(f"wrote synthetic subject {out} (contact sheet: {out / 'contact_sheet.png'})")


def _fit(args: argparse.Namespace) -> None:
    from ..data.subject import load_subject
    from ..fit.config import make_config
    from ..fit.run import fit

    cfg = make_config(args.preset, args.config, args.set)
    subject = load_subject(args.subject)
    report = fit(subject, cfg, args.out, resume=args.resume, force=args.force)
    enc = report["encoder"]["name"] if report["encoder"] else "none"
    print(
        f"avatar: {report['avatar']} (encoder: {enc}; perceptual: {report['perceptual']['name']}; "
        f"{report['seconds']['total']:.0f} s)"
    )


def _render(args: argparse.Namespace) -> None:
    from ..outputs.video import render_command

    for path in render_command(args.run, args.motion, args.cameras, args.out, args.size, args.samples, args.fps)[-2:]:
        print(f"wrote {path}")


def _export(args: argparse.Namespace) -> None:
    from ..outputs.export import export_run

    texture_size = None if args.vertex_colors else args.texture_size
    summary = export_run(args.run, args.out, args.motion, args.resolution, args.faces, texture_size)
    frames = f", {summary['frames']} frames of {args.motion}" if summary["frames"] else ""
    print(
        f"wrote {summary['path']} ({summary['vertices']} vertices, {summary['faces']} faces, "
        f"{summary['joints']} joints{frames}; {summary['appearance']}; {summary['bytes'] / 2**20:.1f} MiB; "
        f"{summary['seconds']:.1f} s)"
    )


def _view(args: argparse.Namespace) -> None:
    from ..outputs.export import export_run
    from ..outputs.viewer import write_viewer

    glb = args.source
    if glb.suffix.lower() != ".glb":
        glb = Path(export_run(args.source, args.out / "avatar.glb", args.motion)["path"])
    print(f"wrote {write_viewer(glb, args.out)} (open it in a browser; no server needed)")


def _demo(args: argparse.Namespace) -> None:
    from .demo import run_demo

    summary = run_demo(args.out, overrides=args.set)
    secs = summary["seconds"]
    print(
        f"demo done in {secs['total']:.0f} s (synth {secs['synth']:.0f} s, fit {secs['fit']:.0f} s, "
        f"render {secs['render']:.0f} s, export {secs['export']:.0f} s)"
    )
    for key in ("turntable", "animation", "contact_sheet", "avatar_glb", "viewer"):
        print(f"  {key}: {summary[key]}")


def _batch(args: argparse.Namespace) -> None:
    from ..fit.config import config_dict, make_config
    from .batch import parse_steps, run_batch

    steps = parse_steps(args.steps)
    cfg = make_config(args.preset, args.config, args.set)
    summary = run_batch(
        args.inputs, args.out, steps, config_dict(cfg), args.address, args.cpus_per_fit, args.size, args.per_folder
    )
    failed = [r for r in summary["jobs"] if r["status"] == "failed"]
    for r in failed:
        print(f"job {r['name']} failed: {r['error']}")
    n, counts = len(summary["jobs"]), summary["counts"]
    print(f"{counts['done']} done, {counts['failed']} failed of {n}; summary: {args.out / 'summary.md'}")
    if failed:
        first = failed[0]
        raise ElicitError(
            f"{len(failed)} of {n} jobs failed; job {first['name']}: {first['error']} (each job's error: "
            f"{args.out / 'summary.md'})"
        )


def _app(args: argparse.Namespace) -> None:
    from .webapp import serve

    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"elicit app: serving on {args.host}: anyone who reaches this address can run jobs", file=sys.stderr)
    serve(args.out, args.host, args.port, args.preset, args.set, args.address, args.cpus_per_fit, args.share)


def _eval(args: argparse.Namespace) -> None:
    from ..data.subject import load_subject
    from ..outputs.evaluate import evaluate_run

    m = evaluate_run(args.run, load_subject(args.subject), args.out, args.scale, args.max_views, align=args.align)
    if "alignment" in m:
        a = m["alignment"]
        print(
            f"aligned {a['fitted_subject']} to the subject: scale {a['scale']:.3f}, vertex error after alignment "
            f"{100 * a['vertex_error_m']['mean']:.1f} cm mean, {100 * a['vertex_error_m']['max']:.1f} cm max"
        )
    for split in ("novel_view", "novel_pose"):
        if split not in m:
            continue
        r = m[split]
        lp = "null" if r["lpips"] is None else f"{r['lpips']:.3f}"
        psnr = "n/a" if r["psnr"] is None else f"{r['psnr']:.2f}"
        ssim = "n/a" if r["ssim"] is None else f"{r['ssim']:.3f}"
        print(f"{split}: PSNR {psnr}  SSIM {ssim}  LPIPS {lp}  ({r['views']} views)")
        if "rear" in r and r["rear"]["views"]:
            print(
                f"  rear (> {r['rear']['degrees']:.0f} deg from the input): PSNR {r['rear']['psnr']:.2f}  "
                f"SSIM {r['rear']['ssim']:.3f}  ({r['rear']['views']} views)"
            )
    print(f"wrote {args.out}")


def _prepare(args: argparse.Namespace) -> None:
    from ..inputs.prepare import mask_beside, prepare

    masks = args.mask or [mask_beside(p) for p in args.photo]
    r = prepare(
        args.photo,
        args.out,
        masks if any(m is not None for m in masks) else None,
        args.params,
        args.focal,
        args.motion,
        force=args.force,
        max_megapixels=args.max_megapixels,
    )
    for row in r.get("photos", [r]):
        kp = row.get("keypoint_error_px")
        kp_text = f", keypoint error {kp['median']:.1f} px median" if kp else ""
        print(f"{row['photo']}: silhouette IoU {row['silhouette_iou']:.3f}{kp_text}")
    print(f"wrote subject {args.out} in {r['seconds']:.0f} s (overlay: {args.out / 'overlay.png'})")


def _import(args: argparse.Namespace) -> None:
    from ..inputs.importers import import_elicit_wild, import_zju

    if args.layout == "elicit-wild":
        out = import_elicit_wild(args.source, args.out, args.motion, args.smpl, args.force)
    else:
        if not args.frames:
            raise ElicitError("import zju needs --frames (the frame ids to import; the first is the input)")
        out = import_zju(args.source, args.out, args.frames, args.input_camera, args.smpl, args.force)
    print(f"wrote subject {out}")


def _rigs(args: argparse.Namespace) -> None:
    from ..data.rigs import orbit_cameras, ring_cameras, write_rig

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


def _weights(args: argparse.Namespace) -> None:
    from ..core import weights

    if args.action == "list":
        found = weights.on_disk()
        if not found:
            print("no CLIP weights on disk: fits use the mirror completion (weights-free fallback)")
        for w in found:
            print(f"{w.model}/{w.tag}  {w.megabytes:.0f} MB  {w.path}")
        return
    path = weights.fetch(args.model, args.tag, args.endpoint)
    print(
        f"fetched {args.model}/{args.tag} into {path}; fits with clip_model={args.model} "
        f"clip_pretrained={args.tag} now use it"
    )


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="elicit", description="ELICIT: one-shot animatable avatars from a single photo")
    p.add_argument("--verbose", action="store_true", help="Warp's banner and the fit's log lines on stderr too")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="write a synthetic clothed subject (elicit-subject/1)")
    who = s.add_mutually_exclusive_group()
    who.add_argument(
        "--seed", type=int_between(0, 2**32 - 1), default=None, help="draws a procedural person (default 0)"
    )
    who.add_argument("--person", choices=sorted(PEOPLE), help="a named person: clothes and posture of real people")
    who.add_argument("--mesh", type=Path, help="a textured OBJ of a person (metres, +y up, facing +z) instead")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--motion", default="walk_in_place", help="built-in target motion")
    s.add_argument("--size", type=int_between(16, MAX_IMAGE_SIZE), default=512, help="image size in pixels")
    s.add_argument("--spp", type=int_between(1, 4096), default=32, help="path-tracing samples per pixel")
    s.add_argument("--force", action="store_true", help="replace a non-empty --out folder")
    s.add_argument(
        "--photos",
        action="store_true",
        help="also render a back and a side photo in the motion's middle frame (multi-photo tests)",
    )
    s.set_defaults(func=_synth)

    f = sub.add_parser("fit", help="fit an avatar to a subject (two-stage ELICIT optimisation)")
    f.add_argument("subject", type=Path, help="an elicit-subject/1 folder")
    f.add_argument("--out", type=Path, required=True, help="run folder (checkpoint, previews, avatar, run.json)")
    f.add_argument("--preset", default="cpu-fast", help="cpu-fast or paper")
    f.add_argument("--config", type=Path, default=None, help="a TOML file of config keys")
    f.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override one config key (or ablation=NAME)"
    )
    f.add_argument("--resume", action="store_true", help="continue from the run folder's checkpoint")
    f.add_argument("--force", action="store_true", help="replace an earlier fit in the run folder")
    f.set_defaults(func=_fit)

    v = sub.add_parser("render", help="free-view / animation video of a fitted avatar, with a contact sheet")
    v.add_argument("run", type=Path, help="a run folder (or its avatar file)")
    v.add_argument(
        "--motion", default=None, help="built-in motion name or motion .npz (default: the subject's, or rest)"
    )
    v.add_argument("--cameras", default="orbit", help="orbit, ring, input, a rig .xml, or a subject folder")
    v.add_argument("--out", type=Path, required=True, help="OUT.mp4, OUT.gif or a folder for PNG frames")
    v.add_argument("--size", type=int_between(16, MAX_IMAGE_SIZE), default=256, help="image size in pixels")
    v.add_argument("--samples", type=int_between(1, 1024), default=64, help="samples per ray")
    v.add_argument("--fps", type=float_between(0.1, 1000.0), default=30.0)
    v.set_defaults(func=_render)

    x = sub.add_parser(
        "export", help="the avatar as an animated glTF binary (.glb): mesh, baked texture, skeleton, motion"
    )
    x.add_argument("run", type=Path, help="a run folder (or its avatar file)")
    x.add_argument("--out", type=Path, required=True, help="OUT.glb")
    x.add_argument(
        "--motion", default="walk_in_place", help="built-in motion name, motion .npz, or none (default: walk_in_place)"
    )
    x.add_argument(
        "--resolution",
        type=float_between(0.002, 0.5),
        default=None,
        help="marching-cubes voxel, metres (default: the avatar's)",
    )
    x.add_argument("--faces", type=int_between(100, 10_000_000), default=None, help="decimate to about this many faces")
    x.add_argument(
        "--texture-size",
        type=int_between(64, 8192),
        default=1024,
        help="side of the baked texture in pixels (default: 1024)",
    )
    x.add_argument(
        "--vertex-colors", action="store_true", help="colour the vertices instead of baking a UV texture (smaller)"
    )
    x.set_defaults(func=_export)

    page = sub.add_parser("view", help="a self-contained web page that shows the avatar and plays its animation")
    page.add_argument("source", type=Path, help="a run folder (exported first) or a .glb")
    page.add_argument("--out", type=Path, required=True, help="folder for index.html and avatar.glb")
    page.add_argument("--motion", default="walk_in_place", help="motion to export when SOURCE is a run folder")
    page.set_defaults(func=_view)

    d = sub.add_parser("demo", help="synthesise the default subject, fit it (cpu-fast) and render videos")
    d.add_argument("--out", type=Path, default=Path("elicit-demo"))
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one fit config key")
    d.set_defaults(func=_demo)

    b = sub.add_parser("batch", help="many avatars on Ray: prepare, fit, render and export each photo or subject")
    b.add_argument("inputs", type=Path, nargs="+", help="photos, subject folders, or folders of them")
    b.add_argument("--out", type=Path, required=True, help="batch folder: one job folder per input, summary.md")
    b.add_argument("--steps", default="prepare,fit,render,export", help="comma-separated steps to run")
    b.add_argument("--preset", default="cpu-fast", help="cpu-fast or paper")
    b.add_argument("--config", type=Path, default=None, help="a TOML file of config keys")
    b.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override one config key (or ablation=NAME)"
    )
    b.add_argument(
        "--address", default=None, help="a Ray cluster (auto, HOST:PORT or ray://HOST:PORT); default: local Ray"
    )
    b.add_argument("--cpus-per-fit", type=int_between(1, 1024), default=1, help="CPUs each job's threads use")
    b.add_argument("--size", type=int_between(16, MAX_IMAGE_SIZE), default=256, help="video and sheet size, pixels")
    b.add_argument(
        "--per-folder",
        action="store_true",
        help="a folder of photos shows one person: one multi-photo job per folder (default: a job per photo)",
    )
    b.set_defaults(func=_batch)

    a = sub.add_parser("app", help="a local web page: photos in, progress, the avatar in a 3D viewer, downloads")
    a.add_argument("--host", default="127.0.0.1", help="address to bind (default: this machine only)")
    a.add_argument("--port", type=int_between(1, 65535), default=7860)
    a.add_argument("--out", type=Path, default=Path("elicit-app"), help="folder of the job folders")
    a.add_argument("--preset", default="cpu-fast", choices=sorted(PRESETS), help="the page's default preset")
    a.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a fit config key applied to every job"
    )
    a.add_argument(
        "--address", default=None, help="a Ray cluster (auto, HOST:PORT or ray://HOST:PORT); default: local Ray"
    )
    a.add_argument(
        "--cpus-per-fit",
        type=int_between(1, 1024),
        default=None,
        help="CPUs each job asks for (default: all of this machine's, so jobs run one at a time; 1 on a cluster)",
    )
    a.add_argument("--share", action="store_true", help="also make a public gradio.live link (off by default)")
    a.set_defaults(func=_app)

    e = sub.add_parser("eval", help="novel-view and novel-pose metrics of a fitted avatar against a subject")
    e.add_argument("run", type=Path)
    e.add_argument("subject", type=Path)
    e.add_argument("--out", type=Path, required=True, help="metrics.json (grids are written beside it)")
    e.add_argument("--scale", type=unit_fraction, default=0.5, help="evaluation image scale, in (0, 1]")
    e.add_argument("--max-views", type=positive_int, default=None, help="evaluate at most this many views per split")
    e.add_argument(
        "--align",
        action="store_true",
        help="the run was fitted on another subject of this person (e.g. from prepare): align the bodies (Umeyama)",
    )
    e.set_defaults(func=_eval)

    q = sub.add_parser("prepare", help="turn photos of one person into a subject: masks, cameras and an Anny body fit")
    q.add_argument("photo", type=Path, nargs="+", help="one or more photos of one person in the same clothes")
    q.add_argument("--out", type=Path, required=True)
    q.add_argument(
        "--mask",
        type=Path,
        action="append",
        default=None,
        help="person mask, 1-, 8- or 16-bit (above half is the person); once per photo, in order "
        "(default: PHOTO_mask.png beside each photo, if there is one)",
    )
    q.add_argument("--params", type=Path, default=None, help="ELICIT/CLIFF gt_params.npz (focal_l, pred_joints)")
    q.add_argument(
        "--focal",
        type=float_between(1.0, 1e6),
        action="append",
        default=None,
        help="focal length in pixels; once for every photo, or once per photo",
    )
    q.add_argument("--motion", default="walk_in_place", help="built-in target motion")
    q.add_argument("--force", action="store_true", help="replace a non-empty --out folder")
    q.add_argument(
        "--max-megapixels", type=positive_float, default=MAX_MEGAPIXELS, help="refuse larger photos (default 40)"
    )
    q.set_defaults(func=_prepare)

    i = sub.add_parser("import", help="import ELICIT's in-the-wild layout or ZJU-MoCap as a subject")
    i.add_argument("layout", choices=["elicit-wild", "zju"])
    i.add_argument("source", type=Path)
    i.add_argument("--out", type=Path, required=True)
    i.add_argument("--motion", default="walk_in_place", help="elicit-wild: built-in target motion")
    i.add_argument("--smpl", default=None, help="SMPL model file or folder (else ELICIT_SMPL_DIR)")
    i.add_argument("--frames", type=int_between(0, 10**7), nargs="*", default=None, help="zju: frame ids")
    i.add_argument("--input-camera", type=int_between(0, 10**4), default=0, help="zju: index of the input camera")
    i.add_argument("--force", action="store_true", help="replace a non-empty --out folder")
    i.set_defaults(func=_import)

    w = sub.add_parser("weights", help="CLIP weights: fetch them (needs the network) or list what is on disk")
    w.add_argument("action", choices=["fetch", "list"])
    clip = {name: PRESETS[name].get("clip_model", FitConfig.clip_model) for name in PRESETS}
    w.add_argument("model", nargs="?", default=FitConfig.clip_model, help=f"open_clip model (presets: {clip})")
    w.add_argument("tag", nargs="?", default=FitConfig.clip_pretrained, help="open_clip pretrained tag")
    w.add_argument("--endpoint", default=None, help="a Hugging Face hub mirror (as $HF_ENDPOINT)")
    w.set_defaults(func=_weights)

    r = sub.add_parser("rig", help="write a camera rig as Mitsuba scene XML")
    r.add_argument("kind", choices=["ring", "orbit"])
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--n", type=int_between(1, 3600), default=23, help="number of cameras (orbit: frames)")
    r.add_argument("--radius", type=float_between(0.01, 1000.0), default=3.0, help="metres")
    r.add_argument(
        "--elevation",
        type=float_between(-89.0, 89.0),
        default=0.0,
        help="degrees (a camera at the pole would look along its own up)",
    )
    r.add_argument("--look-at", type=float_between(-1e4, 1e4), nargs=3, default=(0.0, 0.0, 0.0), help="metres")
    r.add_argument("--focal", type=float_between(1.0, 1e6), default=650.0, help="pixels")
    r.add_argument("--size", type=int_between(16, MAX_IMAGE_SIZE), default=512)
    r.set_defaults(func=_rigs)
    return p


def _terminate(signum, frame) -> None:
    """SIGTERM ends a command as an interruption does: every ``finally`` runs (half-written folders are removed,
    Ray is shut down) before the process exits with ``128 + signum``."""
    _TERMINATED.append(signum)
    raise SystemExit(128 + signum)


_TERMINATED: list[int] = []  # the signal that ended this command (a library may rewrap its SystemExit)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verbose:
        os.environ["ELICIT_WARP_VERBOSE"] = "1"
    else:  # libraries' warnings (torch's, numpy's) would stand between the progress bar and an error's one line
        warnings.simplefilter("ignore")
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        args.func(args)
    except ElicitError as exc:  # one line, even where a library's message it wraps has several
        print(f"elicit {args.command}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except OSError as exc:  # a read-only folder, a full disk: nothing half-written is left in place
        print(f"elicit {args.command}: error: {error_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"elicit {args.command}: interrupted", file=sys.stderr)
        return 130
    except SystemExit:
        if _TERMINATED:
            print(f"elicit {args.command}: terminated", file=sys.stderr)
            return 128 + _TERMINATED[0]
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
