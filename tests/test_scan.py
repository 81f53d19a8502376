"""Textured 3D people as subjects: the OBJ reader and its atlas, triangulated landmarks, the multi-view body fit,
and the mesh bound to the body's skinning."""

import numpy as np
import pytest
from PIL import Image

from elicit_diffrender.body.fitting import triangulate
from elicit_diffrender.core.cameras import look_at
from elicit_diffrender.data.mesh_render import MeshAppearance, MeshRenderer
from elicit_diffrender.inputs.postures import standing
from elicit_diffrender.inputs.scan import ScanError, bind_to_body, read_obj
from elicit_diffrender.inputs.synth import skin_to_pose


def _ring(n: int, size: int = 200):
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n
        cams.append(look_at(np.array([3 * np.sin(a), 0.2, 3 * np.cos(a)]), np.zeros(3), np.array([0.0, 1.0, 0.0]),
                            300.0, size, size))  # fmt: skip
    return cams


def test_triangulation_outvotes_a_view_that_swaps_left_and_right():
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (33, 3))
    cams = _ring(6)
    proj = np.stack([c.K @ np.concatenate([c.R, c.T[:, None]], 1) for c in cams])
    keypoints = []
    for c in cams:
        uv, _ = c.project(points)
        keypoints.append(np.concatenate([uv + rng.normal(0, 0.3, uv.shape), np.ones((33, 1))], 1))
    keypoints = np.stack(keypoints)
    keypoints[3, [11, 12]] = keypoints[3, [12, 11]]  # a rear view with the shoulders swapped
    keypoints[:, 20, 2] = 0.0  # a landmark no view sees
    keypoints[1:, 21, 2] = 0.0  # and one only a single view sees
    found, support = triangulate(proj, keypoints, threshold=4.0)
    ok = support >= 2
    assert not ok[20] and not ok[21] and ok.sum() == 31
    assert np.linalg.norm(found[ok] - points[ok], axis=1).max() < 0.01
    assert support[11] == 5 and support[12] == 5 and support[0] == 6  # the swapped view is left out


def _write_obj(folder, faces_line: str = "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n", mtl_name: str = "scan.mtl") -> None:
    """Two quads side by side, each with its own material and a one-colour texture."""
    Image.new("RGB", (8, 8), (230, 20, 20)).save(folder / "red.png")
    Image.new("RGB", (8, 8), (20, 20, 230)).save(folder / "blue.png")
    (folder / "scan.mtl").write_text("newmtl a\nmap_Kd red.png\nnewmtl b\nmap_Kd blue.png\n")
    (folder / "scan.obj").write_text(
        f"mtllib {mtl_name}\n"
        "v -1 -0.5 0\nv 0 -0.5 0\nv 0 0.5 0\nv -1 0.5 0\nv 0.05 -0.5 0\nv 1 -0.5 0\nv 1 0.5 0\nv 0.05 0.5 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
        "usemtl a\n" + faces_line + "usemtl b\nf 5/1 6/2 7/3 8/4\n"
    )


def test_a_textured_obj_reads_into_one_atlas_with_each_material_in_its_tile(tmp_path):
    _write_obj(tmp_path)
    mesh = read_obj(tmp_path / "scan.obj")
    assert mesh.faces.shape == (4, 3) and mesh.texture.shape[0] == mesh.texture.shape[1]
    cam = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 100.0, 64, 64)
    image = MeshRenderer(mesh.faces, MeshAppearance(uvs=mesh.uvs, texture=mesh.texture)).render(
        mesh.vertices, [cam], ("color",), spp=4
    )["color"][0]
    np.testing.assert_allclose(image[32, 20], np.array([230, 20, 20]) / 255, atol=0.02)  # left quad: red
    np.testing.assert_allclose(image[32, 44], np.array([20, 20, 230]) / 255, atol=0.02)  # right quad: blue


@pytest.mark.parametrize(
    ("faces", "mtl", "message"),
    [
        ("f 1 2 3\n", "scan.mtl", "v/vt"),
        ("f 1/1 2/2 9/3\n", "scan.mtl", "does not exist"),
        ("f 1/1 2/2 3/3\n", "../outside.mtl", "not found beside the mesh"),
    ],
)
def test_a_broken_obj_is_one_clear_error(tmp_path, faces, mtl, message):
    _write_obj(tmp_path, faces, mtl)
    with pytest.raises(ScanError, match=message):
        read_obj(tmp_path / "scan.obj")


def test_a_bound_mesh_is_itself_in_its_pose_and_follows_the_body_elsewhere(anny_body):
    from elicit_diffrender.body.template import vertex_normals

    pose = standing(anny_body)
    orient, transl = np.array([0.0, 0.3, 0.0]), np.array([0.1, 0.0, -0.2])
    posed = anny_body.pose(pose, orient, transl)
    clothes = posed.vertices + 0.01 * vertex_normals(posed.vertices, anny_body.faces)  # 1 cm off the body
    rest, idx, w = bind_to_body(anny_body, clothes, pose, orient, transl)
    again = skin_to_pose(anny_body, rest, idx, w, pose, orient, transl)
    np.testing.assert_allclose(again, clothes, atol=1e-6)
    other = anny_body.zero_pose()
    anny_body.set_semantic(other, "l_elbow", (-1.2, 0.0, 0.0))
    moved = skin_to_pose(anny_body, rest, idx, w, other, orient, transl)
    body = anny_body.pose(other, orient, transl).vertices
    gap = np.linalg.norm(moved - body, axis=1)
    assert np.median(gap) < 0.012 and np.quantile(gap, 0.99) < 0.03  # still about 1 cm off the moved body


@pytest.mark.slow
def test_a_synthetic_person_read_as_a_scan_gets_its_own_body_back(tmp_path):
    """A clothed synthetic person written as an OBJ: the multi-view body fit finds its Anny body (in the scan's
    centred frame) within a few centimetres, and the bound mesh in the fitted pose is the mesh as written."""
    from elicit_diffrender.body.anny_model import AnnyBody
    from elicit_diffrender.inputs.scan import centred, make_scan_person
    from elicit_diffrender.inputs.synth import make_person

    person = make_person(0, texture_size=512)
    pose = standing(person.body)
    verts = person.clothed_vertices(pose, np.zeros(3), np.zeros(3))
    Image.fromarray((person.texture * 255).round().astype(np.uint8)).save(tmp_path / "skin.png")
    (tmp_path / "scan.mtl").write_text("newmtl skin\nmap_Kd skin.png\n")
    uvs = person.renderer.appearance.uvs
    lines = ["mtllib scan.mtl", "usemtl skin"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    lines += [f"vt {u:.6f} {1 - v:.6f}" for u, v in uvs]  # OBJ's v points up
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in person.renderer.faces]
    (tmp_path / "scan.obj").write_text("\n".join(lines) + "\n")

    scan = make_scan_person(tmp_path / "scan.obj", size=384)
    shift = centred(verts)[0] - verts[0]
    truth = AnnyBody(person.outfit.phenotype).pose(pose).vertices + shift
    fitted = scan.body.pose(scan.fitted["pose"], scan.fitted["global_orient"], scan.fitted["transl"]).vertices
    error = np.linalg.norm(fitted - truth, axis=1)
    assert np.mean(error) < 0.03 and scan.fitted["report"]["landmark_error_mm"]["median"] < 30
    again = scan.clothed_vertices(scan.fitted["pose"], scan.fitted["global_orient"], scan.fitted["transl"])
    assert np.abs(np.sort(again, axis=0) - np.sort(centred(verts), axis=0)).max() < 1e-4  # the mesh as written
