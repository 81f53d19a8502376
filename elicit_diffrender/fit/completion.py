"""The weights-free semantic prior: colour what the input camera does not see from what it sees, relit.

One photo shows one side of a person. Without CLIP weights nothing here knows what a back looks
like, but a body is close to symmetric: the back of a sleeve has the colour of its front, the left
leg that of the right. Every colour cell of the canonical grid near the body whose nearest body
vertex the input camera does not see gets a *source* point that it does see, by the first rule
that finds one: its mirror image through its body part's frontal plane (front <-> back; not for
the head, whose back is hair, not a face), through the body's sagittal plane (left <-> right),
through both; the head's back instead copies the nearest seen vertex of its crown (the up-facing
top ``CROWN_DEPTH`` of the head: hair, a hat or bare skin, not the face); else the nearest seen
vertex of the cell's own part, else the nearest seen vertex. The photo's light (``fit.shading``,
fitted to the seen body) says how much darker or brighter the cell's side is than its source's, so
the target is

    t_c = sigmoid(blur(c)(source_c)) * S(n_c) / S(n_source)

with ``S`` evaluated at the input-pose normals of the two points' nearest body vertices, and the term

    L = mean_c || sigmoid(c_cell) - t_c ||^2

pulls every unseen cell towards it. ``blur`` is the mean of trilinear look-ups at the source and six
points ``BLUR_VOXELS`` away; the targets are detached and recomputed every ``REFRESH`` steps (the
seen side they copy changes slowly). No render, no encoder.

A vertex is seen when it faces the input camera, projects inside the input mask and lies within
``DEPTH_TOLERANCE`` of the depth of the body's own surface there.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..body import PART_NAMES
from ..core.cameras import Camera
from ..model.field import CanonicalField, grid_points, nearest

DEPTH_TOLERANCE = 0.03  # metres: a vertex this far behind the visible surface is hidden
INSIDE_VOXELS = 2.0  # cells down to this many voxels inside the body surface are coloured
BLUR_VOXELS = 1.5  # spacing of the blur stencil at the source
NO_FRONT_BACK = ("head",)  # parts whose back is not their mirrored front: they copy their crown
CROWN_UP = 0.5  # a vertex whose canonical normal's up component exceeds this ...
CROWN_DEPTH = 0.06  # ... and that lies at most this far (metres) below its part's top is on the crown
REFRESH = 10  # steps between recomputations of the targets


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
    sources: torch.Tensor  # (N, 3) canonical positions of the seen points they copy
    gains: torch.Tensor  # (N,) S(n_cell) / S(n_source): the photo's light on the cell's side against the source's
    rule_counts: dict[str, int]  # how many cells each rule gave a source
    unseen: int  # unseen cells near the body
    _target: torch.Tensor | None = None
    _key: int = -1
    _blur: torch.Tensor | None = None  # (N, cells) sparse: the blur's trilinear weights of every colour cell

    @classmethod
    def build(
        cls,
        field: CanonicalField,
        canonical: np.ndarray,
        normals: np.ndarray,
        vertex_parts: np.ndarray,
        seen: np.ndarray,
        sdf: np.ndarray,
        margin: float,
        light: np.ndarray | None = None,
        garment: np.ndarray | None = None,
    ) -> MirrorCompletion:
        """Sources for ``field``'s unseen cells from the canonical body (``canonical`` vertices, ``normals``,
        ``vertex_parts``, and ``sdf``: ``field.body_distance`` of it) and which of its vertices the input camera
        sees; cells up to ``margin`` outside the body count, and the ``garment`` cells (flat bool: a garment's
        hull) however far out. ``light`` (V,) is the photo's light ``S`` at every vertex (input pose); without
        it the gains are 1."""
        pts = grid_points(field.box.double(), field.shape).reshape(-1, 3).numpy()
        sdf = sdf.reshape(-1)
        room = sdf < margin if garment is None else (sdf < margin) | garment
        near = np.nonzero((sdf > -INSIDE_VOXELS * field.voxel_size) & room)[0]
        tree = cKDTree(canonical)
        _, idx = nearest(tree, pts[near])
        hidden = ~seen[idx]
        cells, p, owner = near[hidden], pts[near[hidden]], idx[hidden]
        part = vertex_parts[owner]
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
        source_vertex = np.zeros(len(cells), dtype=np.int64)
        counts = {}
        for name, candidate, allowed in (
            ("front/back", front_back, mirrored_ok),
            ("left/right", left_right, np.ones(len(cells), dtype=bool)),
            ("both", both, mirrored_ok),
        ):
            free = np.nonzero(np.isnan(source[:, 0]) & allowed)[0]
            _, cand = nearest(tree, candidate[free]) if free.size else (None, np.zeros(0, dtype=np.int64))
            ok = seen[cand]
            source[free[ok]] = candidate[free[ok]]
            source_vertex[free[ok]] = cand[ok]
            counts[name] = int(ok.sum())
        # Then the nearest seen vertex of a pool: for the head its crown (the back of a head is hair, a hat or
        # bare skin like its top, not the face), then the cell's own part, then any part.
        # Below CROWN_DEPTH the up-facing vertices are brows, eyelids, the nose's ridge and the lips: the face.
        top = np.full(len(PART_NAMES), -np.inf)
        np.maximum.at(top, vertex_parts, canonical[:, 1])
        crown = seen & (normals[:, 1] > CROWN_UP) & (canonical[:, 1] > top[vertex_parts] - CROWN_DEPTH)
        no_mirror = [PART_NAMES.index(n) for n in NO_FRONT_BACK]
        for name, pool_of in (
            ("crown", lambda k: crown & (vertex_parts == k) if k in no_mirror else None),
            ("nearest seen of its part", lambda k: seen & (vertex_parts == k)),
            ("nearest seen", lambda k: seen),
        ):
            counts[name] = 0
            free = np.nonzero(np.isnan(source[:, 0]))[0]
            for k in np.unique(part[free]):
                pool = pool_of(int(k))
                if pool is None or not pool.any():
                    continue
                rows, pool = free[part[free] == k], np.nonzero(pool)[0]
                _, j = nearest(cKDTree(canonical[pool]), p[rows])
                source[rows], source_vertex[rows] = canonical[pool[j]], pool[j]
                counts[name] += int(rows.size)
        has = ~np.isnan(source[:, 0])
        gains = np.ones(len(cells)) if light is None else light[owner] / light[source_vertex]
        device = field.color.device
        return cls(
            torch.as_tensor(cells[has], dtype=torch.long, device=device),
            torch.as_tensor(source[has], dtype=torch.float32, device=device),
            torch.as_tensor(gains[has], dtype=torch.float32, device=device),
            counts,
            int(cells.size),
        )

    def __len__(self) -> int:
        return int(self.cells.numel())

    def blur_matrix(self, field: CanonicalField) -> torch.Tensor:
        """(N, X*Y*Z) sparse: row ``i`` averages the trilinear look-ups (border-clamped, nodes on the box's
        corners) of the colour grid at source ``i`` and the six points ``BLUR_VOXELS`` cells around it. The
        sources are fixed, so this is built once and every refresh of the targets is one sparse product."""
        if self._blur is None:
            step = BLUR_VOXELS * field.voxel_size
            eye = torch.eye(3, dtype=torch.float64)
            offsets = torch.cat([torch.zeros(1, 3, dtype=torch.float64), step * eye, -step * eye])
            points = (self.sources.double().cpu()[:, None, :] + offsets[None]).reshape(-1, 3)
            box, shape = field.box.double().cpu(), torch.tensor(field.shape)
            f = ((points - box[0]) / (box[1] - box[0]) * (shape - 1)).clamp(min=torch.zeros(3), max=shape - 1.0)
            base = torch.minimum(f.floor().long(), shape - 2)
            frac = f - base
            rows = torch.arange(len(self)).repeat_interleave(offsets.shape[0])
            index, weight = [], []
            for corner in range(8):
                bit = torch.tensor([corner & 1, (corner >> 1) & 1, corner >> 2])
                node = base + bit
                index.append((node[:, 0] * shape[1] + node[:, 1]) * shape[2] + node[:, 2])
                weight.append(torch.where(bit.bool(), frac, 1.0 - frac).prod(1) / offsets.shape[0])
            coo = torch.sparse_coo_tensor(
                torch.stack([rows.repeat(8), torch.cat(index)]),
                torch.cat(weight).float(),
                (len(self), int(shape.prod())),
                check_invariants=True,
            ).coalesce()
            with warnings.catch_warnings():  # "sparse CSR support is in beta": its product is 6x COO's here
                warnings.simplefilter("ignore", UserWarning)
                self._blur = coo.to_sparse_csr().to(self.sources.device)
        return self._blur

    @torch.no_grad()
    def targets(self, field: CanonicalField) -> torch.Tensor:
        """(N, 3) the relit, blurred colour at every cell's source."""
        logits = torch.sparse.mm(self.blur_matrix(field), field.color.detach().reshape(-1, 3))
        return (torch.sigmoid(logits) * self.gains[:, None]).clamp(0.0, 1.0)

    def state(self) -> dict:
        """The current targets (a resumed fit continues with the same ones)."""
        return {} if self._target is None else {"key": self._key, "target": self._target}

    def load_state(self, state: dict) -> None:
        self._target, self._key = (state["target"], int(state["key"])) if state else (None, -1)

    def loss(self, field: CanonicalField, step: int, cell_logits: torch.Tensor) -> torch.Tensor:
        """The term over every unseen cell with a source, whose colour logits ``cell_logits`` (N, 3) are
        ``field.color``'s rows :attr:`cells`; targets are recomputed every ``REFRESH`` steps."""
        if len(self) == 0:
            return torch.zeros((), device=field.color.device)
        if self._target is None or step // REFRESH != self._key:
            self._target, self._key = self.targets(field), step // REFRESH
        color = torch.sigmoid(cell_logits)
        return ((color - self._target) ** 2).sum(-1).mean()
