"""Motions: ``motion.npz`` files, built-in procedural motions, and SMPL sequences (AMASS, ZJU-MoCap).

A motion holds ``pose`` (F, J, 3) axis-angle in the body model's own joint order and axes,
``global_orient`` (F, 3) and ``transl`` (F, 3) applied to the posed body about the world origin,
and optional ``frame_ids`` (F,).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..body import BodyModel
from ..core.checks import numeric
from ..core.errors import ElicitError
from ..core.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from ..core.io import atomic_write
from ..core.safe_load import load_npy, load_npz

MAX_TRANSLATION = 1000.0  # metres: a body farther from the origin is a unit or convention mistake
BUILTIN_MOTIONS = ("walk_in_place", "turn_around", "wave", "squat", "rest", "anny_walk")


class MotionError(ElicitError):
    """A motion file or name that cannot be used."""


@dataclass
class Motion:
    pose: np.ndarray  # (F, J, 3)
    global_orient: np.ndarray  # (F, 3)
    transl: np.ndarray  # (F, 3)
    frame_ids: np.ndarray = field(default=None)  # (F,)
    fps: float = 30.0
    name: str = ""

    def __post_init__(self) -> None:
        self.pose = np.asarray(self.pose, dtype=np.float32)
        n = self.pose.shape[0]
        self.global_orient = np.asarray(self.global_orient, dtype=np.float32).reshape(n, 3)
        self.transl = np.asarray(self.transl, dtype=np.float32).reshape(n, 3)
        self.frame_ids = np.arange(n) if self.frame_ids is None else np.asarray(self.frame_ids).astype(np.int64)

    def __len__(self) -> int:
        return self.pose.shape[0]

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.pose[i], self.global_orient[i], self.transl[i]

    def select(self, indices) -> Motion:
        idx = np.asarray(indices, dtype=np.int64)
        return Motion(
            self.pose[idx], self.global_orient[idx], self.transl[idx], self.frame_ids[idx], self.fps, self.name
        )

    def placed(self, rotation: np.ndarray, translation: np.ndarray) -> Motion:
        """The motion moved rigidly: ``x_world = rotation @ x + translation`` for every frame."""
        rot = torch.as_tensor(np.asarray(rotation, dtype=np.float64))
        glob = axis_angle_to_matrix(torch.as_tensor(self.global_orient, dtype=torch.float64))
        orient = matrix_to_axis_angle(rot @ glob).numpy()
        transl = self.transl.astype(np.float64) @ rot.numpy().T + np.asarray(translation, dtype=np.float64)
        return Motion(self.pose.copy(), orient, transl, self.frame_ids.copy(), self.fps, self.name)

    def save(self, path: str | Path) -> Path:
        def write(p: Path) -> None:
            with open(p, "wb") as f:
                np.savez(
                    f,
                    pose=self.pose,
                    global_orient=self.global_orient,
                    transl=self.transl,
                    frame_ids=self.frame_ids,
                    fps=np.float32(self.fps),
                )

        return atomic_write(path, write)


def load_motion_npz(path: str | Path, n_joints: int | None = None) -> Motion:
    """Read and validate a ``motion.npz``; every problem names the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise MotionError(f"{path}: motion file not found")
    return motion_from_arrays(load_npz(path, MotionError), path, n_joints)


def motion_from_arrays(data: dict, path: Path, n_joints: int | None = None) -> Motion:
    """A motion from ``motion.npz``'s arrays: (F, J, 3) pose, (F, 3) global_orient and transl, optional
    (F,) frame_ids and fps; every problem names the file and the field."""
    for key in ("pose", "global_orient", "transl"):
        if key not in data:
            raise MotionError(f"{path}: missing field '{key}'")
    pose = numeric(data["pose"], f"{path} field 'pose'", (-1, -1, 3), MotionError)
    n = pose.shape[0]
    if n == 0:
        raise MotionError(f"{path}: field 'pose' has no frames")
    if n_joints is not None and pose.shape[1] != n_joints:
        raise MotionError(f"{path}: field 'pose' has {pose.shape[1]} joints, the body model has {n_joints}")
    orient = numeric(data["global_orient"], f"{path} field 'global_orient'", (n, 3), MotionError)
    transl = numeric(data["transl"], f"{path} field 'transl'", (n, 3), MotionError)
    if np.abs(transl).max() > MAX_TRANSLATION:
        raise MotionError(
            f"{path}: field 'transl' reaches {np.abs(transl).max():.3g} m; translations are metres (at most "
            f"{MAX_TRANSLATION:g})"
        )
    frame_ids = None
    if "frame_ids" in data:
        frame_ids = numeric(data["frame_ids"], f"{path} field 'frame_ids'", (n,), MotionError)
        if (frame_ids != np.round(frame_ids)).any() or len(set(frame_ids.tolist())) != n:
            raise MotionError(f"{path}: field 'frame_ids' must be {n} distinct integers")
    fps = 30.0
    if "fps" in data:
        fps = float(numeric(data["fps"], f"{path} field 'fps'", (), MotionError))
        if fps <= 0:
            raise MotionError(f"{path}: field 'fps' must be positive, got {fps}")
    return Motion(pose, orient, transl, frame_ids, fps, path.stem)


