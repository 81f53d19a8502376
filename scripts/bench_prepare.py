#!/usr/bin/env python
"""``elicit prepare`` against a reference commit's, on photos with a true body and on real photos.

Inputs: the input image (with its mask and focal length) of every photo-path subject (the seeds, the named
people, among them seated, crossed and raised postures, and the scans of ``--scans`` when given), and the
shared real photos of ``--real`` (with their masks and CLIFF parameters). Both versions of ``prepare`` (the
reference exported with ``git archive``) run on every input. For each: the body's silhouette IoU against the
mask and the median keypoint error (``fit_report.json``); with a true body also the mean vertex error after a
similarity alignment and the lean of the torso and of each shin against the true one (degrees between the
directions, each in its own input camera's level frame: see ``evaluate.lean_angles``). Writes
``docs/benchmarks/prepare.{json,md}``. Finished inputs are reused.

    python scripts/bench_prepare.py --scans ../shared/scans --real ../shared/real [--reference 7adf964]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from elicit_diffrender.apps.benchtools import (
    ROOT_DIR,
    SCAN_CREDITS,
    SYNTHETIC_SUBJECTS,
    benchmark_people,
    elicit_command,
    export_commit,
    markdown_table,
    mean,
    run,
    synthesize_person,
    synthesize_subjects,
    worker_env,
    write_report,
)

REFERENCE = "7adf964"  # main on 2026-12-05, before the posture work
REAL = {  # folder -> (photo, mask, CLIFF parameters)
    "elicit_fs0000_m394": ("gt_image.png", "gt_mask.png", "gt_params.npz"),
    "elicit_fs2804_m394": ("gt_image.png", "gt_mask.png", "gt_params.npz"),
    "elicit_fs3903_m394": ("gt_image.png", "gt_mask.png", "gt_params.npz"),
    "elicit_fs7818_m394": ("gt_image.png", "gt_mask.png", "gt_params.npz"),
    "pifu_ryota": ("ryota.png", "ryota_mask.png", None),
}
IOU_DROP = 0.005  # an IoU lower than the reference's by more than this is a drop
KEYPOINT_RISE_PX = 0.5  # a median keypoint error higher than the reference's by more than this is a drop
LEAN_TARGET_DEG = 3.0  # mean torso and shin lean error over the inputs with a true body


def true_body_metrics(prepared: Path, truth: Path) -> dict:
    """Vertex error after the similarity alignment and lean errors of the prepared body against the true one."""
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.outputs.evaluate import align_bodies

    aligned = align_bodies(load_subject(prepared), load_subject(truth))
    lean = aligned.lean_error
    return {"vertex_error_cm": 100 * float(aligned.residual.mean()), **{f"lean_{k}_deg": v for k, v in lean.items()}}


def true_body_iou(truth: Path) -> float:
    """The silhouette IoU of the true body (in the input pose, seen by the input camera) against the input mask,
    as ``prepare`` reports its own body's: what a perfect body scores where the mask also holds clothes and hair."""
    from elicit_diffrender.data.mesh_render import MeshRenderer
    from elicit_diffrender.data.subject import load_subject

    subject = load_subject(truth)
    camera, frame = subject.input_camera, subject.input_frame
    posed = subject.body.pose(*subject.motion.frame(subject.input_index))
    body = MeshRenderer(subject.body.faces).render(posed.vertices, [subject.cameras[camera]], ("mask",))["mask"][0] > 0
    mask = subject.mask(camera, frame) > 0.5
    return float((body & mask).sum() / max((body | mask).sum(), 1))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference", default=REFERENCE, help=f"commit to compare against (default {REFERENCE})")
    p.add_argument("--scans", type=Path, default=None, help="../shared/scans: add its scans as inputs")
    p.add_argument("--real", type=Path, default=None, help="../shared/real: add its photos as inputs")
    p.add_argument("--jobs", type=int, default=2, help="inputs prepared side by side (each single-threaded)")
    p.add_argument("--work", type=Path, default=ROOT_DIR / "runs" / "bench_prepare")
    p.add_argument("--out", type=Path, default=ROOT_DIR / "docs" / "benchmarks")
    args = p.parse_args()
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.inputs.mediapipe_bridge import mediapipe_python

    elicit = str(Path(sys.executable).with_name("elicit"))
    # Both versions use this checkout's MediaPipe environment (the exported reference has none beside it).
    env = {**worker_env(args.jobs), "ELICIT_MEDIAPIPE_PYTHON": mediapipe_python() or ""}
    start = time.perf_counter()
    synthesize_subjects(elicit, args.work, SYNTHETIC_SUBJECTS, env)
    truths = {f"seed {seed}": args.work / f"subject_{seed}" for seed, _ in SYNTHETIC_SUBJECTS}
    for name in benchmark_people(args.scans):
        truths[name] = synthesize_person(elicit, args.work, name, "walk_in_place", env, args.scans)
    inputs = {}  # name -> prepare's arguments
    for name, truth in truths.items():
        subject = load_subject(truth)
        cam, frame = subject.input_camera, subject.input_frame
        inputs[name] = [str(subject.image_path(cam, frame)), "--mask", str(subject.mask_path(cam, frame)),
                        "--focal", str(float(subject.cameras[cam].K[0, 0]))]  # fmt: skip
    for name, (photo, mask, params) in REAL.items() if args.real is not None else ():
        folder = args.real / name
        inputs[name] = [str(folder / photo), "--mask", str(folder / mask)]
        inputs[name] += ["--params", str(folder / params)] if params else []
    sha = export_commit(args.reference, args.work / "reference_code")
    versions = {"reference": args.work / "reference_code", "this checkout": ROOT_DIR}

    def prepare(version: str, name: str) -> dict:
        out = args.work / version.replace(" ", "_") / name.replace(" ", "_")
        if not (out / "fit_report.json").is_file():
            side_env = {**env, "PYTHONPATH": str(versions[version])}
            cmd = [*elicit_command(versions[version]), "prepare", *inputs[name], "--out", str(out), "--force"]
            run(cmd, side_env, out.parent / f"{out.name}.log")
        report = json.loads((out / "fit_report.json").read_text())
        row = {"iou": report["silhouette_iou"], "keypoint_px": report.get("keypoint_error_px", {}).get("median")}
        if name in truths:
            row.update(true_body_metrics(out, truths[name]))
        return row

    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        jobs = {(v, n): pool.submit(prepare, v, n) for v in versions for n in inputs}
        results = {key: job.result() for key, job in jobs.items()}

    rows = []
    for name in inputs:
        ref, new = results[("reference", name)], results[("this checkout", name)]
        row = {"input": name, "true_body": name in truths}
        row["iou_truth"] = true_body_iou(truths[name]) if name in truths else None
        for key in ref:
            row[f"{key}_ref"], row[f"{key}_new"] = ref[key], new[key]
        row["dropped"] = new["iou"] < ref["iou"] - IOU_DROP or (
            None not in (new["keypoint_px"], ref["keypoint_px"])
            and new["keypoint_px"] > ref["keypoint_px"] + KEYPOINT_RISE_PX
        )
        rows.append(row)
    with_truth = [r for r in rows if r["true_body"]]
    lean = {
        version: {
            part: mean([r[f"lean_{part}_deg_{version}"] for r in with_truth])
            for part in ("torso", "left_shin", "right_shin")
        }
        for version in ("ref", "new")
    }
    truth_below = [r["input"] for r in with_truth if r["iou_truth"] < min(r["iou_ref"], r["iou_new"])]
    target = {
        "no_input_drops": not any(r["dropped"] for r in rows),
        "lean_within_3_deg": all(v <= LEAN_TARGET_DEG for v in lean["new"].values()),
    }
    data = {"reference_commit": sha, "rows": rows, "mean_lean_deg": lean, "target": target,
            "truth_iou_below_both": truth_below, "seconds": time.perf_counter() - start}  # fmt: skip
    columns = [("input", "input"), ("iou_truth", "IoU truth")]
    for key, label in (("iou", "IoU"), ("keypoint_px", "kp px"), ("vertex_error_cm", "vertex cm"),
                       ("lean_torso_deg", "torso lean"), ("lean_left_shin_deg", "l shin"),
                       ("lean_right_shin_deg", "r shin")):  # fmt: skip
        columns += [(f"{key}_ref", f"{label} ref"), (f"{key}_new", label)]
    columns.append(("dropped", "dropped"))
    credits = "".join(f"- {SCAN_CREDITS[n]}\n" for n in SCAN_CREDITS if n in inputs)
    md = (
        f"# `elicit prepare` against `{sha[:10]}`\n\n"
        f"`scripts/bench_prepare.py`: both versions of `prepare` on the input image, mask and focal length of every "
        f"photo-path subject (a true body: seeds, named people, scans) and on the shared real photos (masks and "
        f"CLIFF parameters). IoU: the body's silhouette against the mask; kp: median keypoint error; vertex: mean "
        f"error after a similarity alignment onto the true body; lean: degrees between the fitted and the true "
        f"torso (pelvis to neck) and shins, each in its own input camera's level frame. IoU truth: the true body's "
        f"silhouette against the same mask.\n\n"
        f"{markdown_table(rows, columns)}\n"
        f"The true body's IoU is below both versions' on {len(truth_below)} of the {len(with_truth)} inputs with a "
        f"true body: the masks hold clothes and hair, and a body swollen into them scores higher than the true one. "
        f"There the vertex error, not the IoU, says which body is nearer the truth.\n\n"
        f"Mean lean error over the {len(with_truth)} inputs with a true body: reference "
        f"{', '.join(f'{k} {v:.1f}' for k, v in lean['ref'].items())}; this checkout "
        f"{', '.join(f'{k} {v:.1f}' for k, v in lean['new'].items())} degrees.\n\n"
        f"Targets: {', '.join(f'{k}: {v}' for k, v in target.items())}.\n"
        + (f"\nScans (CC BY 4.0):\n{credits}" if credits else "")
    )
    json_path, md_path = write_report(args.out, "prepare", data, md)
    print(md)
    print(f"wrote {json_path} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
