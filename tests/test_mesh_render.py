"""Mitsuba renders: exact labels, silhouettes equal depth > 0, per-part pixel counts, colour."""

import numpy as np
import pytest
import trimesh

from elicit_diffrender.body.template import template_colors
from elicit_diffrender.core.cameras import look_at
from elicit_diffrender.data.mesh_render import MeshAppearance, MeshRenderer, RenderError
from elicit_diffrender.data.rigs import ring_cameras


def first_hit_faces(vertices: np.ndarray, faces: np.ndarray, cam) -> np.ndarray:
    """Index of the triangle hit through every pixel centre (-1 for a miss): brute-force Moller-Trumbore."""
    o, d = (t.numpy().astype(np.float64) for t in cam.rays())
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a  # (F, 3)
    p = np.cross(d[:, None], e2[None])  # (R, F, 3)
    det = np.einsum("rfk,fk->rf", p, e1)
    inv = 1.0 / np.where(np.abs(det) < 1e-12, np.nan, det)
    s = o[:, None] - a[None]
    u = np.einsum("rfk,rfk->rf", s, p) * inv
    q = np.cross(s, e1[None])
    v = np.einsum("rk,rfk->rf", d, q) * inv
    t = np.einsum("fk,rfk->rf", e2, q) * inv
    hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(hit, t, np.inf)
    best = t.argmin(1)
    out = np.where(np.isfinite(t.min(1)), best, -1)
    return out.reshape(cam.height, cam.width)


def test_labels_are_exact_per_pixel():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 7, len(mesh.faces))
    cam = look_at([0.3, 0.4, 2.0], [0, 0, 0], [0, 1, 0], focal=90.0, width=64, height=48)
    out = MeshRenderer(np.asarray(mesh.faces), face_labels=labels).render(
        np.asarray(mesh.vertices), [cam], ("labels", "mask", "depth")
    )
    hit_faces = first_hit_faces(np.asarray(mesh.vertices), np.asarray(mesh.faces), cam)
    expected = np.where(hit_faces >= 0, labels[np.maximum(hit_faces, 0)], -1)
    agree = (out["labels"][0] == expected).mean()
    assert agree > 0.995, agree  # only pixel centres lying on a triangle edge may differ
    assert out["labels"].dtype == np.int16


def test_silhouette_depth_and_part_counts(anny_body):
    body = anny_body
    renderer = MeshRenderer(body.faces, MeshAppearance(vertex_colors=template_colors(body)), body.face_parts())
    cams = ring_cameras(n=4, focal=325, width=256, height=256)
    out = renderer.render(body.rest_vertices, cams, ("labels", "mask", "depth", "alpha", "color"), spp=8)
    np.testing.assert_array_equal(out["mask"] > 0, out["depth"] > 0)
    np.testing.assert_array_equal(out["mask"] > 0, out["labels"] >= 0)
    front = np.bincount(out["labels"][0][out["labels"][0] >= 0], minlength=10)
    assert (front > 40).all(), front  # every part is visible from the front
    assert front[0] > front[2] and front[0] > front[4]  # the torso is larger than an upper arm or a forearm
    # Depth: camera z of the body lies around the 3 m radius.
    d = out["depth"][0][out["mask"][0] > 0]
    assert 2.6 < d.min() < d.max() < 3.4
    # Soft alpha agrees with the hard mask except along edges.
    assert np.abs(out["alpha"] - out["mask"]).mean() < 0.02
    # A side view shows one arm mostly hiding the other.
    side = np.bincount(out["labels"][1][out["labels"][1] >= 0], minlength=10)
    assert side[2] != side[3]


def test_color_channel_is_the_albedo():
    mesh = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    col = np.tile([[0.2, 0.6, 0.9]], (len(mesh.vertices), 1))
    cam = look_at([1.0, 1.0, 2.0], [0, 0, 0], [0, 1, 0], focal=60.0, width=48, height=48)
    out = MeshRenderer(np.asarray(mesh.faces), MeshAppearance(vertex_colors=col)).render(
        np.asarray(mesh.vertices), [cam], ("color", "alpha"), spp=16
    )
    inside = out["alpha"][0] > 0.999
    np.testing.assert_allclose(out["color"][0][inside], np.tile([0.2, 0.6, 0.9], (inside.sum(), 1)), atol=1e-4)


def test_render_requests_are_checked():
    mesh = trimesh.creation.box()
    r = MeshRenderer(np.asarray(mesh.faces))
    cams = ring_cameras(n=1, width=16, height=16)
    with pytest.raises(RenderError, match="unknown channels"):
        r.render(np.asarray(mesh.vertices), cams, ("normals",))
    with pytest.raises(RenderError, match="face_labels"):
        r.render(np.asarray(mesh.vertices), cams, ("labels",))
    with pytest.raises(RenderError, match="share an image size"):
        r.render(np.asarray(mesh.vertices), cams + ring_cameras(n=1, width=8, height=8), ("mask",))
    with pytest.raises(RenderError, match="vertices"):
        r.render(np.zeros((3, 3)), cams, ("mask",))


def test_differentiable_silhouette_covers_the_mask_and_grows_toward_a_larger_target():
    import torch

    from elicit_diffrender.core.cameras import Camera
    from elicit_diffrender.data.mesh_render import DifferentiableSilhouette

    # A 1 m square at z = 0 seen from 3 m: about 21 x 21 pixels in the middle of a 64 x 64 image.
    verts = torch.tensor([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]], requires_grad=True)
    faces = np.array([[0, 2, 1], [0, 3, 2]])  # facing the camera (emitters are one-sided)
    cam = Camera(np.array([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]]), np.eye(3), np.array([0.0, 0.0, 3.0]), 64, 64)
    render = DifferentiableSilhouette(faces, 4, cam, spp=16)
    a = render(verts)
    values = a.detach()
    assert a.shape == (64, 64) and torch.isfinite(values).all() and values.min() >= 0 and values.max() <= 1
    area = (64.0 / 3.0) ** 2  # the square's projected area in pixels (anti-aliased coverage)
    assert abs(float(values.sum()) - area) < 0.02 * area
    exact = MeshRenderer(faces).render(verts.detach().numpy(), [cam], ("mask",))["mask"][0]
    assert (values.numpy()[exact > 0] > 0.2).all()  # it lies where the exact silhouette does
    # A larger target square: lowering the loss means moving every corner outwards.
    target = torch.zeros(64, 64)
    target[16:48, 16:48] = 1.0
    ((a - target) ** 2).mean().backward()
    outward = (verts.grad[:, :2] * verts.detach()[:, :2]).sum(1)
    assert (outward < 0).all(), verts.grad
