"""The weights-free semantic prior: colour what the input camera does not see from its mirror image.

One photo shows one side of a person. Without CLIP weights nothing here knows what a back looks
like, but a body is close to symmetric: the back of a sleeve has the colour of its front, the left
leg that of the right. Every colour cell of the canonical grid near the body whose nearest body
vertex the input camera does not see gets a *source* point that it does see: its mirror image
through its body part's frontal plane (front <-> back; not for the head, whose back is hair, not a
face), else through the body's sagittal plane (left <-> right), else through both, whichever's
nearest body vertex is seen first. Cells without a seen source keep what they have. The term

    L = mean_c || sigmoid(c_cell) - sigmoid(blur(c)(source_cell)) ||^2

over every unseen cell with a source pulls it towards the detached colour that the fit gives its
source (which the input photo trains), blurred: the mean of trilinear look-ups at the source and
six points ``BLUR_VOXELS`` away. No render, no encoder.

A vertex is seen when it faces the input camera, projects inside the input mask and lies within
``DEPTH_TOLERANCE`` of the depth of the body's own surface there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..avatar import sample_grid
from ..body import PART_NAMES
from ..cameras import Camera
from ..field import CanonicalField, grid_points, signed_distance

DEPTH_TOLERANCE = 0.03  # metres: a vertex this far behind the visible surface is hidden
INSIDE_VOXELS = 2.0  # cells down to this many voxels inside the body surface are coloured
BLUR_VOXELS = 1.5  # spacing of the blur stencil at the source
NO_FRONT_BACK = ("head",)  # parts whose back is not their mirrored front


def visible_vertices(
    vertices: np.ndarray, normals: np.ndarray, camera: Camera, depth: np.ndarray, person: np.ndarray
) -> np.ndarray:
    """(V,) bool: which posed ``vertices`` (with outward ``normals``) the camera sees, given the body's
    (H, W) z-depth (0 = none) and the person's (H, W) mask."""
    uv, z = camera.project(vertices)
    facing = np.einsum("vc,vc->v", normals, camera.center - vertices) > 0
    h, w = depth.shape
    px = np.floor(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h) & (z > 0)
    seen = np.zeros(len(vertices), dtype=bool)
    u, v = px[inside, 0], px[inside, 1]
    d = depth[v, u]
    seen[inside] = person[v, u] & (d > 0) & (z[inside] <= d + DEPTH_TOLERANCE)
    return seen & facing


@dataclass
class MirrorCompletion:
    cells: torch.Tensor  # (N,) flat indices of unseen colour cells
    sources: torch.Tensor  # (N, 3) canonical positions of their seen mirror images
    rule_counts: dict[str, int]  # how many cells each mirror gave a source
    unseen: int  # unseen cells near the body, with a source or without

    @classmethod
    def build(
        cls,
        field: CanonicalField,
        canonical: np.ndarray,
        normals: np.ndarray,
        vertex_parts: np.ndarray,
        seen: np.ndarray,
        margin: float,
    ) -> MirrorCompletion:
        """Sources for ``field``'s unseen cells from the canonical body (``canonical`` vertices, ``normals``,
        ``vertex_parts``) and which of its vertices the input camera sees; cells up to ``margin`` outside
        the body count."""
        pts = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
        sdf = signed_distance(pts, canonical, normals)
        near = np.nonzero((sdf > -INSIDE_VOXELS * field.voxel_size) & (sdf < margin))[0]
        tree = cKDTree(canonical)
        _, idx = tree.query(pts[near])
        hidden = ~seen[idx]
        cells, p, part = near[hidden], pts[near[hidden]], vertex_parts[idx[hidden]]
        centre_z = np.zeros(len(PART_NAMES))
        for k in np.unique(vertex_parts):
            centre_z[k] = canonical[vertex_parts == k, 2].mean()
        front_back = p.copy()
        front_back[:, 2] = 2 * centre_z[part] - p[:, 2]
        left_right = p.copy()
        left_right[:, 0] = 2 * canonical[:, 0].mean() - p[:, 0]
        both = np.stack([left_right[:, 0], p[:, 1], front_back[:, 2]], 1)
        mirrored_ok = ~np.isin(part, [PART_NAMES.index(n) for n in NO_FRONT_BACK])
        source = np.full_like(p, np.nan)
        counts = {}
        for name, candidate, allowed in (
            ("front/back", front_back, mirrored_ok),
            ("left/right", left_right, np.ones(len(cells), dtype=bool)),
            ("both", both, mirrored_ok),
        ):
            free = np.nonzero(np.isnan(source[:, 0]) & allowed)[0]
            if free.size == 0:
                counts[name] = 0
                continue
            _, cand = tree.query(candidate[free])
            ok = seen[cand]
            source[free[ok]] = candidate[free[ok]]
            counts[name] = int(ok.sum())
        has = ~np.isnan(source[:, 0])
        device = field.color.device
        return cls(
            torch.as_tensor(cells[has], dtype=torch.long, device=device),
            torch.as_tensor(source[has], dtype=torch.float32, device=device),
            counts,
            int(cells.size),
        )

    def __len__(self) -> int:
        return int(self.cells.numel())

    def loss(self, field: CanonicalField) -> torch.Tensor:
        """The term over every unseen cell with a source."""
        if len(self) == 0:
            return torch.zeros((), device=field.color.device)
        step = BLUR_VOXELS * field.voxel_size
        eye = torch.eye(3, device=self.sources.device)
        offsets = torch.cat([torch.zeros(1, 3, device=eye.device), step * eye, -step * eye])
        stencil = (self.sources[:, None, :] + offsets[None]).reshape(-1, 3)
        with torch.no_grad():
            logits = sample_grid(field.color.detach().permute(3, 0, 1, 2), field.box, stencil)
            target = torch.sigmoid(logits.reshape(len(self), offsets.shape[0], 3).mean(1))
        color = torch.sigmoid(field.color.reshape(-1, 3)[self.cells])
        return ((color - target) ** 2).sum(-1).mean()
