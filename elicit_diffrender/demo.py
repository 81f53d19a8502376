"""``elicit demo``: the shipped default subject, end to end, offline.

Synthesise the default subject (seed 0), fit it with the ``cpu-fast`` preset, then render a
turntable, an animation in a motion the avatar never saw, and a contact sheet
(input | front | side | back | novel pose), and export the avatar doing that motion as ``avatar.glb``
with a web page that plays it (``viewer/index.html``).
Synthesis and the fit are skipped when their results already exist, so an interrupted demo picks
up where it stopped.
"""

from __future__ import annotations

import time
from pathlib import Path

from .animate import contact_sheet, load_avatar, render_sequence, write_video
from .avatar import AVATAR_FILE
from .config import make_config
from .export import export_glb
from .io import write_json
from .motions import builtin_motion
from .rigs import read_rig, shipped_rig_path
from .viewer import write_viewer

DEMO_SEED = 0
DEMO_MOTION = "walk_in_place"  # the training motion
NOVEL_MOTION = "squat"  # shown only after fitting


def run_demo(out: str | Path = "elicit-demo", size: int = 256, overrides: list[str] | None = None) -> dict:
    from .fit import fit
    from .fit.checkpoint import CHECKPOINT
    from .subject import SubjectError, load_subject
    from .synth import synthesize

    out = Path(out)
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    subject_dir = out / "subject"
    try:
        subject = load_subject(subject_dir)
    except SubjectError:
        synthesize(DEMO_SEED, subject_dir, motion_name=DEMO_MOTION, force=True)
        subject = load_subject(subject_dir)
    times["synth"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    run_dir = out / "run"
    if not (run_dir / AVATAR_FILE).is_file():
        cfg = make_config("cpu-fast", None, overrides)
        fit(subject, cfg, run_dir, resume=(run_dir / CHECKPOINT).is_file())
    times["fit"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    avatar = load_avatar(run_dir)
    orbit = [c.scaled(size / c.width) for c in read_rig(shipped_rig_path("orbit"))]
    ring = [c.scaled(size / c.width) for c in read_rig(shipped_rig_path("ring"))]
    turntable = render_sequence(avatar, orbit, subject.motion.select([subject.input_index]), desc="turntable")
    write_video(out / "turntable.mp4", turntable)
    novel = builtin_motion(NOVEL_MOTION, avatar.body)
    front = [c.scaled(size / c.width) for c in read_rig(shipped_rig_path("input"))]
    animation = render_sequence(avatar, [ring[2]], novel, desc="animation")  # a three-quarter view
    write_video(out / "animation.mp4", animation)
    times["render"] = time.perf_counter() - t2

    # Contact sheet: input | front | side | back | novel pose.
    cam_in = subject.cameras[subject.input_camera]
    scale = size / max(cam_in.width, cam_in.height)
    target = subject.image(subject.input_camera, subject.input_frame)
    step = max(1, round(1 / scale))
    tiles = [target[::step, ::step]]
    input_pose = subject.motion.frame(subject.input_index)
    for cam in (front[0], ring[len(ring) // 4], ring[len(ring) // 2]):
        tiles.append(avatar.render_pose(cam, *input_pose)["rgb"])
    tiles.append(animation[len(animation) // 2])
    sheet = contact_sheet(
        tiles, ["input", "front", "side", "back", f"novel pose ({NOVEL_MOTION})"], out / "contact_sheet.png"
    )
    t3 = time.perf_counter()
    glb = export_glb(avatar, out / "avatar.glb", novel)["path"]
    page = write_viewer(glb, out / "viewer")
    times["export"] = time.perf_counter() - t3
    times["total"] = time.perf_counter() - t0
    summary = {
        "subject": str(subject_dir),
        "run": str(run_dir),
        "turntable": str(out / "turntable.mp4"),
        "animation": str(out / "animation.mp4"),
        "contact_sheet": str(sheet),
        "avatar_glb": glb,
        "viewer": str(page),
        "seconds": times,
    }
    write_json(out / "demo.json", summary)
    return summary
