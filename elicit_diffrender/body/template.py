"""The template texture of the body prior: a distinct colour per body part, brighter on the front.

ELICIT initialises the avatar on renders of the body in this texture, so that every part and its
facing are unambiguous even where limbs overlap the torso.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .base import PART_NAMES, BodyModel

PART_COLORS = np.array([
    [0.80, 0.80, 0.80],  # torso
    [0.95, 0.80, 0.55],  # head
    [0.90, 0.25, 0.25],  # left upper arm
    [0.25, 0.45, 0.90],  # right upper arm
    [0.95, 0.55, 0.20],  # left forearm
    [0.30, 0.80, 0.85],  # right forearm
    [0.55, 0.85, 0.30],  # left thigh
    [0.65, 0.35, 0.85],  # right thigh
    [0.95, 0.85, 0.25],  # left shin
    [0.85, 0.35, 0.60],  # right shin
])  # fmt: skip
assert PART_COLORS.shape[0] == len(PART_NAMES)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals)


def template_colors(body: BodyModel) -> np.ndarray:
    """(V, 3) template colour per vertex: the part colour, shaded 0.55..1 from back to front."""
    normals = vertex_normals(body.rest_vertices, body.faces)
    facing = 0.775 + 0.225 * normals[:, 2]  # +z is the body's front
    return np.clip(PART_COLORS[body.vertex_parts()] * facing[:, None], 0.0, 1.0)
