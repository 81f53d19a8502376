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

from ..core.io import write_json
from ..data.motions import builtin_motion
from ..fit.config import make_config
from ..model.avatar import AVATAR_FILE
from ..model.load import load_avatar
from ..outputs.export import export_glb
from ..outputs.video import NOVEL_MOTION, write_showcase
from ..outputs.viewer import write_viewer

DEMO_SEED = 0
DEMO_MOTION = "walk_in_place"  # the training motion


def run_demo(out: str | Path = "elicit-demo", size: int = 256, overrides: list[str] | None = None) -> dict:
    from ..data.subject import SubjectError, load_subject
    from ..fit.checkpoint import CHECKPOINT
    from ..fit.run import fit
    from ..inputs.synth import synthesize

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
    shown = write_showcase(avatar, subject, out, size)
    times["render"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    glb = export_glb(avatar, out / "avatar.glb", builtin_motion(NOVEL_MOTION, avatar.body))["path"]
    page = write_viewer(glb, out / "viewer")
    times["export"] = time.perf_counter() - t3
    times["total"] = time.perf_counter() - t0
    summary = {
        "subject": str(subject_dir),
        "run": str(run_dir),
        **{key: str(path) for key, path in shown.items()},
        "avatar_glb": glb,
        "viewer": str(page),
        "seconds": times,
    }
    write_json(out / "demo.json", summary)
    return summary
