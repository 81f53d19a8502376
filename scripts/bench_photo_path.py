#!/usr/bin/env python
"""Quality on the path a user takes: a body from ``elicit prepare``, not the ground-truth body.

Subjects: the three seeds of the quality benchmark, the named people (clothes and postures of real people:
an open jacket over a shirt and tie, front-only details, a held folder, crossed arms, hands in pockets, short and
long hair, a dark suit, seated, crossed legs, raised and forward arms) and, with ``--scans``, the openly licensed
3D people of ``../shared/scans`` (CC BY 4.0; their credits are in the report). For each: ``elicit prepare`` on its
input image (with its mask and focal length), ``elicit fit`` on the prepared subject (full model,
explicit-texture baseline, ``ablation=no_semantic``), and ``elicit eval --align`` against the subject's other
views. A photo fixes neither scale nor depth, so evaluation maps the prepared frame onto the truth's by the
similarity (Umeyama) between the two input-pose bodies, for evaluation only; the pose error that remains counts.
Writes ``docs/benchmarks/photo_path.{json,md}``: novel-view PSNR, SSIM, side- and rear-view PSNR, the rear views'
hole fraction and the lean of the prepared body, per subject and as means over all subjects and over the new
ones (everything but the seeds). Finished jobs are reused, so an interrupted run resumes.

    python scripts/bench_photo_path.py --scans ../shared/scans   # every subject
    python scripts/bench_photo_path.py --quick                  # a seed and a named person
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from elicit_diffrender.apps.benchtools import (
    SCAN_CREDITS,
    SYNTHETIC_SUBJECTS,
    add_job_arguments,
    benchmark_people,
    fit_and_eval,
    markdown_table,
    mean,
    run,
    synthesize_person,
    synthesize_subjects,
    worker_env,
    write_report,
)

VARIANTS = {
    "full model": [],
    "body mesh with explicit texture": ["baseline=explicit_texture"],
    "without semantic loss": ["ablation=no_semantic"],
}
MARGIN_DB = 2.0  # the full model's lead over the baseline, on the mean over all subjects and over the new ones
HOLE_TARGET = 0.02  # rear views' hole fraction, every subject
LEAN_TARGET_DEG = 3.0  # mean torso and shin lean error


def prepare_subject(elicit: str, truth: Path, out: Path, motion: str, env: dict) -> None:
    """``elicit prepare`` on the subject's input image, mask and focal length (``motion``: the prepared subject's
    training motion)."""
    if (out / "subject.json").is_file():
        return
    from elicit_diffrender.data.subject import load_subject

    subject = load_subject(truth)
    cam, frame = subject.input_camera, subject.input_frame
    focal = float(subject.cameras[cam].K[0, 0])
    cmd = [elicit, "prepare", str(subject.image_path(cam, frame)), "--mask", str(subject.mask_path(cam, frame))]
    cmd += ["--focal", str(focal), "--motion", motion, "--out", str(out)]
    run(cmd, env, out.parent / f"{out.name}.prepare.log")


def summary(name: str, per: list[dict]) -> dict:
    """Means over subjects of one method's metrics."""
    nv = [r["novel_view"] for r in per]
    return {
        "setting": name,
        "psnr": mean([m["psnr"] for m in nv]),
        "ssim": mean([m["ssim"] for m in nv]),
        "side_psnr": mean([m["side"]["psnr"] for m in nv]),
        "rear_psnr": mean([m["rear"]["psnr"] for m in nv]),
        "rear_holes": mean([m["rear"]["hole_fraction"] for m in nv]),
        "rear_spill": mean([m["rear"]["spill"] for m in nv]),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_job_arguments(p, "bench_photo_path")
    p.add_argument("--scans", type=Path, default=None, help="../shared/scans: add its scans as subjects")
    args = p.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    env = worker_env(args.jobs)
    seeds = SYNTHETIC_SUBJECTS[:1] if args.quick else SYNTHETIC_SUBJECTS
    start = time.perf_counter()
    synthesize_subjects(elicit, args.work, seeds, env)
    truths = {f"seed {seed}": args.work / f"subject_{seed}" for seed, _ in seeds}
    motions = {f"seed {seed}": motion for seed, motion in seeds}
    for name in benchmark_people(args.scans, args.quick):
        truths[name] = synthesize_person(elicit, args.work, name, "walk_in_place", env, args.scans)
        motions[name] = "walk_in_place"
    prepared = {name: args.work / f"prepared_{name.replace(' ', '_')}" for name in truths}
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        list(pool.map(lambda n: prepare_subject(elicit, truths[n], prepared[n], motions[n], env), truths))
        futures = {
            (name, variant): pool.submit(
                fit_and_eval,
                elicit,
                prepared[name],
                prepared[name] / "runs" / variant.replace(" ", "_"),
                overrides + args.set,
                env,
                truths[name],
                ["--align"],
            )
            for name in truths
            for variant, overrides in VARIANTS.items()
        }
        results = {key: f.result() for key, f in futures.items()}

    names = list(truths)
    new = [n for n in names if not n.startswith("seed ")]
    rows = [summary(v, [results[(n, v)] for n in names]) for v in VARIANTS]
    new_rows = [summary(v, [results[(n, v)] for n in new]) for v in VARIANTS] if new else []
    per_subject = []
    for n in names:
        full = results[(n, "full model")]
        lean = full["alignment"]["lean_deg"]["error"]
        row = {"subject": n, "vertex_cm": 100 * full["alignment"]["vertex_error_m"]["mean"]}
        for v, key in zip(VARIANTS, ("full", "baseline", "no_semantic"), strict=True):
            row[f"{key}_psnr"] = results[(n, v)]["novel_view"]["psnr"]
            row[f"{key}_rear"] = results[(n, v)]["novel_view"]["rear"]["psnr"]
        row["rear_holes"] = full["novel_view"]["rear"]["hole_fraction"]
        row.update({f"lean_{k}": v for k, v in lean.items()})
        per_subject.append(row)
    lean_mean = {k: mean([r[f"lean_{k}"] for r in per_subject]) for k in ("torso", "left_shin", "right_shin")}
    full, baseline = rows[0], rows[1]
    target = {
        "full_beats_baseline_by_2db_psnr": full["psnr"] - baseline["psnr"] >= MARGIN_DB,
        "on_the_new_subjects_too": not new_rows or new_rows[0]["psnr"] - new_rows[1]["psnr"] >= MARGIN_DB,
        "full_beats_no_semantic_every_subject": all(
            r["full_psnr"] > r["no_semantic_psnr"] and r["full_rear"] > r["no_semantic_rear"] for r in per_subject
        ),
        "rear_holes_at_most_2_percent": all(r["rear_holes"] <= HOLE_TARGET for r in per_subject),
        "lean_within_3_deg": all(v <= LEAN_TARGET_DEG for v in lean_mean.values()),
    }
    data = {
        "subjects": names,
        "preset": "cpu-fast",
        "encoder": results[(names[0], "full model")].get("encoder"),
        "rows": rows,
        "new_subject_rows": new_rows,
        "per_subject": per_subject,
        "mean_lean_error_deg": lean_mean,
        "target": target,
        "seconds": time.perf_counter() - start,
    }
    columns = [("setting", "method"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("side_psnr", "side PSNR"),
               ("rear_psnr", "rear PSNR"), ("rear_holes", "rear holes"), ("rear_spill", "rear spill")]  # fmt: skip
    subject_columns = [("subject", "subject")]
    for key, label in (("full", "full"), ("baseline", "baseline"), ("no_semantic", "no_semantic")):
        subject_columns += [(f"{key}_psnr", f"{label} PSNR"), (f"{key}_rear", f"{label} rear")]
    subject_columns += [("rear_holes", "full rear holes"), ("vertex_cm", "body cm"), ("lean_torso", "torso lean"),
                        ("lean_left_shin", "l shin lean"), ("lean_right_shin", "r shin lean")]  # fmt: skip
    credits = "".join(f"- {SCAN_CREDITS[n]}\n" for n in SCAN_CREDITS if n in truths)
    md = (
        f"# Photo path: a body from `elicit prepare`\n\n{len(names)} subjects ({', '.join(names)}), each prepared "
        f"from its input image, mask and focal length, fitted with `cpu-fast` (semantic encoder: "
        f"**{data['encoder']}**) and evaluated on its other views after a similarity alignment of the two input-pose "
        f"bodies (for evaluation only). Side views: 60-120 degrees from the input; rear views: more than 120. Holes: "
        f"the share of the true mask the avatar leaves empty (alpha < 0.5); spill: what it covers outside, as a share "
        f"of the mask. Lean: degrees between the prepared and the true torso and shins (see `bench_prepare.py`).\n\n"
        f"## All subjects\n\n{markdown_table(rows, columns)}\n"
        + (f"## The new subjects (all but the seeds)\n\n{markdown_table(new_rows, columns)}\n" if new_rows else "")
        + f"## Per subject (novel-view and rear-view PSNR)\n\n{markdown_table(per_subject, subject_columns)}\n"
        f"Mean lean error: {', '.join(f'{k} {v:.1f}' for k, v in lean_mean.items())} degrees.\n\n"
        f"Targets: {', '.join(f'{k}: {v}' for k, v in target.items())}.\n"
        + (f"\nScans (CC BY 4.0):\n{credits}" if credits else "")
    )
    name = "photo_path" if not args.quick else "photo_path_quick"
    json_path, md_path = write_report(args.out, name, data, md)
    print(md)
    print(f"wrote {json_path} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
