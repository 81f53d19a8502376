"""Named input postures of synthetic people, made by aiming the limbs.

A posture names the world direction (x the body's left, y up, z its front) that each limb segment it
changes should point in: an upper arm, a forearm, a thigh or a shin. :func:`aim` turns those into joint
rotations: each segment's joint takes the smallest rotation that carries the segment from where its parent
leaves it onto its target, so the rest of the chain follows. Segments a posture does not name keep the
relaxed standing pose of :func:`standing`.
"""

from __future__ import annotations

import numpy as np
import torch

from ..body.base import BodyModel
from ..core.geometry import axis_angle_to_matrix, matrix_to_axis_angle

# segment -> (semantic joint that turns it, semantic joint at its far end)
SEGMENTS = {
    "l_upper_arm": ("l_shoulder", "l_elbow"), "l_forearm": ("l_elbow", "l_wrist"),
    "r_upper_arm": ("r_shoulder", "r_elbow"), "r_forearm": ("r_elbow", "r_wrist"),
    "l_thigh": ("l_hip", "l_knee"), "l_shin": ("l_knee", "l_ankle"),
    "r_thigh": ("r_hip", "r_knee"), "r_shin": ("r_knee", "r_ankle"),
}  # fmt: skip
PARENT_SEGMENT = {"l_forearm": "l_upper_arm", "r_forearm": "r_upper_arm", "l_shin": "l_thigh", "r_shin": "r_thigh"}


def _mirror(direction: tuple[float, float, float]) -> tuple[float, float, float]:
    return (-direction[0], direction[1], direction[2])


def _both(left: dict[str, tuple]) -> dict[str, tuple]:
    """Targets for the left side's segments and their mirror images for the right side's."""
    return {**left, **{"r" + k[1:]: _mirror(v) for k, v in left.items()}}


# Targets of each posture (the right side mirrored from the left where the posture is symmetric).
POSTURES: dict[str, dict[str, tuple[float, float, float]]] = {
    "standing": {},
    "seated": _both({"l_thigh": (0.12, -0.05, 1.0), "l_shin": (0.05, -1.0, 0.05)}),  # on an invisible box
    "legs_crossed": {"l_thigh": (-0.22, -1.0, 0.1), "l_shin": (-0.2, -1.0, -0.02), "r_thigh": (-0.05, -1.0, 0.0)},
    "arms_raised": _both({"l_upper_arm": (0.35, 1.0, 0.05), "l_forearm": (0.2, 1.0, 0.1)}),
    "arms_forward": _both({"l_upper_arm": (0.12, -0.1, 1.0), "l_forearm": (0.02, 0.0, 1.0)}),
    "arms_crossed": {
        "l_upper_arm": (0.3, -0.8, 0.45),
        "l_forearm": (-1.0, 0.12, 0.22),
        "r_upper_arm": (-0.3, -0.8, 0.45),
        "r_forearm": (1.0, 0.22, 0.3),
    },  # fmt: skip
    "hands_in_pockets": _both({"l_upper_arm": (0.2, -1.0, -0.05), "l_forearm": (-0.15, -1.0, 0.35)}),
    "holding": _both({"l_upper_arm": (0.12, -1.0, 0.12), "l_forearm": (-0.35, 0.05, 1.0)}),  # forearms forward
}


def standing(body: BodyModel) -> np.ndarray:
    """The relaxed standing pose: arms slightly lowered from the rest A-pose, elbows a little bent."""
    pose = body.zero_pose()
    body.set_semantic(pose, "l_shoulder", (0.0, 0.0, -np.radians(8.0)))
    body.set_semantic(pose, "r_shoulder", (0.0, 0.0, np.radians(8.0)))
    body.set_semantic(pose, "l_elbow", (-np.radians(10.0), 0.0, 0.0))
    body.set_semantic(pose, "r_elbow", (-np.radians(10.0), 0.0, 0.0))
    return pose


def smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the rotation of least angle that carries direction ``a`` onto direction ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(a @ b)
    if sin < 1e-9:  # parallel (or opposite: turn about any axis across a)
        if cos > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        sin = np.linalg.norm(axis)
    rotvec = axis / sin * np.arctan2(sin, cos)
    return axis_angle_to_matrix(torch.as_tensor(rotvec)).numpy()


def aim(body: BodyModel, pose: np.ndarray, targets: dict[str, tuple[float, float, float]]) -> np.ndarray:
    """``pose`` with each named segment turned to point along its target (world directions)."""
    pose = pose.copy()
    rest = body.pose(body.zero_pose()).bone_transforms
    for segment in sorted(targets, key=lambda s: s in PARENT_SEGMENT):  # parents first
        joint, end = SEGMENTS[segment]
        head, tail = (rest[body.joint_index(body.semantic[n]), :3, 3] for n in (joint, end))
        rest_dir = tail - head
        # The segment's direction as its parent leaves it: the parent's posed rotation applied to the rest one.
        parent_rot = np.eye(3)
        if segment in PARENT_SEGMENT:
            parent_joint = SEGMENTS[PARENT_SEGMENT[segment]][0]
            parent_rot = _world_rotation(body, pose, parent_joint)
        local = smallest_rotation(parent_rot @ rest_dir, np.asarray(targets[segment], dtype=np.float64))
        own = parent_rot.T @ local @ parent_rot  # the same turn, in the joint's own (rest-aligned) axes
        rotvec = matrix_to_axis_angle(torch.as_tensor(own)).numpy()
        body.set_semantic(pose, joint, rotvec)
    return pose


def _world_rotation(body: BodyModel, pose: np.ndarray, joint: str) -> np.ndarray:
    """The rotation a joint's posed frame has against its rest frame (the product down its chain)."""
    posed = body.pose(pose).bone_transforms
    rest = body.pose(body.zero_pose()).bone_transforms
    j = body.joint_index(body.semantic[joint])
    return posed[j, :3, :3] @ rest[j, :3, :3].T


def posture(body: BodyModel, name: str) -> np.ndarray:
    """The named input posture (see ``POSTURES``) for ``body``."""
    if name not in POSTURES:
        raise KeyError(f"unknown posture {name!r}; choose from {sorted(POSTURES)}")
    return aim(body, standing(body), POSTURES[name])
