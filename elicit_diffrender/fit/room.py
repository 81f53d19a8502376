"""Room for what the photo shows beyond the body: hair, loose clothing, a large head, a skirt's depth.

The avatar may hold density within ``box_margin`` of the canonical body. Where the input mask
reaches further from the body's own silhouette than that, the room grows to that reach (plus
``SLACK``), but only at the canonical points whose place in the input pose projects inside the mask:
one photo says how far hair stands out sideways and up, not how far back, so the room in depth is
the same reach, and the novel-view terms and the sparsity prior decide what fills it.

A garment that bridges the legs (a skirt, a dress) is the exception where one photo does say more:
at an image row where the mask covers the whole gap between the body's two legs, the mask's run
over the legs is the garment's width there, and the garment is taken to be as deep as it is wide:
a circular cross-section about the legs' centre at that row (``garment_hull``). Its cells get the
room they need, and stage 2 starts with them opaque (:meth:`CanonicalField.fill`), so that side
views show the skirt's depth instead of a skirt that hugs the thighs.

Hair that stands off the head's outline in the photo (above the ears) stands off the back of the
head too, which the photo cannot show: ``hair_hull`` takes the outline's median standoff all round
the hair-covered head, and its cells are treated like a garment's (room, opaque from stage 2 on).
Without it, the back of a voluminous head of hair was flat and the photo's hair was smeared in
front of the face instead (looked at on the synthetic subjects with hair volume).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..body import PART_NAMES, BodyModel, PosedBody
from ..body.template import vertex_normals
from ..core.cameras import Camera
from ..data.mesh_render import MeshRenderer
from ..data.subject import Subject
from ..model.field import Room, nearest, signed_distance, splat_weights

SLACK = 0.03  # metres added to the measured reach
MAX_REACH = 0.5  # metres: a mask further than this from the body is not the person's
MIN_SHARE = 0.002  # mask pixels beyond the margin, as a share of the mask, that count as more than the body
WORK_SIZE = 512  # the mask is compared at most at this size (pixels, longer side)
LEGS = (("left_thigh", "left_shin"), ("right_thigh", "right_shin"))
LEG_PARTS = tuple(tuple(PART_NAMES.index(n) for n in side) for side in LEGS)  # indices into PART_NAMES, per side
MIN_GAP = 0.07  # metres: a garment bridges a gap this wide between the legs somewhere (touching thighs do not)
MAX_HOLE = 6  # rows: the garment's band runs on through this many rows that do not bridge
WIDTH_SMOOTHING = 9  # rows: the garment's width is the running median over this many rows (a hand beside it)
HULL_LATTICE = 0.02  # metres between the points that measure how far the hull stands off the body
MIN_HAIR = 0.01  # metres: hair that stands off the head's outline by less than this gets no hull ...
MIN_HAIR_PIXELS = 2.0  # ... or by fewer pixels than this (a pixel's disagreement of mask and body is no hair)


@dataclass
class InputFrame:
    """The input view at the work size: camera, person mask, the body's part labels and vertices in the input
    pose, and the map of canonical points to their place in the input pose (the body's own skinning)."""

    camera: Camera
    person: np.ndarray  # (H, W) bool
    labels: np.ndarray  # (H, W) int body part, -1 background
    posed: np.ndarray  # (V, 3) the body's vertices in the input pose
    canonical: np.ndarray  # (V, 3) in the canonical pose
    normals: np.ndarray  # (V, 3) canonical vertex normals
    vertex_parts: np.ndarray  # (V,)
    to_input_pose: Callable[[np.ndarray], np.ndarray]

    @classmethod
    def load(cls, subject: Subject) -> InputFrame:
        body = subject.body
        posed = body.pose(*subject.motion.frame(subject.input_index))
        cam = subject.cameras[subject.input_camera]
        cam = cam.scaled(min(1.0, WORK_SIZE / max(cam.width, cam.height)))
        person = subject.mask(subject.input_camera, subject.input_frame).astype(np.float32)
        person = ndimage.zoom(person, (cam.height / person.shape[0], cam.width / person.shape[1]), order=1) > 0.5
        labels = MeshRenderer(body.faces, face_labels=body.face_parts()).render(posed.vertices, [cam], ("labels",))
        canon = body.pose(body.canonical_pose())
        normals = vertex_normals(canon.vertices, body.faces)
        return cls(
            cam, person, labels["labels"][0], posed.vertices, canon.vertices, normals, body.vertex_parts(),
            canonical_to_pose(body, posed),
        )  # fmt: skip

    def in_mask(self, points: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """(P,) bool: input-pose ``points`` that project inside ``mask`` (default: the person mask)."""
        inside = self.person if mask is None else mask
        px, _, ok = self.camera.pixels(points, inside.shape)
        hit = np.zeros(len(points), dtype=bool)
        hit[ok] = inside[px[ok, 1], px[ok, 0]]
        return hit


def canonical_to_pose(body: BodyModel, posed: PosedBody) -> Callable[[np.ndarray], np.ndarray]:
    """The map of canonical points (P, 3) to their place in ``posed``: the body's own skinning, each point with the
    blend of its nearest vertices' weights (:func:`splat_weights`)."""
    canon = body.pose(body.canonical_pose())
    can_to_obs = body.reduced_transforms(posed) @ np.linalg.inv(body.reduced_transforms(canon))
    weights = body.reduced_weights()
    frames = can_to_obs[:, :3, :].reshape(len(can_to_obs), 12)  # each bone's 3 x 4 map, flat

    def to_pose(points: np.ndarray) -> np.ndarray:
        blended = (splat_weights(points, canon.vertices, weights) @ frames).reshape(-1, 3, 4)  # each point's own map
        return np.einsum("pij,pj->pi", blended[:, :, :3], points) + blended[:, :, 3]

    return to_pose


def input_room(subject: Subject, margin: float, garment: bool = True, hair: bool = True) -> Room:
    """The room of ``subject``'s avatar: ``margin``, grown where its input mask reaches further from the body,
    and over the hulls of the hair round the head (with ``hair``) and of a garment that bridges the legs (with
    ``garment``)."""
    frame = InputFrame.load(subject)
    room = Room(margin)
    silhouette = frame.labels >= 0
    _, depth = frame.camera.project(frame.posed)
    metres_per_pixel = float(np.median(depth)) / float(frame.camera.K[0, 0])
    beyond = ndimage.distance_transform_edt(~silhouette) * metres_per_pixel
    outside = frame.person & (beyond > margin) & (beyond < MAX_REACH)
    if outside.sum() >= MIN_SHARE * max(frame.person.sum(), 1):
        room.reach = float(np.percentile(beyond[outside], 99)) + SLACK
        grown = ndimage.binary_dilation(frame.person, iterations=2)
        room.extends = lambda points: frame.in_mask(frame.to_input_pose(points), grown)
    tests, reaches, names = [], [], []
    hair_found = hair_hull(frame, metres_per_pixel) if hair else None
    if hair_found is not None:
        tests.append(hair_found[0])
        reaches.append(min(hair_found[1] + SLACK, MAX_REACH))
        names.append("hair")
    hull = garment_hull(frame) if garment else None
    if hull is not None:
        legs = frame.canonical[np.isin(frame.vertex_parts, np.ravel(LEG_PARTS))]
        lo, hi = legs.min(0) - MAX_REACH, legs.max(0) + MAX_REACH
        axes = [np.arange(lo[a], hi[a], HULL_LATTICE) for a in range(3)]
        lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        lattice = lattice[signed_distance(lattice, frame.canonical, frame.normals) < MAX_REACH]
        inside = lattice[hull(lattice)]
        if len(inside):
            off = signed_distance(inside, frame.canonical, frame.normals)
            tests.append(hull)
            reaches.append(float(min(off.max() + SLACK, MAX_REACH)))
            names.append("garment")
    if tests:
        room.hull = lambda points: np.logical_or.reduce([test(points) for test in tests])
        room.hull_reach, room.hull_names = max(reaches), tuple(names)
    return room


def hair_hull(frame: InputFrame, metres_per_pixel: float) -> tuple[Callable[[np.ndarray], np.ndarray], float] | None:
    """The hair's hull, as a test of canonical points, and its depth in metres (None where the hair stands off
    the head by less than ``MIN_HAIR`` or ``MIN_HAIR_PIXELS``: a bald head, hair flat on the skull). The depth
    is how far the person mask stands off the body's head outline above the ears in the input view: the median
    over that outline, an outline pixel with nothing beyond it counting 0. The hull holds the points within
    that depth outside the hair-covered head (above the ears, and behind them down to the nape; not the face)
    whose place in the input pose projects inside the mask: the sides and top as the photo shows them, and the
    back of the head, which it cannot show."""
    from .completion import hair_covered, head_layout

    head = PART_NAMES.index("head")
    silhouette = frame.labels >= 0
    layout = head_layout(frame.canonical, frame.vertex_parts)
    ear_y = layout[0]
    on_head = frame.vertex_parts == head
    ears, _ = frame.camera.project(frame.posed[on_head & (np.abs(frame.canonical[:, 1] - ear_y) < 0.02)])
    if not len(ears):
        return None
    outline = (frame.labels == head) & ~ndimage.binary_erosion(silhouette)
    outline &= (np.arange(outline.shape[0]) < float(np.median(ears[:, 1])))[:, None]  # above the ears
    if not outline.any():
        return None
    distance, (rows, cols) = ndimage.distance_transform_edt(~silhouette, return_indices=True)
    beyond = frame.person & ~silhouette & outline[rows, cols]
    standoff = np.zeros(outline.shape)
    np.maximum.at(standoff, (rows[beyond], cols[beyond]), distance[beyond])
    pixels = float(np.median(standoff[outline]))
    depth = pixels * metres_per_pixel
    if depth < MIN_HAIR or pixels < MIN_HAIR_PIXELS:
        return None
    scalp = hair_covered(frame.canonical, frame.vertex_parts, layout)
    tree = cKDTree(frame.canonical)
    reach = depth + HULL_LATTICE  # a point that close to the scalp's surface lies this close to a scalp vertex
    lo, hi = frame.canonical[scalp].min(0) - reach, frame.canonical[scalp].max(0) + reach

    def contains(points: np.ndarray) -> np.ndarray:
        """(P,) bool: canonical ``points`` within the hair's depth off the hair-covered head."""
        hit = np.all((points >= lo) & (points <= hi), axis=1)  # the head's box first: a grid is millions of points
        if hit.any():
            sdf = signed_distance(points[hit], frame.canonical, frame.normals, tree=tree)
            hit[hit] = (sdf > 0) & (sdf <= depth)
        if hit.any():
            _, owner = nearest(tree, points[hit])
            hit[np.flatnonzero(hit)[~scalp[owner]]] = False
        if hit.any():
            hit[hit] = frame.in_mask(frame.to_input_pose(points[hit]))
        return hit

    return contains, depth


def garment_hull(frame: InputFrame) -> Callable[[np.ndarray], np.ndarray] | None:
    """The hull of a garment that bridges the legs in the input view, as a test of canonical points (None when
    no garment does): circular cross-sections, one per image row of the garment's band, as wide as the mask's
    run over the legs there, centred on the legs' middle (left/right in the image, front/back from the legs'
    vertices). Thighs that touch bridge a narrow gap too, so only a band that bridges a gap of at least
    ``MIN_GAP`` counts; it runs from there up and down through bridged rows (holes up to ``MAX_HOLE`` rows)."""
    cam, person, labels = frame.camera, frame.person, frame.labels
    leg_ids = np.ravel(LEG_PARTS)
    legs = [np.isin(labels, side) for side in LEG_PARTS]
    passable = (labels < 0) | np.isin(labels, leg_ids)  # the run stops at arms and hands
    uv, z = cam.project(frame.posed)
    on_legs = np.isin(frame.vertex_parts, leg_ids)
    fx, cx = float(cam.K[0, 0]), float(cam.K[0, 2])
    left, right, depth, gap = (np.full(cam.height, np.nan) for _ in range(4))
    for v in np.nonzero(legs[0].any(1) & legs[1].any(1))[0]:
        spans = sorted((c.min(), c.max()) for c in (np.nonzero(legs[0][v])[0], np.nonzero(legs[1][v])[0]))
        (a0, a1), (b0, b1) = spans
        between = slice(a1 + 1, b0)
        if b0 - a1 < 3 or not person[v, between].all() or (labels[v, between] >= 0).all():
            continue  # legs touching, apart in the photo, or joined by the body itself (the crotch)
        near = on_legs & (np.abs(uv[:, 1] - (v + 0.5)) <= 2.0)
        if not near.any():
            continue  # no leg vertices at this row
        x0, x1 = a0, b1
        while x0 > 0 and person[v, x0 - 1] and passable[v, x0 - 1]:
            x0 -= 1
        while x1 < cam.width - 1 and person[v, x1 + 1] and passable[v, x1 + 1]:
            x1 += 1
        # The legs' middle in depth: halfway between their nearest and furthest vertices at this row.
        depth[v] = 0.5 * (z[near].min() + z[near].max())
        left[v], right[v], gap[v] = x0, x1 + 1, (b0 - a1 - 1) * depth[v] / fx
    bridged = ~np.isnan(left)
    if not (gap[bridged] >= MIN_GAP).any():
        return None
    seed = int(np.nanargmax(gap))
    band = np.zeros(cam.height, dtype=bool)
    for direction in (-1, 1):
        v, hole = seed, 0
        while 0 <= v < cam.height and hole <= MAX_HOLE:
            hole = 0 if bridged[v] else hole + 1
            band[v] = True
            v += direction
    rows = np.nonzero(band & bridged)[0]
    band[: rows.min()] = band[rows.max() + 1 :] = False
    every = np.arange(cam.height)
    left, right, depth = (np.interp(every, rows, a[rows]) for a in (left, right, depth))
    width = ndimage.median_filter(right - left, size=WIDTH_SMOOTHING, mode="nearest")
    radius = 0.5 * width * depth / fx  # metres
    middle = ((left + right) / 2 - cx) * depth / fx  # camera x of the centre, metres

    def contains(points: np.ndarray) -> np.ndarray:
        """(P,) bool: canonical ``points`` inside the garment's hull."""
        posed = frame.to_input_pose(points)
        x_cam = cam.world_to_camera(posed)
        uv_p, _ = cam.project(posed)
        v = np.floor(uv_p[:, 1]).astype(int)
        ok = (v >= 0) & (v < cam.height) & (x_cam[:, 2] > 0)
        ok[ok] = band[v[ok]]
        hit = np.zeros(len(points), dtype=bool)
        r = v[ok]
        hit[ok] = (x_cam[ok, 0] - middle[r]) ** 2 + (x_cam[ok, 2] - depth[r]) ** 2 <= radius[r] ** 2
        return hit & frame.in_mask(posed)

    return contains
