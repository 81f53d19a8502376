"""Anny (NAVER, Apache-2.0): the default body model. It ships all of its data.

Poses use Anny's default ``local-ref`` parameterisation: a rotation per bone (the 4x4 pose parameter
with zero translation), whose axes are Anny's native z-up frame. Vertices and bone frames are
returned in the common world frame (+y up, facing +z) through the fixed rotation ``ANNY_TO_WORLD``.
"""

from __future__ import annotations

import functools
import os
import threading

import numpy as np
import torch

from ..core.device import init_warp
from ..core.geometry import axis_angle_to_matrix
from .base import PART_NAMES, BodyModel, BodyModelError, PosedBody, apply_global, check_pose

# Anny: x = body left, z = up, the body faces -y.  World: x = left, y = up, faces +z.
ANNY_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

SEMANTIC = {
    "pelvis": "root", "spine_lower": "spine04", "spine_mid": "spine03", "spine_upper": "spine01",
    "neck": "neck01", "head": "head",
    "l_collar": "clavicle.L", "l_shoulder": "upperarm01.L", "l_elbow": "lowerarm01.L", "l_wrist": "wrist.L",
    "r_collar": "clavicle.R", "r_shoulder": "upperarm01.R", "r_elbow": "lowerarm01.R", "r_wrist": "wrist.R",
    "l_hip": "upperleg01.L", "l_knee": "lowerleg01.L", "l_ankle": "foot.L",
    "r_hip": "upperleg01.R", "r_knee": "lowerleg01.R", "r_ankle": "foot.R",
}  # fmt: skip

# 21 joints drive the skinning warp; the other 83 (twist bones, fingers, toes, eyes) follow their
# nearest kept ancestor. The built-in motions only rotate kept joints, so the merge is exact there.
REDUCED = [
    "root", "spine04", "spine03", "spine02", "spine01", "neck01", "head",
    "clavicle.L", "upperarm01.L", "lowerarm01.L", "wrist.L", "clavicle.R", "upperarm01.R", "lowerarm01.R", "wrist.R",
    "upperleg01.L", "lowerleg01.L", "foot.L", "upperleg01.R", "lowerleg01.R", "foot.R",
]  # fmt: skip

_LOCK = threading.Lock()


def _part_of(name: str) -> int:
    side = "left" if name.endswith(".L") else "right" if name.endswith(".R") else None
    base = name.split(".")[0]
    if base.startswith(("neck", "head", "eye", "jaw", "tongue")):
        return PART_NAMES.index("head")
    if base.startswith(("root", "pelvis", "spine", "breast")) or side is None:
        return PART_NAMES.index("torso")
    if base.startswith(("clavicle", "shoulder", "upperarm")):
        return PART_NAMES.index(f"{side}_upper_arm")
    if base.startswith(("lowerarm", "wrist", "finger", "metacarpal", "thumb", "hand")):
        return PART_NAMES.index(f"{side}_forearm")
    if base.startswith("upperleg"):
        return PART_NAMES.index(f"{side}_thigh")
    if base.startswith(("lowerleg", "foot", "toe", "ankle")):
        return PART_NAMES.index(f"{side}_shin")
    return PART_NAMES.index("torso")


@functools.cache
def anny_model():
    """The shared Anny torch module (the first call in a fresh cache takes about a minute)."""
    with _LOCK:
        return import_anny().Anny().to(torch.float64)


def import_anny():
    """The ``anny`` package, imported after Warp is initialised our way (its import calls ``wp.init()``, whose
    no-GPU banner would otherwise reach stderr)."""
    init_warp()
    import anny

    return anny


class AnnyBody(BodyModel):
    """Anny with a fixed phenotype (gender, age, muscle, weight, height, proportions in [0, 1])."""

    name = "anny"

    def __init__(self, phenotype: dict[str, float] | None = None) -> None:
        model = anny_model()
        labels = list(model.phenotype_labels)
        phenotype = dict(phenotype or {})
        for key, value in phenotype.items():
            if key not in labels:
                raise BodyModelError(f"anny: unknown phenotype key {key!r}; choose from {labels}")
            if not isinstance(value, (int, float)) or not 0.0 <= float(value) <= 1.0:
                raise BodyModelError(f"anny: phenotype {key!r} must be a number in [0, 1], got {value!r}")
        self.phenotype = {k: float(phenotype.get(k, 0.5)) for k in labels}
        self._model = model
        self.joint_names = list(model.bone_labels)
        self.parents = np.asarray(model.bone_parents, dtype=np.int64)
        self.faces = model.get_triangular_faces().cpu().numpy().astype(np.int64)
        self.skin_idx = model.vertex_bone_indices.cpu().numpy().astype(np.int64)
        self.skin_w = model.vertex_bone_weights.cpu().numpy().astype(np.float64)
        self.uvs = model.texture_coordinates.cpu().numpy().astype(np.float64)
        self.face_uvs = model.face_texture_coordinate_indices.cpu().numpy().astype(np.int64)
        self.semantic = dict(SEMANTIC)
        self.reduced_joints = list(REDUCED)
        self.part_of_joint = {n: _part_of(n) for n in self.joint_names}
        self.model_axes = ANNY_TO_WORLD.copy()
        self.rest_vertices = self.pose(self.zero_pose()).vertices

    def _forward(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Anny forward for (N, J, 3) local-ref rotations -> world vertices (N, V, 3), frames (N, J, 4, 4)."""
        n = poses.shape[0]
        params = torch.eye(4, dtype=torch.float64).repeat(n, self.n_joints, 1, 1)
        params[..., :3, :3] = axis_angle_to_matrix(torch.as_tensor(poses, dtype=torch.float64))
        pheno = {k: torch.full((n,), v, dtype=torch.float64) for k, v in self.phenotype.items()}
        with torch.no_grad():
            out = self._model(pose_parameters=params, phenotype_kwargs=pheno)
        a4 = np.eye(4)
        a4[:3, :3] = ANNY_TO_WORLD
        verts = out["vertices"].cpu().numpy() @ ANNY_TO_WORLD.T
        frames = np.einsum("ij,nbjk->nbik", a4, out["bone_poses"].cpu().numpy())
        return verts, frames

    def pose(
        self, pose: np.ndarray, global_orient: np.ndarray | None = None, transl: np.ndarray | None = None
    ) -> PosedBody:
        pose = check_pose(pose, self.n_joints, self.name)
        verts, frames = self._forward(pose[None])
        return apply_global(verts[0], frames[0], global_orient, transl)

    def pose_batch(
        self, poses: np.ndarray, global_orients: np.ndarray, transls: np.ndarray, chunk: int = 16
    ) -> list[PosedBody]:
        """Pose a whole motion, ``chunk`` frames per Anny call."""
        out = []
        for s in range(0, poses.shape[0], chunk):
            verts, frames = self._forward(np.asarray(poses[s : s + chunk], dtype=np.float64))
            for k in range(verts.shape[0]):
                out.append(apply_global(verts[k], frames[k], global_orients[s + k], transls[s + k]))
        return out


def build_cache() -> None:
    """Build Anny's one-time cache (``ANNY_CACHE_DIR``, default ~/.cache/anny) and check the mesh."""
    body = AnnyBody()
    print(
        f"anny ready: {body.rest_vertices.shape[0]} vertices, {body.n_joints} bones "
        f"(cache: {os.environ.get('ANNY_CACHE_DIR', '~/.cache/anny')})"
    )
