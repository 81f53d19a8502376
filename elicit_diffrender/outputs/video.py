"""Free-view and animation videos of a fitted avatar, and contact sheets.

Video frame ``k`` shows pose ``k mod F`` of the motion from camera ``k mod C`` of the rig, so an orbit
rig with a held pose is a turntable, one camera with a motion is an animation, and both together a
free-view animation. Shipped rigs live in the body frame (pelvis at the origin, +y up, facing +z),
where built-in motions are defined too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..core.cameras import Camera
from ..core.errors import ElicitError
from ..core.io import atomic_write, write_image
from ..data.motions import Motion, load_motion
from ..data.rigs import read_rig, shipped_rig_path
from ..model.load import load_avatar

VIDEO_SUFFIXES = (".mp4", ".gif")


class AnimateError(ElicitError):
    """A render request that cannot be served."""


def resolve_cameras(spec: str, size: int) -> tuple[list[Camera], Motion | None]:
    """Cameras from ``orbit``, ``ring``, ``input``, a rig XML file or a subject folder (+ its motion)."""
    if spec in ("orbit", "ring", "input"):
        cams = read_rig(shipped_rig_path(spec))
        return [c.scaled(size / c.width) for c in cams], None
    path = Path(spec)
    if path.is_dir():
        from ..data.subject import load_subject

        subject = load_subject(path)
        cams = [subject.cameras[subject.input_camera]] + [
            c for n, c in subject.cameras.items() if n != subject.input_camera
        ]
        return [c.scaled(size / max(c.width, c.height)) for c in cams], subject.motion
    if path.suffix == ".xml":
        return [c.scaled(size / max(c.width, c.height)) for c in read_rig(path)], None
    raise AnimateError(f"--cameras {spec!r}: expected orbit, ring, input, a rig .xml file or a subject folder")


def render_sequence(
    avatar,
    cameras: list[Camera],
    motion: Motion,
    n_samples: int = 64,
    n_frames: int | None = None,
    desc: str = "render",
) -> list[np.ndarray]:
    """RGB frames (H, W, 3) in [0, 1] on black: frame k is pose k mod F from camera k mod C."""
    n = n_frames or max(len(cameras), len(motion))
    frames = []
    for k in tqdm(range(n), desc=desc, unit="frame", leave=False):
        camera = cameras[k % len(cameras)]
        frames.append(avatar.render_pose(camera, *motion.frame(k % len(motion)), n_samples)["rgb"])
    return frames


def write_video(path: str | Path, frames: list[np.ndarray], fps: float = 30.0) -> Path:
    import imageio.v2 as imageio

    path = Path(path)
    if path.suffix not in VIDEO_SUFFIXES:
        raise AnimateError(f"{path}: video output must end in {VIDEO_SUFFIXES} (or name a folder for PNG frames)")
    data = [(np.clip(f, 0, 1) * 255 + 0.5).astype(np.uint8) for f in frames]

    def write(tmp: Path) -> None:
        if path.suffix == ".gif":
            imageio.mimsave(tmp, data, format="GIF", duration=1000.0 / fps, loop=0)
        else:
            imageio.mimsave(tmp, data, format="FFMPEG", fps=fps, macro_block_size=1, quality=7)

    return atomic_write(path, write)


def contact_sheet(tiles: list[np.ndarray], captions: list[str], path: str | Path) -> Path:
    """Tiles side by side with a caption strip above each."""
    from PIL import Image, ImageDraw

    h = max(t.shape[0] for t in tiles)
    cols = []
    for tile, text in zip(tiles, captions, strict=True):
        img = np.zeros((h + 18, tile.shape[1], 3), dtype=np.float32)
        img[18 : 18 + tile.shape[0]] = tile[..., :3]
        pil = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
        ImageDraw.Draw(pil).text((4, 3), text, fill=(255, 255, 255))
        cols.append(np.asarray(pil).astype(np.float32) / 255.0)
    return write_image(path, np.concatenate(cols, 1))


def render_command(
    run: str | Path,
    motion_spec: str | None,
    cameras_spec: str,
    out: str | Path,
    size: int = 256,
    n_samples: int = 64,
    fps: float = 30.0,
) -> list[Path]:
    """``elicit render``: a video (or PNG frames) and a contact sheet; returns the written paths."""
    avatar = load_avatar(run)
    cameras, subject_motion = resolve_cameras(cameras_spec, size)
    if motion_spec is None:
        motion = subject_motion or load_motion("rest", avatar.body)
    else:
        motion = load_motion(motion_spec, avatar.body)
    frames = render_sequence(avatar, cameras, motion, n_samples)
    out = Path(out)
    written = []
    if out.suffix in VIDEO_SUFFIXES:
        written.append(write_video(out, frames, fps))
        sheet_path = out.with_name(out.stem + "_contact.png")
    else:
        for k, frame in enumerate(frames):
            written.append(write_image(out / f"{k:05d}.png", frame))
        sheet_path = out / "contact_sheet.png"
    picks = np.linspace(0, len(frames) - 1, min(8, len(frames))).astype(int)
    written.append(contact_sheet([frames[k] for k in picks], [f"frame {k}" for k in picks], sheet_path))
    return written


NOVEL_MOTION = "squat"  # the showcase's motion, one the avatar never saw
TURNTABLE_FRAMES = 60


def write_showcase(avatar, subject, out: str | Path, size: int = 256) -> dict[str, Path]:
    """What ``elicit demo`` and ``elicit batch`` show of an avatar, written into ``out``: a turntable in the
    input pose (``turntable.mp4``, a ring around the body, whatever frame the subject lives in), an
    animation in a motion it never saw from a three-quarter view (``animation.mp4``), and a contact sheet
    (input | front | side | back | novel pose)."""
    from ..data.motions import builtin_motion
    from ..data.rigs import place_ring

    out = Path(out)
    ring = place_ring(subject, TURNTABLE_FRAMES, size)
    input_pose = subject.motion.select([subject.input_index])
    spin = render_sequence(avatar, ring, input_pose, desc="turntable")
    turntable = write_video(out / "turntable.mp4", spin)
    novel = builtin_motion(NOVEL_MOTION, avatar.body)  # in the body frame, where the shipped rigs are
    three_quarter = read_rig(shipped_rig_path("ring"))[2]
    frames = render_sequence(avatar, [three_quarter.scaled(size / three_quarter.width)], novel, desc="animation")
    animation = write_video(out / "animation.mp4", frames)
    cam_in = subject.cameras[subject.input_camera]
    step = max(1, round(max(cam_in.width, cam_in.height) / size))
    tiles = [subject.image(subject.input_camera, subject.input_frame)[::step, ::step]]
    tiles += [spin[k * TURNTABLE_FRAMES // 4] for k in range(3)] + [frames[len(frames) // 2]]
    captions = ["input", "front", "side", "back", f"novel pose ({NOVEL_MOTION})"]
    sheet = contact_sheet(tiles, captions, out / "contact_sheet.png")
    return {"turntable": turntable, "animation": animation, "contact_sheet": sheet}
