#!/usr/bin/env python
"""Several photos of one person: does a back photo give a back that is seen, not guessed?

For each synthetic subject (``elicit synth --photos``: a seed whose patterns wrap around the body, and people
with front-only details, a held folder and long hair), ``elicit prepare`` makes three subjects from its photos,
each photo with its mask and focal length:

* one photo: the front (the input camera in the input frame);
* front + back: the front, and a photo from about 180 degrees in another frame and pose of the motion;
* front + side: the front, and a photo from about 90 degrees in that other frame.

Each is fitted with ``cpu-fast`` (front + back also with ``multi_photo=reference``, the paper's use of extra
photos as semantic references only) and evaluated with ``elicit eval --align`` on the other ring views of the
input frame, none of which any photo shows in that pose: novel-view PSNR, and its front (up to 60 degrees from
the input), side (60-120) and rear (beyond 120) splits. The prepared cameras of the extra photos are measured
against the true ones (:func:`camera_error`). Writes ``docs/benchmarks/multi_photo.{json,md}`` and a contact
sheet of each subject's back (``multi_photo_backs.png``) and one subject from four sides with one photo and with
two (``multi_photo_twins.png``). Finished jobs are reused.

    python scripts/bench_multi_photo.py            # every subject
    python scripts/bench_multi_photo.py --quick    # one subject
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from elicit_diffrender.apps.benchtools import (
    add_job_arguments,
    fit_and_eval,
    markdown_table,
    mean,
    run,
    worker_env,
    write_report,
)

SUBJECTS = ("seed_1", "open_jacket_tie", "front_details", "held_folder", "long_hair")
REFERENCE = "front + back, multi_photo=reference"
SETTINGS = {  # setting -> (the photos it prepares from, fit overrides)
    "one photo": (("front",), []),
    "front + back": (("front", "back"), []),
    REFERENCE: (("front", "back"), ["multi_photo=reference"]),
    "front + side": (("front", "side"), []),
}
REAR_GAIN_DB = 4.0  # front + back over one photo, rear views, mean over subjects
FRONT_DROP_DB = 0.2  # at most this much lost on the front views
CAMERA_CM, CAMERA_DEG = 10.0, 5.0  # the second camera against the truth, after aligning its body


def synthesize(elicit: str, work: Path, name: str, env: dict) -> Path:
    path = work / f"subject_{name}"
    if not (path / "subject.json").is_file():
        who = ["--seed", name.split("_")[1]] if name.startswith("seed_") else ["--person", name]
        run([elicit, "synth", *who, "--photos", "--out", str(path)], env, work / f"synth_{name}.log")
    return path


def photo_views(truth: Path) -> dict[str, tuple[str, int]]:
    """The synthetic subject's photos: ``front`` is its input view, ``back`` and ``side`` its extra photos."""
    meta = json.loads((truth / "subject.json").read_text())
    photos = {k: tuple(v) for k, v in meta["synthetic"]["photos"].items()}
    return {"front": (meta["input"]["camera"], meta["input"]["frame"]), **photos}


def prepare(elicit: str, truth: Path, photos: tuple[str, ...], out: Path, env: dict) -> Path:
    if (out / "subject.json").is_file():
        return out
    from elicit_diffrender.data.subject import load_subject

    subject, views = load_subject(truth), photo_views(truth)
    cmd = [elicit, "prepare"]
    masks, focals = [], []
    for photo in photos:
        cam, frame = views[photo]
        cmd.append(str(subject.image_path(cam, frame)))
        masks += ["--mask", str(subject.mask_path(cam, frame))]
        focals += ["--focal", str(float(subject.cameras[cam].K[0, 0]))]
    run([*cmd, *masks, *focals, "--out", str(out)], env, out.parent / f"{out.name}.prepare.log")
    return out


def prepared_dir(work: Path, name: str, photos: tuple[str, ...]) -> Path:
    return work / f"prepared_{name}_{'_'.join(photos)}"


def camera_errors(prepared: Path, truth: Path, photos: tuple[str, ...]) -> dict[str, dict[str, float]]:
    """Each extra photo's prepared camera against the true one: centimetres and degrees."""
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.outputs.evaluate import camera_error

    fitted, true = load_subject(prepared), load_subject(truth)
    views = photo_views(truth)
    out = {}
    for k, photo in enumerate(photos[1:], start=1):
        metres, degrees = camera_error(fitted, fitted.inputs[k], true, views[photo])
        out[photo] = {"cm": 100.0 * metres, "degrees": degrees}
    return out


