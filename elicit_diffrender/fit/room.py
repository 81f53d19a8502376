"""Room for what the photo shows beyond the body: hair, loose clothing, a large head.

The avatar may hold density within ``box_margin`` of the canonical body. Where the input mask
reaches further from the body's own silhouette than that, the room grows to that reach (plus
``SLACK``), but only at the canonical points whose place in the input pose projects inside the mask:
one photo says how far hair stands out sideways and up, not how far back, so the room in depth is
the same reach, and the novel-view terms and the sparsity prior decide what fills it.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..field import Room, splat_weights
from ..mesh_render import MeshRenderer
from ..subject import Subject

SLACK = 0.03  # metres added to the measured reach
MAX_REACH = 0.5  # metres: a mask further than this from the body is not the person's
MIN_SHARE = 0.002  # mask pixels beyond the margin, as a share of the mask, that count as more than the body
WORK_SIZE = 512  # the mask is compared at most at this size (pixels, longer side)


def input_room(subject: Subject, margin: float) -> Room:
    """The room of ``subject``'s avatar: ``margin``, grown where its input mask reaches further from the body."""
    body = subject.body
    posed = body.pose(*subject.motion.frame(subject.input_index))
    cam = subject.cameras[subject.input_camera]
    scale = min(1.0, WORK_SIZE / max(cam.width, cam.height))
    cam = cam.scaled(scale)
    person = subject.mask(subject.input_camera, subject.input_frame).astype(np.float32)
    person = ndimage.zoom(person, (cam.height / person.shape[0], cam.width / person.shape[1]), order=1) > 0.5
    silhouette = MeshRenderer(body.faces).render(posed.vertices, [cam], ("mask",))["mask"][0] > 0.5
    _, depth = cam.project(posed.vertices)
    metres_per_pixel = float(np.median(depth)) / float(cam.K[0, 0])
    beyond = ndimage.distance_transform_edt(~silhouette) * metres_per_pixel
    outside = person & (beyond > margin) & (beyond < MAX_REACH)
    if outside.sum() < MIN_SHARE * max(person.sum(), 1):
        return Room(margin)
    reach = float(np.percentile(beyond[outside], 99)) + SLACK
    inside = ndimage.binary_dilation(person, iterations=2)
    canon = body.pose(body.canonical_pose())
    can_to_obs = body.reduced_transforms(posed) @ np.linalg.inv(body.reduced_transforms(canon))
    weights = body.reduced_weights()

    def extends(points: np.ndarray) -> np.ndarray:
        """Canonical points whose place in the input pose projects inside the (dilated) input mask."""
        w = splat_weights(points, canon.vertices, weights)
        posed_pts = np.einsum("pb,bij,pj->pi", w, can_to_obs[:, :3, :3], points) + w @ can_to_obs[:, :3, 3]
        uv, z = cam.project(posed_pts)
        px = np.floor(uv).astype(int)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        hit = np.zeros(len(points), dtype=bool)
        hit[ok] = inside[px[ok, 1], px[ok, 0]]
        return hit

    return Room(margin, reach, extends)