# ---- built-in procedural motions ------------------------------------------------------------------
def _rx(a: float) -> tuple[float, float, float]:
    return (a, 0.0, 0.0)


def _ry(a: float) -> tuple[float, float, float]:
    return (0.0, a, 0.0)


def _rz(a: float) -> tuple[float, float, float]:
    return (0.0, 0.0, a)


def _walk_frame(t: float) -> dict:
    """One walking-in-place phase t in [0, 1): semantic joint -> world-axis rotation vector."""
    s = math.sin(2 * math.pi * t)
    lift_l, lift_r = max(0.0, s), max(0.0, -s)
    d = math.radians
    return {
        "l_hip": _rx(-d(35) * lift_l), "r_hip": _rx(-d(35) * lift_r),
        "l_knee": _rx(d(60) * lift_l), "r_knee": _rx(d(60) * lift_r),
        "l_ankle": _rx(-d(10) * lift_l), "r_ankle": _rx(-d(10) * lift_r),
        "l_shoulder": _rx(d(25) * s), "r_shoulder": _rx(-d(25) * s),
        "l_elbow": _rx(-d(20) - d(10) * lift_r), "r_elbow": _rx(-d(20) - d(10) * lift_l),
        "spine_mid": _ry(d(5) * s),
    }  # fmt: skip


def _wave_frame(t: float) -> dict:
    d = math.radians
    swing = math.sin(2 * math.pi * t)
    return {
        "r_shoulder": (0.0, 0.0, -d(110)),  # raise the right arm sideways above the shoulder
        "r_elbow": (0.0, d(25) * swing, -d(35)),
        "l_shoulder": _rx(d(5)),
        "head": _rz(-d(8) * swing),
        "spine_mid": _rz(d(4)),
    }


def _squat_frame(t: float) -> dict:
    d = math.radians
    depth = 0.5 - 0.5 * math.cos(2 * math.pi * t)
    return {
        "l_hip": _rx(-d(95) * depth), "r_hip": _rx(-d(95) * depth),
        "l_knee": _rx(d(115) * depth), "r_knee": _rx(d(115) * depth),
        "l_ankle": _rx(-d(25) * depth), "r_ankle": _rx(-d(25) * depth),
        "spine_lower": _rx(d(25) * depth),
        "l_shoulder": _rx(-d(70) * depth), "r_shoulder": _rx(-d(70) * depth),
    }  # fmt: skip


