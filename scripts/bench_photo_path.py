#!/usr/bin/env python
"""Quality on the path a user takes: a body from ``elicit prepare``, not the ground-truth body.

For every synthetic subject: ``elicit prepare`` on its input image (with its mask and focal
length), ``elicit fit`` on the prepared subject (full model, explicit-texture baseline,
``ablation=no_semantic``), and ``elicit eval --align`` against the synthetic subject's other
views. A photo fixes neither scale nor depth, so evaluation maps the prepared frame onto the
ground truth's by the similarity (Umeyama) between the two input-pose bodies, for evaluation only;
the pose error that remains counts. Writes ``docs/benchmarks/photo_path.{json,md}``: novel-view
PSNR, SSIM and rear-view PSNR (cameras more than 120 degrees from the input) per subject and mean.
Finished jobs are reused, so an interrupted run resumes.

    python scripts/bench_photo_path.py            # 3 subjects
    python scripts/bench_photo_path.py --quick    # 1 subject
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from elicit_diffrender.apps.benchtools import (
    SYNTHETIC_SUBJECTS,
    add_job_arguments,
    fit_and_eval,
    markdown_table,
    mean,
    run,
    synthesize_subjects,
    worker_env,
    write_report,
)

VARIANTS = {
    "full model": [],
    "body mesh with explicit texture": ["baseline=explicit_texture"],
    "without semantic loss": ["ablation=no_semantic"],
}


def prepare_subject(elicit: str, truth: Path, out: Path, motion: str, env: dict) -> None:
    """``elicit prepare`` on the synthetic subject's input image, mask and focal length."""
    if (out / "subject.json").is_file():
        return
    from elicit_diffrender.data.subject import load_subject

    subject = load_subject(truth)
    cam, frame = subject.input_camera, subject.input_frame
    focal = float(subject.cameras[cam].K[0, 0])
    cmd = [elicit, "prepare", str(subject.image_path(cam, frame)), "--mask", str(subject.mask_path(cam, frame))]
    cmd += ["--focal", str(focal), "--motion", motion, "--out", str(out)]
    run(cmd, env, out.parent / f"{out.name}.prepare.log")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_job_arguments(p, "bench_photo_path")
    args = p.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    env = worker_env(args.jobs)
    subjects = SYNTHETIC_SUBJECTS[:1] if args.quick else SYNTHETIC_SUBJECTS
    start = time.perf_counter()
    synthesize_subjects(elicit, args.work, subjects, env)
    for seed, motion in subjects:
        prepare_subject(elicit, args.work / f"subject_{seed}", args.work / f"prepared_{seed}", motion, env)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = {
            (seed, name): pool.submit(
                fit_and_eval,
                elicit,
                args.work / f"prepared_{seed}",
                args.work / f"prepared_{seed}" / "runs" / name.replace(" ", "_"),
                overrides + args.set,
                env,
                args.work / f"subject_{seed}",
                ["--align"],
            )
            for name, overrides in VARIANTS.items()
            for seed, _ in subjects
        }
        results = {key: f.result() for key, f in futures.items()}

    rows = []
    for name in VARIANTS:
        per = [results[(seed, name)] for seed, _ in subjects]
        rows.append(
            {
                "setting": name,
                "psnr": mean([r["novel_view"]["psnr"] for r in per]),
                "ssim": mean([r["novel_view"]["ssim"] for r in per]),
                "rear_psnr": mean([r["novel_view"]["rear"]["psnr"] for r in per]),
                "per_subject_psnr": [r["novel_view"]["psnr"] for r in per],
                "per_subject_ssim": [r["novel_view"]["ssim"] for r in per],
                "per_subject_rear_psnr": [r["novel_view"]["rear"]["psnr"] for r in per],
                "fit_seconds": mean([r.get("fit_seconds") for r in per]),
                "encoder": per[0].get("encoder"),
            }
        )
    full, baseline, no_semantic = rows
    alignment = [
        {**results[(seed, "full model")]["alignment"], "fitted_subject": f"prepared_{seed}"} for seed, _ in subjects
    ]
    target = {
        "full_beats_baseline_by_2db_psnr": full["psnr"] - baseline["psnr"] >= 2.0,
        "full_beats_baseline_ssim": full["ssim"] > baseline["ssim"],
        "full_beats_no_semantic_every_subject": all(
            f > n for f, n in zip(full["per_subject_psnr"], no_semantic["per_subject_psnr"], strict=True)
        ),
    }
    data = {
        "subjects": [{"seed": s, "motion": m} for s, m in subjects],
        "preset": "cpu-fast",
        "encoder": full["encoder"],
        "alignment": alignment,
        "rows": rows,
        "target": target,
        "seconds": time.perf_counter() - start,
    }
    columns = [("setting", "method"), ("psnr", "PSNR"), ("ssim", "SSIM"), ("rear_psnr", "rear-view PSNR")]
    per_subject = [
        {"subject": f"seed {seed}", **{name: results[(seed, name)]["novel_view"]["psnr"] for name in VARIANTS}}
        for seed, _ in subjects
    ]
    align_rows = [
        {"subject": f"seed {seed}", "scale": a["scale"], "mean_cm": 100 * a["vertex_error_m"]["mean"]}
        for (seed, _), a in zip(subjects, alignment, strict=True)
    ]
    md = (
        f"# Photo path: a body from `elicit prepare`\n\n{len(subjects)} synthetic subject(s) "
        f"({', '.join(f'seed {s} / {m}' for s, m in subjects)}), each prepared from its input image, mask and "
        f"focal length, fitted with `cpu-fast` (semantic encoder: **{full['encoder']}**) and evaluated on the "
        f"synthetic subject's other views after a similarity alignment of the two input-pose bodies (for evaluation "
        f"only). Rear views: cameras more than 120 degrees from the input. Mean over subjects.\n\n"
        f"{markdown_table(rows, columns)}\n"
        f"## Novel-view PSNR per subject\n\n"
        f"{markdown_table(per_subject, [('subject', 'subject'), *((n, n) for n in VARIANTS)])}\n"
        f"## Body after alignment (prepared against ground truth)\n\n"
        f"{markdown_table(align_rows, [('subject', 'subject'), ('scale', 'scale'), ('mean_cm', 'vertex error, cm')])}"
        f"\nTargets: {', '.join(f'{k}: {v}' for k, v in target.items())}.\n"
    )
    name = "photo_path" if not args.quick else "photo_path_quick"
    json_path, md_path = write_report(args.out, name, data, md)
    print(md)
    print(f"wrote {json_path} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
