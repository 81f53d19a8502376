"""The weights-free semantic prior: colour what the input camera does not see from what it sees, relit.

One photo shows one side of a person. Without CLIP weights nothing here knows what a back looks
like, but a body is close to symmetric: the back of a sleeve has the colour of its front, the left
leg that of the right. Every colour cell of the canonical grid near the body whose nearest body
vertex the input camera does not see gets a *source* point that it does see, by the first rule
that finds one: its mirror image through its body part's frontal plane (front <-> back; not for
the head, whose back is hair, not a face), through the body's sagittal plane (left <-> right),
through both; the head's back instead copies the nearest seen vertex of its crown (the up-facing
top ``CROWN_DEPTH`` of the head: hair, a hat or bare skin, not the face); else the nearest seen
vertex of the cell's own part, else the nearest seen vertex. The torso's front middle
(``FRONT_STRIP`` each side of the midline: a tie, a placket, a V-neck, an open jacket's gap) is
copied nowhere: a back cell there mirrors the front beside it. The photo's light (``fit.shading``,
fitted to the seen body) says how much darker or brighter the cell's side is than its source's, so
the target is

    t_c = sigmoid(blur(c)(source_c)) * S(n_c) / S(n_source)

with ``S`` evaluated at the input-pose normals of the two points' nearest body vertices, and the term

    L = mean_c sigmoid'(0)^2 || c_cell - logit(t_c) ||^2

pulls every unseen cell's colour logits ``c_cell`` towards it. The pull acts on the logits, as the grid's
smoothness does: through the sigmoid its gradient vanished on dark and saturated targets, and the smoothness
blurred garment borders on the unseen side (the top faded into the trousers at the waist); ``sigmoid'(0)^2``
keeps its strength on mid-tones. Targets are clamped to ``TARGET_RANGE``. ``blur`` is the mean of
trilinear look-ups at the source and six points ``BLUR_VOXELS`` away; the targets are detached and
recomputed every ``REFRESH`` steps (the seen side they copy changes slowly). No render, no encoder.

A vertex is seen when it faces the input camera, projects inside the input mask and lies within
``DEPTH_TOLERANCE`` of the depth of the body's own surface there. A completed cell on the body's far side in every
photo (:func:`behind_body`: past the middle of the ray's way through the body) takes its colour from the completion
alone: a photo's rays that cross a soft or thin front do not paint it. A seen vertex is no source when it lies within
the arms' reach in front of the body (:func:`within_held_reach`): what the photo shows there may be a folder, a
phone or a bag the hands hold, which the back does not carry.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ..body import PART_NAMES
from ..core.cameras import Camera
from ..model.field import CanonicalField, grid_axes, nearest, node_points

DEPTH_TOLERANCE = 0.03  # metres: a vertex this far behind the visible surface is hidden
EXIT_SPREAD = 3  # pixels over which a vertex's depth marks where rays leave the body
INSIDE_VOXELS = 2.0  # cells down to this many voxels inside the body surface are coloured
BLUR_VOXELS = 1.5  # spacing of the blur stencil at the source
NO_FRONT_BACK = ("head",)  # parts whose back is not their mirrored front: they copy their crown
CROWN_UP = 0.5  # a vertex whose canonical normal's up component exceeds this ...
CROWN_DEPTH = 0.06  # ... and that lies at most this far (metres) below its part's top is on the crown
REFRESH = 10  # steps between recomputations of the targets
TARGET_RANGE = (0.01, 0.99)  # target colours are clamped here: their logits stay finite
MID_TONE_SLOPE = 0.25  # sigmoid'(0): the pull on the logits matches a pull on colours at mid-tones
# The guarded rule (``completion = "guarded"``) compares a mirror source's photo colour with what the cell's part
# shows at the cell's band (its place along the part's axis): the mode of the photo colours of the well-seen points
# within ``BAND_HALF`` of it along the axis (at most ``BAND_MOST`` of them, evenly spread). A point is well seen when
# its normal is within ``WELL_SEEN`` (cosine) of the way to the camera (nearer the silhouette a pixel is smeared over
# the surface and mixed with the background).
BAND_HALF = 0.025
BAND_MOST = 48
WELL_SEEN = 0.3
MIN_PART_SEEN = 30  # a part with fewer well-seen vertices has no band colour to compare with
GUARD_RADIUS = 0.15  # colour radius of a band's mode: a garment's pattern is one colour, two garments are two
DETAIL_DISTANCE = 0.2  # a mirror source this far in colour from its band's mode shows a front-only detail
MODE_CHUNK = 4096  # cells whose candidates' colour distances are compared at once
HAIR_CANDIDATES = 16  # seen hair points whose mode colour a scalp cell takes
# The head: a cell behind the ears or above them takes the hair the photo shows round the face, if it shows hair:
# at least HAIR_SHARE of the head's upper seen vertices darker than HAIR_DARKER times the face's skin, or of
# another hue (chromaticity at least HAIR_HUE from the skin's); a forehead lit brighter than the cheeks is skin.
HAIR_DARKER = 0.7
HAIR_HUE = 0.05
HAIR_SHARE = 0.3
FACE_HALF_WIDTH = 0.045  # metres each side of the face's midline: eyes, nose and mouth, copied nowhere
# Metres each side of the torso's midline: its front shows ties, plackets, V-necks, an open jacket's gap, a zip, a
# logo; never copied. A back cell there copies the front at this distance from the midline, near the side seams.
FRONT_STRIP = 0.12
# What the hands may hold: a forearm (with its hand) whose points lie at least FRONT_GAP in front of the torso's
# surface behind them in the image (HELD_SHARE of them or more) is held out in front; the image region they span
# (both arms together), grown by HELD_REACH, may show a held object instead of the torso. TORSO_NEAR: how close
# (metres, in the image) a torso point must project to count as behind a forearm point.
FRONT_GAP = 0.08
HELD_SHARE = 0.5
HELD_REACH = 0.15
TORSO_NEAR = 0.03


def facing_cosine(vertices: np.ndarray, normals: np.ndarray, camera: Camera) -> np.ndarray:
    """(V,) cosine between every vertex's (unit) normal and the way from it to the camera's centre."""
    to_camera = camera.center - vertices
    return np.einsum("vc,vc->v", normals, to_camera) / np.maximum(np.linalg.norm(to_camera, axis=1), 1e-9)


def visible_vertices(
    vertices: np.ndarray, normals: np.ndarray, camera: Camera, depth: np.ndarray, person: np.ndarray
) -> np.ndarray:
    """(V,) bool: which posed ``vertices`` (with outward ``normals``) the camera sees, given the body's
    (H, W) z-depth (0 = none) and the person's (H, W) mask."""
    px, z, inside = camera.pixels(vertices, depth.shape)
    facing = np.einsum("vc,vc->v", normals, camera.center - vertices) > 0
    seen = np.zeros(len(vertices), dtype=bool)
    u, v = px[inside, 0], px[inside, 1]
    d = depth[v, u]
    seen[inside] = person[v, u] & (d > 0) & (z[inside] <= d + DEPTH_TOLERANCE)
    return seen & facing