def job(elicit: str, work: Path, name: str, setting: str, env: dict) -> dict:
    truth = work / f"subject_{name}"
    photos, overrides = SETTINGS[setting]
    prepared = prepare(elicit, truth, photos, prepared_dir(work, name, photos), env)
    run_dir = prepared / "runs" / ("reference" if overrides else "full")
    metrics = fit_and_eval(elicit, prepared, run_dir, overrides, env, truth, ["--align"])
    nv = metrics["novel_view"]
    row = {
        "subject": name,
        "setting": setting,
        "psnr": nv["psnr"],
        "ssim": nv["ssim"],
        "front_psnr": nv["front"]["psnr"],
        "side_psnr": nv["side"]["psnr"],
        "rear_psnr": nv["rear"]["psnr"],
        "rear_holes": nv["rear"]["hole_fraction"],
        "grid": str(Path(run_dir) / "eval" / "novel_view_grid.png"),
    }
    if len(photos) > 1:
        row["cameras"] = camera_errors(prepared, truth, photos)
    return row


def view_tiles(work: Path, name: str, camera: str, settings: list[str]) -> list[np.ndarray]:
    """One ring camera of a subject's input frame: the truth, then the avatar of each setting (half size)."""
    from elicit_diffrender.data.subject import load_subject
    from elicit_diffrender.model.load import load_avatar
    from elicit_diffrender.outputs.evaluate import align_bodies, camera_in_frame

    truth = load_subject(work / f"subject_{name}")
    tiles = [truth.image(camera, truth.input_frame)[::2, ::2]]
    for setting in settings:
        photos, overrides = SETTINGS[setting]
        prepared = prepared_dir(work, name, photos)
        fitted = load_subject(prepared)
        avatar = load_avatar(prepared / "runs" / ("reference" if overrides else "full"))
        aligned = camera_in_frame(truth.cameras[camera], *align_bodies(fitted, truth).similarity)
        tiles.append(avatar.render_pose(aligned.scaled(0.5), *fitted.motion.frame(fitted.input_index))["rgb"])
    return tiles


