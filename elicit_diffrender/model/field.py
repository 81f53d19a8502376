"""The avatar's learnable volumes: the canonical radiance grid and the motion-weight volume.

Both are node-aligned grids over boxes in canonical space. Density is stored as raw values in
units of optical depth per grid cell (the renderer scales by 1 / voxel size); colour as logits.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

from ..core.host_reads import on_host

EMPTY_DENSITY = -6.0  # softplus(-6) = 0.0025 per cell: transparent but still trainable


def grid_shape(box: torch.Tensor, voxel: float) -> tuple[int, int, int]:
    ext = (box[1] - box[0]).tolist()
    return tuple(max(2, math.ceil(e / voxel) + 1) for e in ext)


def grid_axes(box: torch.Tensor, shape: tuple[int, ...]) -> list[torch.Tensor]:
    """The node coordinates along each axis (float64)."""
    return [torch.linspace(float(box[0, a]), float(box[1, a]), shape[a], dtype=torch.float64) for a in range(3)]


def node_points(axes: list[np.ndarray], index: tuple[np.ndarray, ...]) -> np.ndarray:
    """(N, 3) positions of the nodes at per-axis indices ``index`` of a grid whose axes are ``axes``
    (:func:`grid_axes`), without building the whole grid."""
    return np.stack([axes[a][index[a]] for a in range(3)], 1)


def grid_points(box: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """World positions of every node, (X, Y, Z, 3)."""
    return torch.stack(torch.meshgrid(*grid_axes(box, shape), indexing="ij"), -1)


def nearest(tree: cKDTree, points: np.ndarray, k: int = 1, within: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """``tree.query(points, k)`` on the CPUs this process is given (distances and indices); a neighbour farther
    than ``within`` is not looked for (distance ``inf``, index ``tree.n``)."""
    from ..core.device import cpus_given

    return tree.query(points, k=k, workers=cpus_given(), distance_upper_bound=within)


def signed_distance(
    points: np.ndarray, vertices: np.ndarray, normals: np.ndarray, k: int = 4, tree: cKDTree | None = None
) -> np.ndarray:
    """Approximate signed distance to a closed mesh: distance to the nearest vertices, signed by their normals
    (``tree``: a ``cKDTree`` of ``vertices``, if one is at hand)."""
    dist, idx = nearest(cKDTree(vertices) if tree is None else tree, points, k)
    sign = np.sign(np.einsum("pkc,pkc->pk", points[:, None] - vertices[idx], normals[idx]).mean(1))
    return dist[:, 0] * np.where(sign == 0, 1.0, sign)


# CanonicalField.body_distance is exact within this many voxels of the body: its readers compare it with one voxel
# (the initial density's smooth step, clothing's sparsity) or read it inside the body (the completion's band)
EXACT_VOXELS = 2.0


def _level_nodes(n: int, stride: int) -> np.ndarray:
    """Node indices of one axis at ``stride``: every ``stride``-th, and the last, so that every node lies in a cell."""
    return np.unique(np.r_[np.arange(0, n, stride), n - 1])


def grid_signed_distance(
    box: torch.Tensor, shape: tuple[int, int, int], vertices: np.ndarray, normals: np.ndarray, exact_within: float
) -> np.ndarray:
    """(X, Y, Z) :func:`signed_distance` at the nodes of a grid, coarse to fine, computed only where it is needed.

    The distance to the nearest vertex ``d`` is 1-Lipschitz: inside a cell of the coarser level whose corners
    hold ``d_c``, every node has ``d >= max_c(d_c) - diag`` (``diag``: the cell's diagonal). Where that bound
    reaches ``exact_within`` and every corner lies outside the body, the node takes the bound, positive; every
    other node is computed. Levels go from stride 8 to 1. So every value inside the body and every value below
    ``exact_within`` is :func:`signed_distance`'s; a value at or above ``exact_within`` is outside, with a
    magnitude at most the true distance. (Only outside, where the vertex-normal vote is smooth, does a node take
    its corners' sign; inside it, the vote can flip, so the inside is always computed.)
    """
    axes = [a.numpy() for a in grid_axes(box, shape)]
    tree = cKDTree(vertices)
    out = np.full(shape, np.nan)

    def exact(index: tuple[np.ndarray, ...]) -> np.ndarray:
        return signed_distance(node_points(axes, index), vertices, normals, tree=tree)

    stride = 8
    prev = [_level_nodes(n, stride) for n in shape]
    ii = np.meshgrid(*prev, indexing="ij")
    out[np.ix_(*prev)] = exact(tuple(i.ravel() for i in ii)).reshape(ii[0].shape)
    while stride > 1:
        stride //= 2
        nodes = [_level_nodes(n, stride) for n in shape]
        coarse = out[np.ix_(*prev)]
        d, pos = np.abs(coarse), coarse > 0
        # per coarse cell: the largest corner distance and whether every corner is outside
        dmax, all_pos = d[:-1, :-1, :-1], pos[:-1, :-1, :-1]
        for corner in range(1, 8):
            sl = tuple(slice(1, None) if corner >> a & 1 else slice(None, -1) for a in range(3))
            dmax, all_pos = np.maximum(dmax, d[sl]), all_pos & pos[sl]
        cell = [
            np.clip(np.searchsorted(p, n, side="right") - 1, 0, len(p) - 2) for p, n in zip(prev, nodes, strict=True)
        ]
        width = [np.diff(axes[a][prev[a]]).max() for a in range(3)]
        lo = dmax[np.ix_(*cell)] - float(np.sqrt(sum(w * w for w in width)))
        certain = (lo >= exact_within) & all_pos[np.ix_(*cell)]
        grid = np.ix_(*nodes)
        level = out[grid]
        known = ~np.isnan(level)
        level = np.where(known, level, np.where(certain, lo, np.nan))
        todo = np.nonzero(np.isnan(level))
        if todo[0].size:
            level[todo] = exact(tuple(nodes[a][todo[a]] for a in range(3)))
        out[grid] = level
        prev = nodes
    return out


SPLAT_CHUNK = 8192  # points blended at a time by :func:`splat_weights`


def splat_weights(points: np.ndarray, vertices: np.ndarray, weights: np.ndarray, k: int = 8) -> np.ndarray:
    """(P, B) skinning weights at ``points``: the inverse-square-distance blend of the ``k`` nearest vertices'."""
    dist, idx = nearest(cKDTree(vertices), points, k)
    w = 1.0 / np.maximum(dist, 1e-3) ** 2
    blend = np.empty((len(points), weights.shape[1]))
    for lo in range(0, len(points), SPLAT_CHUNK):  # a chunk's (chunk, B) rows stay in cache over the k neighbours
        part = slice(lo, lo + SPLAT_CHUNK)
        wp, ip = w[part], idx[part]
        acc = wp[:, 0, None] * weights[ip[:, 0]]  # one neighbour at a time: no (P, k, B) gather
        for j in range(1, ip.shape[1]):
            acc += wp[:, j, None] * weights[ip[:, j]]
        blend[part] = acc
    return blend / w.sum(1, keepdims=True)


@dataclass
class Room:
    """How far outside the canonical body the avatar may hold density (metres): ``margin`` everywhere, ``reach``
    at the points ``extends`` selects (where the photo shows more than the body: hair, loose clothing), and
    ``hull_reach`` at the points ``hull`` selects (the hair's depth round the head, a garment's between the legs:
    ``hull_names``, :mod:`elicit_diffrender.fit.room`)."""

    margin: float
    reach: float = 0.0
    extends: Callable[[np.ndarray], np.ndarray] | None = None
    hull_reach: float = 0.0
    hull: Callable[[np.ndarray], np.ndarray] | None = None
    hull_names: tuple[str, ...] = ()

    @property
    def widest(self) -> float:
        out = max(self.margin, self.reach) if self.extends is not None else self.margin
        return max(out, self.hull_reach) if self.hull is not None else out

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(P,) the room at each canonical point."""
        out = np.full(len(points), self.margin)
        if self.extends is not None and self.reach > self.margin:
            out[self.extends(points)] = self.reach
        if self.hull is not None:
            inside = self.hull(points)
            out[inside] = np.maximum(out[inside], self.hull_reach)
        return out


class BoxedVolume(nn.Module):
    """A volume over a canonical ``box`` (2, 3), a buffer that travels with the module, and ``box_host``, its copy
    on the host that kernel launches take by value (reading the buffer would wait for the device); the copy
    follows a loaded state."""

    def __init__(self, box: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("box", box.to(torch.float32).clone())
        self.box_host = self.box.clone()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self.box_host = self.box.detach().cpu().clone()


class CanonicalField(BoxedVolume):
    """Density and colour on a grid over ``box`` with an occupancy grid for empty-space skipping."""

    def __init__(
        self, box: torch.Tensor, voxel_size: float, activation: str = "softplus", occupancy_cell: float = 0.04
    ) -> None:
        super().__init__(box)
        self.voxel_size = float(voxel_size)
        self.activation = activation
        self.occupancy_cell = float(occupancy_cell)
        shape = grid_shape(self.box, voxel_size)
        self.density = nn.Parameter(torch.full(shape, EMPTY_DENSITY))
        self.color = nn.Parameter(torch.zeros(*shape, 3))
        occ_shape = grid_shape(self.box, occupancy_cell) if occupancy_cell > 0 else (1, 1, 1)
        self.register_buffer("occupancy", torch.ones(occ_shape, dtype=torch.uint8))

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.density.shape)

    def activate(self, raw: torch.Tensor) -> torch.Tensor:
        """Density from raw grid values. The renderer looks the raw grid up first and activates after, so a
        density between nodes is ``activate(trilinear(raw))``, not the (larger: softplus is convex) trilinear
        look-up of activated nodes."""
        return F.softplus(raw) if self.activation == "softplus" else torch.relu(raw)

    def body_distance(self, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(X, Y, Z) the signed distance of every node to the canonical body, exact within ``EXACT_VOXELS`` voxels
        of it and a bound with the right sign beyond (:func:`grid_signed_distance`)."""
        exact_within = EXACT_VOXELS * self.voxel_size
        return grid_signed_distance(self.box.double(), self.shape, vertices, normals, exact_within)

    def init_from_body(
        self, sdf: np.ndarray, vertices: np.ndarray, normals: np.ndarray, inside: float = 3.0, room: Room | None = None
    ) -> None:
        """Start from the body prior: opaque inside the canonical mesh, empty outside; ``sdf`` is
        :meth:`body_distance` of the body (``vertices``, ``normals``).

        ``room`` limits the occupancy grid to the points within its room of the body (clothing, hair),
        so rays skip the rest of the box from the first step on.
        """
        # A smooth step from `inside` (one voxel inside the surface) to empty (one voxel outside).
        t = np.clip(0.5 - sdf / (2 * self.voxel_size), 0.0, 1.0)
        with torch.no_grad():
            self.density.copy_(torch.as_tensor(EMPTY_DENSITY + t * (inside - EMPTY_DENSITY), dtype=torch.float32))
        if room is not None and self.occupancy_cell > 0:
            cells = grid_points(self.box.double(), tuple(self.occupancy.shape)).reshape(-1, 3).numpy()
            allowed = signed_distance(cells, vertices, normals) < room(cells) + self.occupancy_cell
            self.occupancy.copy_(torch.as_tensor(allowed.reshape(self.occupancy.shape), dtype=torch.uint8))

    @torch.no_grad()
    def fill(self, inside: np.ndarray, value: float = 3.0) -> None:
        """Make the cells where the flat bool mask ``inside`` is set at least ``value`` dense (raw)."""
        flat = self.density.view(-1)
        cells = torch.as_tensor(np.flatnonzero(inside), device=flat.device)
        flat[cells] = flat[cells].clamp(min=value)

    @torch.no_grad()
    def set_colors_by_part(self, vertices: np.ndarray, vertex_parts: np.ndarray, part_colors: np.ndarray) -> None:
        """Colour every cell with the colour of the body part of its nearest body vertex."""
        pts = grid_points(self.box.double(), self.shape).reshape(-1, 3).numpy()
        _, idx = nearest(cKDTree(vertices), pts)
        rgb = np.clip(part_colors[vertex_parts[idx]], 0.02, 0.98)
        logits = np.log(rgb / (1 - rgb)).reshape(*self.shape, 3)
        self.color.copy_(torch.as_tensor(logits, dtype=torch.float32))

    def random_block(self, block: int = 40, generator: torch.Generator | None = None) -> tuple[slice, ...]:
        """A random ``block``^3 sub-grid, for cheap unbiased estimates of whole-grid regularisers."""
        with on_host():  # a CPU generator's draws
            start = [int(torch.randint(0, max(1, n - block) + 1, (1,), generator=generator)) for n in self.shape]
        return tuple(slice(s, s + block) for s in start)

    def sparsity_loss(self, density: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        """Cauchy sparsity ``log(1 + 2 sigma^2)`` of a block of the raw density, counted where ``where`` (the same
        block of a mask) is 1."""
        sigma = self.activate(density)
        return (torch.log1p(2 * sigma**2) * where).mean()


ROOM_BLEND = 0.02  # metres outside the surface where the motion weights pass from the body's to the room's


class MotionWeights(BoxedVolume):
    """Skinning weights over canonical space: softmax over (bones + background) logits on a grid."""

    def __init__(self, box: torch.Tensor, n_bones: int, resolution: int = 32) -> None:
        super().__init__(box)
        self.n_bones = n_bones
        self.logits = nn.Parameter(torch.zeros(n_bones + 1, resolution, resolution, resolution))

    def init_from_body(
        self, vertices: np.ndarray, normals: np.ndarray, weights: np.ndarray, room: Room, room_weight: float = 1.0
    ) -> None:
        """Splat the body's (reduced) skinning weights (:func:`splat_weights`); the background takes over
        beyond the ``room`` outside the surface, and within it the bones keep ``room_weight`` of their weight
        (1 on and inside the body, blending over the first few centimetres)."""
        shape = tuple(self.logits.shape[1:])
        pts = grid_points(self.box.double(), shape).reshape(-1, 3).numpy()
        bones = splat_weights(pts, vertices, weights)
        sdf = signed_distance(pts, vertices, normals)
        on_body = 1.0 / (1.0 + np.exp((sdf - ROOM_BLEND) / 0.01))
        fg = (room_weight + (1.0 - room_weight) * on_body) / (1.0 + np.exp((sdf - room(pts)) / 0.02))
        probs = np.concatenate([bones * fg[:, None], (1.0 - fg)[:, None]], 1)
        logits = np.log(np.maximum(probs, 1e-8)).T.reshape(self.n_bones + 1, *shape)
        with torch.no_grad():
            self.logits.copy_(torch.as_tensor(logits, dtype=torch.float32))

    def forward(self) -> torch.Tensor:
        """(B, R, R, R) bone weights (the background channel dropped, as HumanNeRF)."""
        return torch.softmax(self.logits, 0)[:-1].contiguous()