def exit_depth(vertices: np.ndarray, camera: Camera, depth: np.ndarray) -> np.ndarray:
    """(H, W) the z-depth where each pixel's ray leaves the posed body (its furthest vertex there, spread over
    ``EXIT_SPREAD`` pixels to close the gaps between vertices), where the body's (H, W) z-``depth`` (0 = none) has a
    first hit; 0 elsewhere."""
    px, z, ok = camera.pixels(vertices, depth.shape)
    far = np.zeros(depth.shape)
    np.maximum.at(far, (px[ok, 1], px[ok, 0]), z[ok])
    far = ndimage.grey_dilation(far, size=EXIT_SPREAD)
    return np.where(depth > 0, np.maximum(far, depth), 0.0)


def behind_body(points: np.ndarray, camera: Camera, depth: np.ndarray, far: np.ndarray) -> np.ndarray:
    """(P,) bool: posed ``points`` on the far side of the body in ``camera``: past the middle of each ray's way
    through it (between its (H, W) z-``depth`` of entry, 0 = none, and its ``far`` depth of exit, :func:`exit_depth`)
    and more than ``DEPTH_TOLERANCE`` behind the entry. What the camera's photo shows there lies in front of them."""
    px, z, inside = camera.pixels(points, depth.shape)
    behind = np.zeros(len(points), dtype=bool)
    d, e = depth[px[inside, 1], px[inside, 0]], far[px[inside, 1], px[inside, 0]]
    behind[inside] = (d > 0) & (z[inside] > np.maximum(d + DEPTH_TOLERANCE, 0.5 * (d + e)))
    return behind