def _ground(body: BodyModel, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> np.ndarray:
    """Translations that keep the lowest vertex at the rest pose's floor height, frame by frame."""
    floor = body.rest_vertices[:, 1].min()
    out = transl.copy()
    posed = _pose_all(body, pose, orient, transl)
    for i, p in enumerate(posed):
        out[i, 1] += floor - p.vertices[:, 1].min()
    return out


def _pose_all(body: BodyModel, pose, orient, transl):
    if hasattr(body, "pose_batch"):
        return body.pose_batch(pose, orient, transl)
    return [body.pose(pose[i], orient[i], transl[i]) for i in range(pose.shape[0])]


def builtin_motion(name: str, body: BodyModel, n_frames: int | None = None) -> Motion:
    """A built-in motion for ``body``: walk_in_place, turn_around, wave, squat, rest, or anny_walk (Anny's
    shipped walk cycle, Anny bodies only)."""
    if name == "anny_walk":
        if body.name != "anny":
            raise MotionError(f"motion 'anny_walk' is Anny's walk cycle; it needs an Anny body, not {body.name!r}")
        from ..body.anny_walk import anny_walk_cycle

        clip, _ = anny_walk_cycle(body, n_frames or 40)
        return Motion(clip.pose, clip.global_orient, clip.transl, None, clip.fps, "anny_walk")
    frames: dict[str, tuple[int, Callable[[float], dict]]] = {
        "walk_in_place": (30, _walk_frame),
        "turn_around": (48, _walk_frame),
        "wave": (30, _wave_frame),
        "squat": (36, _squat_frame),
        "rest": (1, lambda t: {}),
    }
    if name not in frames:
        raise MotionError(f"unknown motion {name!r}; built-in motions are {BUILTIN_MOTIONS}")
    default_n, frame_fn = frames[name]
    n = n_frames or default_n
    pose = np.zeros((n, body.n_joints, 3), dtype=np.float64)
    orient = np.zeros((n, 3))
    transl = np.zeros((n, 3))
    for i in range(n):
        t = i / n
        phase = (2 * t) % 1.0 if name == "turn_around" else t
        for joint, rotvec in frame_fn(phase).items():
            body.set_semantic(pose[i], joint, rotvec)
        if name == "turn_around":
            orient[i] = (0.0, 2 * math.pi * t, 0.0)
    if name in ("walk_in_place", "turn_around", "squat"):
        transl = _ground(body, pose, orient, transl)
    return Motion(pose, orient, transl, None, 30.0, name)


# ---- SMPL sequences -------------------------------------------------------------------------------
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def read_amass(path: str | Path, body: BodyModel, step: int = 1) -> Motion:
    """An AMASS ``.npz`` (SMPL-H/SMPL-X poses, z-up world) as a motion of an SMPL-family body."""
    path = Path(path)
    return _amass_motion(load_npz(path, MotionError), path, body, step)


def _amass_motion(data: dict, path: Path, body: BodyModel, step: int = 1) -> Motion:
    if body.name not in ("smpl", "smplx"):
        raise MotionError(f"{path}: AMASS poses are SMPL joints; the subject's body model is {body.name!r}")
    for key in ("poses", "trans"):
        if key not in data:
            raise MotionError(f"{path}: missing field '{key}' (not an AMASS file?)")
    poses = numeric(data["poses"], f"{path} field 'poses'", (-1, -1), MotionError)[::step]
    trans = numeric(data["trans"], f"{path} field 'trans'", (-1, 3), MotionError)[::step]
    n_body = min(body.n_joints, 22)
    if poses.shape[1] < 3 * n_body or poses.shape[0] != trans.shape[0] or poses.shape[0] == 0:
        raise MotionError(f"{path}: fields 'poses' {poses.shape} and 'trans' {trans.shape} do not match an AMASS clip")
    pose = np.zeros((poses.shape[0], body.n_joints, 3))
    pose[:, :n_body] = poses[:, : 3 * n_body].reshape(-1, n_body, 3)
    fps = 30.0
    if "mocap_framerate" in data:
        fps = float(numeric(data["mocap_framerate"], f"{path} field 'mocap_framerate'", (), MotionError)) / step
    motion = Motion(pose, np.zeros((pose.shape[0], 3)), trans, None, fps, path.stem)
    return motion.placed(Z_UP_TO_Y_UP, np.zeros(3))


def read_zju_params(folder: str | Path, body: BodyModel, frames: list[int] | None = None) -> Motion:
    """ZJU-MoCap / EasyMocap ``new_params/<frame>.npy`` files (``poses``, ``Rh``, ``Th``) of an SMPL body."""
    folder = Path(folder)
    if body.name not in ("smpl", "smplx"):
        raise MotionError(f"{folder}: ZJU/EasyMocap poses are SMPL joints; the body model is {body.name!r}")
    files = [p for p in folder.glob("*.npy") if p.stem.isdigit()] if folder.is_dir() else []
    files.sort(key=lambda p: int(p.stem))
    if not files:
        raise MotionError(f"{folder}: no <frame>.npy parameter files")
    if frames is not None:
        by_id = {int(p.stem): p for p in files}
        missing = [f for f in frames if f not in by_id]
        if missing:
            raise MotionError(f"{folder}: no parameters for frames {missing[:5]}")
        files = [by_id[f] for f in frames]
    pose, orient, transl, ids = [], [], [], []
    for f in files:
        d = load_npy(f, MotionError)
        if not isinstance(d, dict):
            raise MotionError(f"{f}: expected a dict of 'poses', 'Rh' and 'Th', got {type(d).__name__}")
        for key in ("poses", "Rh", "Th"):
            if key not in d:
                raise MotionError(f"{f}: missing field '{key}'")
        p = numeric(d["poses"], f"{f} field 'poses'", error=MotionError).reshape(-1, 3)
        if p.shape[0] < body.n_joints:
            raise MotionError(f"{f}: field 'poses' has {p.shape[0]} joints, the body model needs {body.n_joints}")
        p = p[: body.n_joints].copy()
        p[0] = 0.0  # EasyMocap keeps the root rotation in Rh
        pose.append(p)
        orient.append(numeric(d["Rh"], f"{f} field 'Rh'", error=MotionError).reshape(-1)[:3])
        transl.append(numeric(d["Th"], f"{f} field 'Th'", error=MotionError).reshape(-1)[:3])
        if orient[-1].shape != (3,) or transl[-1].shape != (3,):
            raise MotionError(f"{f}: fields 'Rh' and 'Th' must hold 3 numbers each")
        ids.append(int(f.stem))
    return Motion(np.stack(pose), np.stack(orient), np.stack(transl), np.array(ids), 30.0, folder.parent.name)


def load_motion(spec: str | Path, body: BodyModel, n_frames: int | None = None) -> Motion:
    """A motion by built-in name, ``motion.npz``, AMASS ``.npz`` or ZJU ``new_params`` folder."""
    spec_str = str(spec)
    if spec_str in BUILTIN_MOTIONS:
        return builtin_motion(spec_str, body, n_frames)
    path = Path(spec)
    if path.is_dir():
        return read_zju_params(path, body)
    if path.suffix == ".npz" and path.is_file():
        data = load_npz(path, MotionError)
        if "poses" in data and "trans" in data:
            return _amass_motion(data, path, body)
        return motion_from_arrays(data, path, body.n_joints)
    raise MotionError(f"{spec_str!r} is neither a built-in motion {BUILTIN_MOTIONS} nor an existing motion file")
