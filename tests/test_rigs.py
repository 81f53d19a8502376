"""Camera rigs: XML round trips, shipped files, and projection agreement with Mitsuba."""

import numpy as np
import pytest

from elicit_diffrender.core.cameras import Camera, look_at
from elicit_diffrender.data.mesh_render import MeshRenderer
from elicit_diffrender.data.rigs import (
    RigError,
    default_rigs,
    place_cameras,
    read_rig,
    rig_xml,
    ring_cameras,
    shipped_rig_path,
    write_rig,
)


def off_centre_camera() -> Camera:
    cam = look_at([0.4, 0.3, 2.5], [0.05, 0.1, 0.0], [0, 1, 0], focal=180.0, width=160, height=120, name="odd")
    cam.K[0, 2], cam.K[1, 2] = 70.0, 52.5
    return cam


def test_round_trip(tmp_path):
    cams = ring_cameras(n=5, radius=2.2, elevation_deg=15, look_at_point=(0.1, 0.2, -0.3)) + [off_centre_camera()]
    path = write_rig(tmp_path / "rig.xml", cams, "test rig")
    back = read_rig(path)
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(cams, back, strict=True):
        np.testing.assert_allclose(b.K, a.K, atol=1e-6)
        np.testing.assert_allclose(b.R, a.R, atol=1e-7)
        np.testing.assert_allclose(b.T, a.T, atol=1e-7)
        assert (b.width, b.height) == (a.width, a.height)


@pytest.mark.parametrize("name", ["input", "ring", "orbit"])
def test_shipped_rigs_match_their_generator(name):
    cams, comment = default_rigs()[name]
    assert shipped_rig_path(name).read_text() == rig_xml(cams, comment)


def test_ring_geometry():
    cams = ring_cameras(n=23, radius=3.0)
    centres = np.stack([c.center for c in cams])
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 3.0, atol=1e-9)
    np.testing.assert_allclose(centres[0], [0, 0, 3.0], atol=1e-9)  # camera 0 faces the body's front
    for c in cams:  # every camera looks at the origin, image up = world up
        uv, z = c.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]]))
        np.testing.assert_allclose(uv[0], [c.width / 2, c.height / 2], atol=1e-6)
        assert uv[1, 1] < uv[0, 1]


def test_lookat_transform_is_read(tmp_path):
    xml = """<scene version="3.0.0"><sensor type="perspective" id="a">
      <float name="fov" value="40"/>
      <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
      <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/></film>
    </sensor></scene>"""
    (tmp_path / "r.xml").write_text(xml)
    cam = read_rig(tmp_path / "r.xml")[0]
    np.testing.assert_allclose(cam.center, [0, 0, 3], atol=1e-9)
    uv, _ = cam.project(np.array([[0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [32, 32], atol=1e-9)


def test_bad_rigs_name_the_problem(tmp_path):
    with pytest.raises(RigError, match="not found"):
        read_rig(tmp_path / "missing.xml")
    (tmp_path / "bad.xml").write_text("<scene><sensor type='perspective' id='x'><film type='hdrfilm'/></sensor>")
    with pytest.raises(RigError, match="not valid XML"):
        read_rig(tmp_path / "bad.xml")
    (tmp_path / "nofov.xml").write_text(
        "<scene><sensor type='perspective' id='x'><film type='hdrfilm'/></sensor></scene>"
    )
    with pytest.raises(RigError, match="fov"):
        read_rig(tmp_path / "nofov.xml")
    cam = off_centre_camera()
    cam.K[1, 1] *= 1.1
    with pytest.raises(RigError, match="square pixels"):
        rig_xml([cam])


def test_place_cameras_keeps_relative_geometry():
    cams = ring_cameras(n=3)
    rot = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    placed = place_cameras(cams, rot, np.array([0.2, 0.3, 5.0]))
    point = np.array([[0.1, 0.4, -0.2]])
    for a, b in zip(cams, placed, strict=True):
        uv_a, _ = a.project(point)
        uv_b, _ = b.project(point @ rot.T + np.array([0.2, 0.3, 5.0]))
        np.testing.assert_allclose(uv_a, uv_b, atol=1e-9)


def test_projection_agrees_with_mitsuba():
    """A small sphere's silhouette centroid in a Mitsuba render lands where the OpenCV camera projects it."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.04)
    cam = off_centre_camera()
    renderer = MeshRenderer(np.asarray(sphere.faces))
    for centre in ([0.0, 0.0, 0.0], [0.35, -0.25, 0.2], [-0.3, 0.3, -0.1]):
        mask = renderer.render(np.asarray(sphere.vertices) + centre, [cam], ("mask",))["mask"][0]
        ys, xs = np.nonzero(mask)
        uv, _ = cam.project(np.array([centre]))
        # The silhouette centroid of a small sphere is its projected centre up to perspective skew (<0.3 px here).
        np.testing.assert_allclose([xs.mean() + 0.5, ys.mean() + 0.5], uv[0], atol=0.35)