def within_held_reach(
    vertices: np.ndarray, vertex_parts: np.ndarray, facing: np.ndarray, camera: Camera, seen: np.ndarray
) -> np.ndarray:
    """(V,) bool: the seen torso vertices (posed ``vertices``; ``facing``: :func:`facing_cosine` to ``camera``)
    that may lie behind something the hands hold: they project into the image region spanned by the forearms held
    out in front of the torso, grown by ``HELD_REACH``. None when no forearm is held out.

    A forearm point is in front when it lies ``FRONT_GAP`` nearer the camera than the torso's camera-facing surface
    that projects within ``TORSO_NEAR`` of it; a forearm is held out when at least ``HELD_SHARE`` of its points
    are. The region is the convex hull of those points (both arms together), grown by the reach in pixels at their
    median depth (mitred corners)."""
    out = np.zeros(len(vertices), dtype=bool)
    is_torso = vertex_parts == PART_NAMES.index("torso")
    torso = is_torso & (facing > 0)
    if not torso.any():
        return out
    uv, z = camera.project(vertices)
    pixels_per_metre = float(camera.K[0, 0]) / np.median(z[torso])
    tree, torso_z = cKDTree(uv[torso]), z[torso]
    in_front = []
    for name in ("left_forearm", "right_forearm"):
        arm = np.nonzero(vertex_parts == PART_NAMES.index(name))[0]
        near = tree.query_ball_point(uv[arm], TORSO_NEAR * pixels_per_metre)
        front = np.array([len(n) > 0 and z[i] < torso_z[n].min() - FRONT_GAP for i, n in zip(arm, near, strict=True)])
        if arm.size and front.mean() >= HELD_SHARE:
            in_front.append(arm[front])
    if not in_front:
        return out
    held = np.concatenate(in_front)
    try:
        hull = ConvexHull(uv[held])
    except QhullError:  # too few or collinear points span no region
        return out
    reach = HELD_REACH * float(camera.K[0, 0]) / np.median(z[held])
    outside = np.max(uv @ hull.equations[:, :2].T + hull.equations[:, 2], axis=1)  # mitred distance to the hull
    return seen & is_torso & (outside < reach)


