"""The body-model interface: rest mesh, skinning, posing, body parts and the reduced skeleton.

World frame (all body models): metres, +y up, the body facing +z, its left side at +x (SMPL's
convention). ``pose`` holds one axis-angle per joint in the model's own order and its own native
axes (``model_axes`` maps them to world axes: identity for SMPL, a fixed rotation for Anny's z-up
frame); a joint's rotation acts on its subtree about the joint. ``global_orient`` and ``transl``
then move the whole posed body about the world origin.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
import torch

from ..core.errors import ElicitError
from ..core.geometry import axis_angle_to_matrix, merge_bones

# The reference code's body-part groups (plus background, the 11 labels of its segmentation).
PART_NAMES = (
    "torso",
    "head",
    "left_upper_arm",
    "right_upper_arm",
    "left_forearm",
    "right_forearm",
    "left_thigh",
    "right_thigh",
    "left_shin",
    "right_shin",
)
BACKGROUND = -1

# Joints the procedural motions drive, named the same for every body model.
SEMANTIC_JOINTS = (
    "pelvis", "spine_lower", "spine_mid", "spine_upper", "neck", "head",
    "l_collar", "l_shoulder", "l_elbow", "l_wrist", "r_collar", "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle",
)  # fmt: skip


class BodyModelError(ElicitError):
    """A body model cannot be built, or was given bad parameters."""


@dataclass
class PosedBody:
    vertices: np.ndarray  # (V, 3) world positions
    bone_transforms: np.ndarray  # (J, 4, 4) world frame of every joint (G_b)


class BodyModel(ABC):
    """A skinned body mesh of fixed shape. Subclasses fill the attributes in ``__init__``."""

    name: str
    joint_names: list[str]
    parents: np.ndarray  # (J,) parent joint index, -1 for the root
    faces: np.ndarray  # (F, 3)
    rest_vertices: np.ndarray  # (V, 3) zero pose
    skin_idx: np.ndarray  # (V, K) joint indices
    skin_w: np.ndarray  # (V, K) weights summing to 1
    semantic: dict[str, str]  # SEMANTIC_JOINTS -> joint name
    part_of_joint: dict[str, int]  # joint name -> index into PART_NAMES
    reduced_joints: list[str]  # joints the skinning warp uses (about 24)
    model_axes: np.ndarray = np.eye(3)  # native joint-rotation axes -> world axes
    uvs: np.ndarray | None = None  # (T, 2) texture coordinates
    face_uvs: np.ndarray | None = None  # (F, 3) indices into uvs

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def joint_index(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise BodyModelError(f"{self.name}: no joint named {name!r}") from None

    @abstractmethod
    def pose(
        self, pose: np.ndarray, global_orient: np.ndarray | None = None, transl: np.ndarray | None = None
    ) -> PosedBody:
        """Pose the body: ``pose`` (J, 3) axis-angle per joint, then the global rotation and translation."""

    def zero_pose(self) -> np.ndarray:
        return np.zeros((self.n_joints, 3), dtype=np.float32)

    def canonical_pose(self) -> np.ndarray:
        """The avatar's canonical pose: legs apart and arms away from the torso (HumanNeRF's "Da-pose")."""
        pose = self.zero_pose()
        self.set_semantic(pose, "l_hip", (0.0, 0.0, np.radians(22.0)))
        self.set_semantic(pose, "r_hip", (0.0, 0.0, -np.radians(22.0)))
        return pose

    # ---- derived quantities -------------------------------------------------------------------
    def dense_weights(self) -> np.ndarray:
        """(V, J) skinning weights."""
        out = np.zeros((self.rest_vertices.shape[0], self.n_joints), dtype=np.float64)
        np.add.at(out, (np.arange(out.shape[0])[:, None], self.skin_idx), self.skin_w)
        return out

    def vertex_parts(self) -> np.ndarray:
        """(V,) body part of each vertex: the part holding most of its skinning weight."""
        parts = np.array([self.part_of_joint[n] for n in self.joint_names])
        per_part = np.zeros((self.rest_vertices.shape[0], len(PART_NAMES)))
        np.add.at(per_part, (np.arange(per_part.shape[0])[:, None], parts[self.skin_idx]), self.skin_w)
        return per_part.argmax(1)

    def face_parts(self) -> np.ndarray:
        """(F,) body part of each face (the most common part among its vertices)."""
        vp = self.vertex_parts()[self.faces]
        counts = np.stack([(vp == p).sum(1) for p in range(len(PART_NAMES))], 1)
        return counts.argmax(1)

    def reduced_map(self) -> np.ndarray:
        """(J,) index into ``reduced_joints`` of each joint's nearest kept ancestor (itself if kept)."""
        keep = [self.joint_index(n) for n in self.reduced_joints]
        return merge_bones(self.parents.tolist(), keep).numpy()

    def reduced_weights(self) -> np.ndarray:
        """(V, B) skinning weights summed onto the reduced skeleton."""
        mapping = self.reduced_map()
        out = np.zeros((self.rest_vertices.shape[0], len(self.reduced_joints)))
        np.add.at(out, (np.arange(out.shape[0])[:, None], mapping[self.skin_idx]), self.skin_w)
        return out

    def reduced_transforms(self, posed: PosedBody) -> np.ndarray:
        """(B, 4, 4) world frames of the reduced skeleton's joints."""
        return posed.bone_transforms[[self.joint_index(n) for n in self.reduced_joints]]

    def set_semantic(self, pose: np.ndarray, name: str, rotvec_world) -> None:
        """Write a rotation given in world axes (x left, y up, z forward) at a semantic joint into ``pose``."""
        pose[self.joint_index(self.semantic[name])] = self.model_axes.T @ np.asarray(rotvec_world, dtype=np.float64)


def apply_global(
    vertices: np.ndarray, frames: np.ndarray, global_orient: np.ndarray | None, transl: np.ndarray | None
) -> PosedBody:
    """Rotate the posed body about the world origin, then translate it."""
    g = np.eye(4)
    if global_orient is not None:
        g[:3, :3] = axis_angle_to_matrix(torch.as_tensor(np.asarray(global_orient, dtype=np.float64))).numpy()
    if transl is not None:
        g[:3, 3] = np.asarray(transl, dtype=np.float64)
    return PosedBody(vertices @ g[:3, :3].T + g[:3, 3], g @ frames)


def check_pose(pose: np.ndarray, n_joints: int, model: str) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (n_joints, 3):
        raise BodyModelError(f"{model}: pose must be ({n_joints}, 3) axis-angle, got {pose.shape}")
    if not np.isfinite(pose).all():
        raise BodyModelError(f"{model}: pose contains NaN or infinite values")
    return pose