def write_sheets(work: Path, subjects: list[str], out: Path) -> None:
    """``multi_photo_backs.png``: each subject's back (the ring camera of the back photo, in the input pose, which
    no photo shows), truth then every setting; ``multi_photo_twins.png``: the first subject with front-only details
    from four sides, truth, one photo and front + back."""
    from elicit_diffrender.core.io import write_image

    rows = [np.concatenate(view_tiles(work, n, photo_views(work / f"subject_{n}")["back"][0], list(SETTINGS)), 1)
            for n in subjects]  # fmt: skip
    write_image(out / "multi_photo_backs.png", np.concatenate(rows, 0))
    name = next((n for n in subjects if not n.startswith("seed_")), subjects[0])
    ring = sorted(json.loads((work / f"subject_{name}" / "cameras.json").read_text()))
    quarter = [ring[round(k * len(ring) / 4) % len(ring)] for k in range(4)]
    columns = [np.concatenate(view_tiles(work, name, cam, ["one photo", "front + back"]), 0) for cam in quarter]
    write_image(out / "multi_photo_twins.png", np.concatenate(columns, 1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_job_arguments(parser, "bench_multi_photo")
    args = parser.parse_args()
    elicit = str(Path(sys.executable).with_name("elicit"))
    work, env = args.work, worker_env(args.jobs)
    work.mkdir(parents=True, exist_ok=True)
    subjects = SUBJECTS[:1] if args.quick else SUBJECTS
    start = time.perf_counter()
    for name in subjects:
        synthesize(elicit, work, name, env)
    photo_sets = list(dict.fromkeys(photos for photos, _ in SETTINGS.values()))
    preparations = [(name, photos) for name in subjects for photos in photo_sets]
    jobs = [(name, setting) for name in subjects for setting in SETTINGS]
    with ThreadPoolExecutor(args.jobs) as pool:  # every subject prepared once, before the fits that share it
        list(pool.map(lambda p: prepare(elicit, work / f"subject_{p[0]}", p[1], prepared_dir(work, *p), env),
                      preparations))  # fmt: skip
        rows = list(pool.map(lambda j: job(elicit, work, *j, env), jobs))
    summary = []
    for setting in SETTINGS:
        mine = [r for r in rows if r["setting"] == setting]
        keys = ("psnr", "ssim", "front_psnr", "side_psnr", "rear_psnr", "rear_holes")
        summary.append({"setting": setting, **{k: mean([r[k] for r in mine]) for k in keys}})
    by = {(r["subject"], r["setting"]): r for r in rows}
    per_subject = []
    for name in subjects:
        one, two, ref = by[(name, "one photo")], by[(name, "front + back")], by[(name, REFERENCE)]
        side = by[(name, "front + side")]
        per_subject.append(
            {
                "subject": name,
                **{
                    f"{k} {label}": r[k]
                    for label, r in (("one", one), ("back", two), ("ref", ref), ("side", side))
                    for k in ("psnr", "rear_psnr")
                },  # fmt: skip
                "rear gain": two["rear_psnr"] - one["rear_psnr"],
                "front change": two["front_psnr"] - one["front_psnr"],
                "back camera cm": two["cameras"]["back"]["cm"],
                "back camera deg": two["cameras"]["back"]["degrees"],
                "side camera cm": side["cameras"]["side"]["cm"],
                "side camera deg": side["cameras"]["side"]["degrees"],
            }
        )
    gain = mean([p["rear gain"] for p in per_subject])
    drop = mean([p["front change"] for p in per_subject])
    targets = {
        "rear_gain_at_least_4db": gain >= REAR_GAIN_DB,
        "front_drop_at_most_0_2db": drop >= -FRONT_DROP_DB,
        "full_beats_reference_every_subject": all(p["psnr back"] > p["psnr ref"] for p in per_subject),
        "back_camera_within_10cm_5deg": all(
            p["back camera cm"] <= CAMERA_CM and p["back camera deg"] <= CAMERA_DEG for p in per_subject
        ),
    }
    write_sheets(work, list(subjects), args.out)
    data = {
        "subjects": list(subjects),
        "summary": summary,
        "per_subject": per_subject,
        "rows": rows,
        "rear_gain_db": gain,
        "front_change_db": drop,
        "targets": targets,
        "seconds": time.perf_counter() - start,
    }
    md = [
        "# Several photos of one person\n",
        f"{len(subjects)} synthetic subjects ({', '.join(subjects)}), each prepared by `elicit prepare` from one "
        "photo (the front), from the front and a back photo (about 180 degrees, another frame and pose), and from "
        "the front and a side photo (about 90 degrees, that frame); fitted with `cpu-fast` and evaluated with "
        "`elicit eval --align` on the other ring views of the input frame. Front: up to 60 degrees from the input; "
        "side: 60-120; rear: beyond 120. `multi_photo=reference` uses the back photo only as a semantic reference "
        "(the paper's variant); without CLIP weights (the semantic prior is then the weights-free completion) "
        "nothing reads it. Cameras: each extra photo's prepared camera against the true one, after the "
        "similarity that maps its prepared body onto the true body in that photo's pose.\n",
        "## Means over the subjects\n",
        markdown_table(
            summary,
            [
                ("setting", "setting"),
                ("psnr", "PSNR"),
                ("ssim", "SSIM"),
                ("front_psnr", "front PSNR"),
                ("side_psnr", "side PSNR"),
                ("rear_psnr", "rear PSNR"),
                ("rear_holes", "rear holes"),
            ],
        ),  # fmt: skip
        f"\nFront + back over one photo: rear views {gain:+.2f} dB, front views {drop:+.2f} dB.\n",
        "\n## Per subject (novel-view and rear-view PSNR; cameras against the truth after aligning their bodies)\n",
        markdown_table(per_subject, [(k, k) for k in per_subject[0]]),
        f"\nTargets: {', '.join(f'{k}: {v}' for k, v in targets.items())}.\n",
        "\nThe back of every subject in the input pose, which no photo shows "
        "([multi_photo_backs.png](multi_photo_backs.png), a row each): truth, then one photo, front + back, "
        "front + back as reference, front + side. The first named person from four sides "
        "([multi_photo_twins.png](multi_photo_twins.png)): truth, one photo, front + back.\n",
    ]
    write_report(args.out, "multi_photo", data, "\n".join(md))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