@dataclass
class MirrorCompletion:
    cells: torch.Tensor  # (N,) flat indices of unseen colour cells
    sources: torch.Tensor  # (N, 3) canonical positions of the seen points they copy
    gains: torch.Tensor  # (N,) S(n_cell) / S(n_source): the photo's light on the cell's side against the source's
    rule_counts: dict[str, int]  # how many cells each rule gave a source
    unseen: int  # unseen cells near the body
    colors: torch.Tensor | None = None  # (N, 3) fixed photo colours (the guarded rule; NaN: none); None: the grid's
    all_fixed: bool = False  # every cell has a fixed photo colour (no NaN in ``colors``)
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
        hull: np.ndarray | None = None,
        colors: np.ndarray | None = None,
        facing: np.ndarray | None = None,
        rule: str = "mirror",
        held: np.ndarray | None = None,
    ) -> MirrorCompletion:
        """Sources for ``field``'s unseen cells from the canonical body (``canonical`` vertices, ``normals``,
        ``vertex_parts``, and ``sdf``: ``field.body_distance`` of it) and which of its vertices the input camera
        sees; cells up to ``margin`` outside the body count, and the ``hull`` cells (flat bool: the room's hulls,
        :mod:`.room`) however far out. ``light`` (V,) is the photo's light ``S`` at every vertex (input pose); without
        it the gains are 1. ``colors`` (V, 3) are the photo's colours at the seen vertices (NaN elsewhere),
        ``facing`` (V,) the cosine between each vertex's normal and the way to the input camera; ``rule`` is
        ``"mirror"`` (:func:`mirror_sources`) or ``"guarded"`` (the mirror, with :func:`guard_details`). ``held`` (V,)
        marks seen vertices that are no source (:func:`within_held_reach`)."""
        sdf = sdf.reshape(-1)
        # Beyond EXACT_VOXELS outside the body ``sdf`` only bounds the distance from below: the nearest-vertex
        # query that finds each cell's owner also gives the distance that decides the room.
        room = sdf < margin if hull is None else (sdf < margin) | hull
        near = np.nonzero((sdf > -INSIDE_VOXELS * field.voxel_size) & room)[0]
        axes = [a.numpy() for a in grid_axes(field.box.double(), field.shape)]
        pts = node_points(axes, np.unravel_index(near, field.shape))  # of ``near``
        tree = cKDTree(canonical)
        dist, idx = nearest(tree, pts, within=max(margin, INSIDE_VOXELS * field.voxel_size))
        in_hull = np.zeros(near.size, dtype=bool) if hull is None else hull[near]
        # Only a hull's cells lie farther out and stay (the others there are neither inside nor within the margin):
        # find their owners too.
        far = np.nonzero(np.isinf(dist) & in_hull)[0]
        if far.size:
            dist[far], idx[far] = nearest(tree, pts[far])
        keep = (sdf[near] < 0) | (dist < margin) | in_hull
        near, idx, pts = near[keep], idx[keep], pts[keep]
        hidden = ~seen[idx]
        cells, p, owner = near[hidden], pts[hidden], idx[hidden]
        held = np.zeros(len(canonical), dtype=bool) if held is None else held
        sources_from = seen & ~held
        source, source_vertex, counts = mirror_sources(p, owner, canonical, normals, vertex_parts, sources_from, tree)
        colors = np.full((len(canonical), 3), np.nan) if colors is None else colors
        facing = np.ones(len(canonical)) if facing is None else facing
        color = None
        if rule == "guarded":
            color = guard_details(
                p, owner, source_vertex, canonical, normals, vertex_parts, sources_from, colors, facing, counts
            )
        if held.any():  # cells that would copy what the hands hold take their part's colour at their band
            _, would_copy, _ = mirror_sources(p, owner, canonical, normals, vertex_parts, seen, tree)
            refused = np.nonzero(held[would_copy])[0]
            well_seen = sources_from & (facing >= WELL_SEEN)
            part = vertex_parts[owner[refused]]
            band = band_colors(p[refused], part, canonical, vertex_parts, well_seen, colors, BAND_HALF)
            lost = np.isnan(band[:, 0])
            band[lost] = band_colors(p[refused[lost]], part[lost], canonical, vertex_parts, well_seen, colors, np.inf)
            color = np.full((len(p), 3), np.nan) if color is None else color
            color[refused] = band
            counts["held in front: band colour"] = int(refused.size)
        has = ~np.isnan(source[:, 0])
        gains = np.ones(len(cells)) if light is None else light[owner] / light[source_vertex]
        device = field.color.device
        return cls(
            torch.as_tensor(cells[has], dtype=torch.long, device=device),
            torch.as_tensor(source[has], dtype=torch.float32, device=device),
            torch.as_tensor(gains[has], dtype=torch.float32, device=device),
            counts,
            int(cells.size),
            None if color is None else torch.as_tensor(color[has], dtype=torch.float32, device=device),
            color is not None and not np.isnan(color[has][:, 0]).any(),
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
        """(N, 3) the relit colour of every cell's source: its fixed photo colour where it has one, else the
        grid's, blurred."""
        if self.colors is not None and self.all_fixed:
            return (self.colors * self.gains[:, None]).clamp(0.0, 1.0)
        logits = torch.sparse.mm(self.blur_matrix(field), field.color.detach().reshape(-1, 3))
        live = torch.sigmoid(logits)
        if self.colors is not None:
            live = torch.where(torch.isnan(self.colors[:, :1]), live, self.colors)
        return (live * self.gains[:, None]).clamp(0.0, 1.0)

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
        target = torch.logit(self._target.clamp(*TARGET_RANGE))
        return MID_TONE_SLOPE**2 * ((cell_logits - target) ** 2).sum(-1).mean()


def mirror_sources(
    p: np.ndarray,
    owner: np.ndarray,
    canonical: np.ndarray,
    normals: np.ndarray,
    vertex_parts: np.ndarray,
    seen: np.ndarray,
    tree: cKDTree,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The mirror rule: for cells at ``p`` (owned by body vertices ``owner``), the first seen point among their
    mirror image through their part's frontal plane (not for the head; a torso cell within ``FRONT_STRIP`` of the
    body's midline takes it moved sideways to that distance, on its own side), through the body's sagittal plane,
    through both; the head's crown for the head; the nearest seen vertex of their part; the nearest seen vertex.
    The image moved sideways is put at the cell's own height above the body's surface (``(p - x_owner) .
    n_owner``) over the body vertex nearest to it: a chest beside its middle is flatter than the back's middle is
    deep, and the plain image would fall in the air in front of it, copying no garment's colour.
    Returns the (N, 3) sources (NaN: none), their body vertices and how many cells each rule served."""
    part = vertex_parts[owner]
    centre_z = np.zeros(len(PART_NAMES))
    for k in np.unique(vertex_parts):
        centre_z[k] = canonical[vertex_parts == k, 2].mean()
    front_back = p.copy()
    front_back[:, 2] = 2 * centre_z[part] - p[:, 2]
    mid = canonical[:, 0].mean()
    left_right = p.copy()
    left_right[:, 0] = 2 * mid - p[:, 0]
    both = np.stack([left_right[:, 0], p[:, 1], front_back[:, 2]], 1)
    mirrored_ok = ~np.isin(part, [PART_NAMES.index(n) for n in NO_FRONT_BACK])
    # The torso's front middle shows what its back does not: a tie, a placket, a V-neck, an open jacket's gap.
    off = p[:, 0] - mid
    in_strip = (part == PART_NAMES.index("torso")) & (np.abs(off) < FRONT_STRIP)
    beside = front_back.copy()
    beside[:, 0] = mid + np.where(off >= 0, 1.0, -1.0) * FRONT_STRIP
    source = np.full_like(p, np.nan)
    source_vertex = np.zeros(len(p), dtype=np.int64)
    counts = {}
    for name, candidate, allowed in (
        ("front/back beside the midline", beside, in_strip),
        ("front/back", front_back, mirrored_ok),
        ("left/right", left_right, np.ones(len(p), dtype=bool)),
        ("both", both, mirrored_ok),
    ):
        free = np.nonzero(np.isnan(source[:, 0]) & allowed)[0]
        _, cand = nearest(tree, candidate[free]) if free.size else (None, np.zeros(0, dtype=np.int64))
        ok = seen[cand]
        if name == "front/back beside the midline":
            rows, at = free[ok], cand[ok]
            height = np.einsum("nc,nc->n", p[rows] - canonical[owner[rows]], normals[owner[rows]])
            candidate[rows] = canonical[at] + height[:, None] * normals[at]
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
    return source, source_vertex, counts


def part_axes(canonical: np.ndarray, vertex_parts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every part's centre and long axis (the first principal direction of its vertices, pointing up or out)."""
    centres = np.zeros((len(PART_NAMES), 3))
    axes = np.tile([0.0, 1.0, 0.0], (len(PART_NAMES), 1))
    for k in np.unique(vertex_parts):
        v = canonical[vertex_parts == k]
        centres[k] = v.mean(0)
        if len(v) >= 3:
            axis = np.linalg.svd(v - centres[k], full_matrices=False)[2][0]
            axes[k] = axis if axis @ (centres[k] - canonical.mean(0)) >= 0 else -axis
    return centres, axes


def band_candidates(pool_along: np.ndarray, cell_along: np.ndarray, half: float, most: int) -> np.ndarray:
    """(N, most) indices into the pool of the points whose place along the axis lies within ``half`` of each
    cell's (evenly thinned to ``most``; -1 pads)."""
    order = np.argsort(pool_along)
    sorted_along = pool_along[order]
    lo = np.searchsorted(sorted_along, cell_along - half)
    hi = np.searchsorted(sorted_along, cell_along + half)
    count = hi - lo
    step = np.maximum(count / most, 1.0)
    k = np.arange(most)[None]
    index = lo[:, None] + np.floor(k * step[:, None]).astype(np.int64)
    valid = k < np.minimum(count, most)[:, None]
    return np.where(valid, order[np.clip(index, 0, len(order) - 1)], -1)


def robust_color(candidates: np.ndarray, colors: np.ndarray, radius: float) -> np.ndarray:
    """Per row of (N, K) candidate vertices (-1: none), the mode of their photo colours: the mean of the colours
    within ``radius`` of the candidate with most such neighbours, recentred once. What most of the candidates
    show wins, so a logo, a tie, a V-neck or a highlight among them neither becomes the colour nor tints it.
    Returns the (N, 3) modes (NaN where no candidate is known)."""
    mode = np.full((len(candidates), 3), np.nan)
    for start in range(0, len(candidates), MODE_CHUNK):
        cand = candidates[start : start + MODE_CHUNK]
        c = np.where((cand >= 0)[..., None], colors[np.maximum(cand, 0)], np.nan)  # (n, K, 3)
        known = ~np.isnan(c[..., 0])
        c0 = np.nan_to_num(c)
        close = np.linalg.norm(c0[:, :, None] - c0[:, None], axis=-1) < radius
        close &= known[:, :, None] & known[:, None]
        rows = np.arange(len(cand))
        centre = c0[rows, close.sum(2).argmax(1)]
        for _ in range(2):  # the mean of the seed's neighbours, then of the mean's
            near = (np.linalg.norm(c0 - centre[:, None], axis=-1) < radius) & known
            mean = (c0 * near[..., None]).sum(1) / np.maximum(near.sum(1, keepdims=True), 1)
            centre = np.where(near.any(1, keepdims=True), mean, centre)
        mode[start : start + MODE_CHUNK] = np.where(known.any(1, keepdims=True), centre, np.nan)
    return mode


def band_colors(
    p: np.ndarray,
    part: np.ndarray,
    canonical: np.ndarray,
    vertex_parts: np.ndarray,
    pool: np.ndarray,
    colors: np.ndarray,
    half: float,
) -> np.ndarray:
    """(N, 3) for cells at ``p`` of body parts ``part``: the mode (:func:`robust_color`) of the photo ``colors`` of
    the ``pool`` (V,) vertices of the same part whose place along the part's axis lies within ``half`` of the
    cell's (``np.inf``: the whole part). NaN where the part has fewer than ``MIN_PART_SEEN`` pool vertices or the
    band none."""
    centres, axes = part_axes(canonical, vertex_parts)
    mode = np.full((len(p), 3), np.nan)
    for k in np.unique(part):
        rows = np.nonzero(part == k)[0]
        members = np.nonzero(pool & (vertex_parts == k))[0]
        if len(members) < MIN_PART_SEEN:
            continue
        along = (canonical[members] - centres[k]) @ axes[k]
        cand = band_candidates(along, (p[rows] - centres[k]) @ axes[k], half, BAND_MOST)
        cand = np.where(cand >= 0, members[np.maximum(cand, 0)], -1)
        mode[rows] = robust_color(cand, colors, GUARD_RADIUS)
    return mode


def head_layout(canonical: np.ndarray, vertex_parts: np.ndarray) -> tuple[float, float, float]:
    """Height and depth of the ears and the midline's x on the canonical head (from ``select_vertices``)."""
    from ..body.fitting import select_vertices

    head = PART_NAMES.index("head")
    sel = select_vertices(
        canonical, vertex_parts, head, (PART_NAMES.index("left_shin"), PART_NAMES.index("right_shin"))
    )
    ears = canonical[[sel["ear.L"], sel["ear.R"]]]
    return float(ears[:, 1].mean()), float(ears[:, 2].mean()), float(ears[:, 0].mean())


def hair_covered(canonical: np.ndarray, vertex_parts: np.ndarray, layout: tuple[float, float, float]) -> np.ndarray:
    """(V,) bool: the head's vertices that hair covers when there is hair: above the ears, or behind them down
    to the nape (``layout``: :func:`head_layout`)."""
    ear_y, ear_z, _ = layout
    y, z = canonical[:, 1], canonical[:, 2]
    head = vertex_parts == PART_NAMES.index("head")
    return head & ((y > ear_y + 0.03) | ((z < ear_z + 0.01) & (y > ear_y - 0.05)))


def hair_pool(
    canonical: np.ndarray, normals: np.ndarray, vertex_parts: np.ndarray, seen: np.ndarray, colors: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V,) bool: the seen head vertices that show hair (darker than the face's skin or of another hue, above or
    behind the ears: the head's outline too, where the hair round a face shows), empty when the head shows too
    little of it (bald, a shaved head, a cap of skin colour); (V,) bool: the face's middle, which is never a
    source; (V,) bool: the head's vertices that hair covers when there is hair (above the ears, or behind them
    down to the nape)."""
    head = vertex_parts == PART_NAMES.index("head")
    layout = head_layout(canonical, vertex_parts)
    ear_y, ear_z, mid_x = layout
    y, z = canonical[:, 1], canonical[:, 2]
    scalp = hair_covered(canonical, vertex_parts, layout)
    face = head & (np.abs(canonical[:, 0] - mid_x) < FACE_HALF_WIDTH) & (z > ear_z + 0.04) & (y < ear_y + 0.05)
    known = seen & ~np.isnan(colors[:, 0])
    cheeks = known & head & (normals[:, 2] > 0.6) & (np.abs(y - ear_y) < 0.04)
    upper = known & head & ((y > ear_y + 0.03) | (z < ear_z))
    if cheeks.sum() < 5 or not upper.any():
        return np.zeros(len(canonical), dtype=bool), face, scalp
    skin = np.median(colors[cheeks], axis=0)
    rgb = np.nan_to_num(colors)
    luma = rgb.sum(1)
    hue = rgb / np.maximum(luma, 1e-6)[:, None]
    other_hue = np.linalg.norm(hue - skin / max(skin.sum(), 1e-6), axis=1) > HAIR_HUE
    hairy = upper & ((luma < HAIR_DARKER * skin.sum()) | other_hue)
    if hairy.sum() < max(10, HAIR_SHARE * upper.sum()):
        return np.zeros(len(canonical), dtype=bool), face, scalp
    return hairy, face, scalp


def guard_details(
    p: np.ndarray,
    owner: np.ndarray,
    source_vertex: np.ndarray,
    canonical: np.ndarray,
    normals: np.ndarray,
    vertex_parts: np.ndarray,
    seen: np.ndarray,
    colors: np.ndarray,
    facing: np.ndarray,
    counts: dict[str, int],
) -> np.ndarray:
    """The guarded mirror rule's fixed colours (N, 3; NaN: the mirror source's live colour stays): a cell whose
    mirror source shows a colour far (``DETAIL_DISTANCE``) from the mode of what its part shows at the cell's band
    (a tie, a V-neck, a logo: details on the front only) takes that mode instead; a head cell above or behind the
    ears takes the hair the photo shows round the face, when it shows hair."""
    color = np.full((len(p), 3), np.nan)
    part = vertex_parts[owner]
    well_seen = seen & (facing >= WELL_SEEN)
    hairy, face, scalp = hair_pool(canonical, normals, vertex_parts, seen, colors)
    mode = band_colors(p, part, canonical, vertex_parts, well_seen & ~face, colors, BAND_HALF)
    source_color = colors[source_vertex]
    detail = np.linalg.norm(source_color - mode, axis=1) > DETAIL_DISTANCE  # False where either is unknown
    color[detail] = mode[detail]
    counts["front detail: band colour"] = int(detail.sum())
    counts["hair"] = 0
    rows = np.nonzero(scalp[owner])[0]
    if hairy.any() and rows.size:
        pool = np.nonzero(hairy)[0]
        count = min(HAIR_CANDIDATES, len(pool))
        _, cand = nearest(cKDTree(canonical[pool]), p[rows], count)
        color[rows] = robust_color(pool[cand.reshape(len(rows), count)], colors, GUARD_RADIUS)
        counts["hair"] = int(rows.size)
    return color
