"""glTF export: a valid animated GLB whose skinned, textured mesh matches the volume render of the same avatar,
in our own reader, in Blender and in the viewer page."""

import json
import shutil
import subprocess
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pygltflib
import pytest
import trimesh
from gltf_skinning import linear_to_srgb, posed_mesh, silhouette, surface_colors

from elicit_diffrender.apps.benchtools import chromium_page
from elicit_diffrender.apps.cli import main
from elicit_diffrender.data.mesh_render import MeshAppearance, MeshRenderer
from elicit_diffrender.data.rigs import place_ring
from elicit_diffrender.data.subject import load_subject
from elicit_diffrender.fit.config import make_config
from elicit_diffrender.fit.run import fit
from elicit_diffrender.inputs.synth import synthesize
from elicit_diffrender.model.avatar import Avatar
from elicit_diffrender.model.load import load_avatar
from elicit_diffrender.outputs.export import ExportError, export_glb

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A small fitted avatar of a synthetic subject (the fit tests' tiny settings) and its GLBs with the
    subject's motion: textured (the default, ``avatar.glb``) and with vertex colours (``vertex_colors.glb``)."""
    from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

    root = tmp_path_factory.mktemp("export")
    subject = load_subject(synthesize(5, root / "subject", size=96, spp=2, n_cameras=3, texture_size=256))
    fit(subject, make_config("cpu-fast", overrides=[*TINY, "init_steps=150", "steps=60"]), root / "run")
    avatar = load_avatar(root / "run")
    summary = export_glb(avatar, root / "avatar.glb", subject.motion)
    export_glb(avatar, root / "vertex_colors.glb", subject.motion, texture_size=None)
    return subject, avatar, root, summary


def three_views(subject) -> list[tuple[int, object]]:
    """(keyframe, camera) at the motion's first, middle and last frames, from three sides of the ring."""
    ring = place_ring(subject, 8, 192)
    n = len(subject.motion)
    return [(0, ring[0]), (n // 2, ring[3]), (n - 1, ring[6])]


def colour_psnr(image: np.ndarray, render: dict, mask: np.ndarray) -> float:
    """PSNR of ``image`` against the volume render's (un-premultiplied) colour inside ``mask``."""
    reference = render["rgb"] / np.maximum(render["alpha"], 1e-6)[..., None]
    return float(-10 * np.log10(max(((image[mask] - reference[mask]) ** 2).mean(), 1e-10)))


def validate_glb(glb: Path) -> None:
    """The Khronos glTF validator's verdict: no errors and no warnings."""
    if shutil.which("node") is None:
        pytest.fail("node is missing: run scripts/setup.sh (it installs nodejs and the glTF validator)")
    done = subprocess.run(
        ["node", str(ROOT / "scripts" / "validate_gltf.mjs"), str(glb)], capture_output=True, text=True, check=False
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert done.returncode == 0 and report["errors"] == 0, report["messages"]
    assert report["warnings"] == 0, report["messages"]


def test_the_glb_validates_and_opens(exported):
    subject, avatar, root, summary = exported
    for glb in (root / "avatar.glb", root / "vertex_colors.glb"):
        validate_glb(glb)
        gltf = pygltflib.GLTF2().load(str(glb))
        assert len(gltf.skins[0].joints) == len(avatar.parents) == summary["joints"]
        assert len(gltf.animations) == 1
        times = gltf.accessors[gltf.animations[0].samplers[0].input]
        n = len(subject.motion)
        assert times.count == n and abs(times.max[0] - (n - 1) / subject.motion.fps) < 1e-4

    scene = trimesh.load(root / "avatar.glb")
    meshes = list(scene.geometry.values())
    assert len(meshes) == 1 and len(meshes[0].vertices) == summary["vertices"]
    # Textured: one material whose base colour is a PNG read through TEXCOORD_0; no vertex colours.
    gltf = pygltflib.GLTF2().load(str(root / "avatar.glb"))
    prim = gltf.meshes[0].primitives[0]
    assert prim.attributes.TEXCOORD_0 is not None and prim.attributes.COLOR_0 is None
    assert len(gltf.materials) == 1 and gltf.materials[0].pbrMetallicRoughness.baseColorTexture.index == 0
    assert len(gltf.images) == 1 and gltf.images[0].mimeType == "image/png"
    texture = surface_colors(root / "avatar.glb")["texture"]
    assert texture.shape == (1024, 1024, 3) and summary["appearance"].startswith("1024x1024 baked texture")
    assert texture.std() > 0.02  # colours, not one flat fill
    uvs = surface_colors(root / "avatar.glb")["uvs"]
    assert uvs.min() >= 0 and uvs.max() <= 1


def test_skinned_mesh_matches_the_volume_render_at_three_poses(exported):
    """Posed by our own glTF reader and drawn by Mitsuba from the file's data: the silhouette matches the volume
    render's, and the baked texture's colours match it better than the vertex colours do."""
    subject, avatar, root, _ = exported
    textured, plain = surface_colors(root / "avatar.glb"), surface_colors(root / "vertex_colors.glb")
    gains = []
    for frame, cam in three_views(subject):
        render = avatar.render_pose(cam, *subject.motion.frame(frame))
        volume_mask = render["alpha"] > 0.5
        scores = []
        for glb, look in (
            ("avatar.glb", MeshAppearance(uvs=textured["uvs"], texture=textured["texture"])),
            ("vertex_colors.glb", MeshAppearance(vertex_colors=linear_to_srgb(plain["vertex_colors"]))),
        ):
            verts, faces = posed_mesh(root / glb, frame)
            mesh_mask = silhouette(cam, verts, faces)
            iou = (mesh_mask & volume_mask).sum() / (mesh_mask | volume_mask).sum()
            assert iou >= 0.9, (glb, frame, iou)
            image = MeshRenderer(faces, look).render(verts, [cam], ("color",), spp=8)["color"][0]
            scores.append(colour_psnr(image, render, mesh_mask & volume_mask))
        print(f"frame {frame}: IoU {iou:.3f}, colour PSNR texture {scores[0]:.1f}, vertex colours {scores[1]:.1f} dB")
        assert scores[0] > 20.0
        gains.append(scores[0] - scores[1])
    assert np.mean(gains) > 0.5, gains


def test_blender_imports_plays_and_renders_the_glb(exported, tmp_path):
    """What a user does: Blender's own glTF importer, its armature posed by the action at three frames, a
    Workbench render compared with the volume render of the same pose and camera."""
    subject, avatar, root, _ = exported
    views = three_views(subject)
    request = {
        "renders": [
            {"keyframe": frame, "camera": cam.to_dict(), "out": str(tmp_path / f"blender_{frame}.png")}
            for frame, cam in views
        ]
    }
    (tmp_path / "request.json").write_text(json.dumps(request))
    blender_python = ROOT / ".venv-blender" / "bin" / "python"
    if not blender_python.is_file():
        pytest.fail(f"{blender_python} is missing: run scripts/setup.sh (it installs bpy, Blender as a module)")
    done = subprocess.run(
        [str(blender_python), str(ROOT / "tests" / "blender_glb.py"), str(root / "avatar.glb"),
         str(tmp_path / "request.json"), str(tmp_path / "report.json")],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    (mesh,) = report["meshes"]
    assert mesh["uv_layers"] == 1 and mesh["images"] == [[1024, 1024]] and mesh["skinned_by"]
    assert [a["bones"] for a in report["armatures"]] == [len(avatar.parents)] == [21]
    assert [a["keyframes"] for a in report["actions"]] == [len(subject.motion)]
    bounds = {tuple(np.round(r["min"] + r["max"], 4)) for r in report["renders"]}
    assert len(bounds) == 3  # the action moves the mesh
    for (frame, cam), shot in zip(views, report["renders"], strict=True):
        image = np.asarray(imageio.imread(shot["out"]), dtype=np.float32) / 255
        render = avatar.render_pose(cam, *subject.motion.frame(frame))
        blender_mask, volume_mask = image[..., 3] > 0.5, render["alpha"] > 0.5
        iou = (blender_mask & volume_mask).sum() / (blender_mask | volume_mask).sum()
        psnr = colour_psnr(image[..., :3], render, blender_mask & volume_mask)
        print(f"Blender, frame {frame}: silhouette IoU {iou:.3f}, colour PSNR {psnr:.1f} dB")
        assert iou >= 0.9 and psnr > 20.0, (frame, iou, psnr)


def test_export_command(exported, tmp_path, capsys):
    _, _, root, _ = exported
    out = tmp_path / "a.glb"
    assert main(["export", str(root / "run"), "--out", str(out), "--motion", "wave", "--faces", "4000"]) == 0
    text = capsys.readouterr().out
    assert "wrote" in text and "frames of wave" in text and "1024x1024 baked texture" in text and "MiB" in text
    assert len(trimesh.load(out).geometry) == 1
    assert len(next(iter(trimesh.load(out).geometry.values())).faces) <= 4400
    small = tmp_path / "small.glb"
    assert main(["export", str(root / "run"), "--out", str(small), "--texture-size", "256"]) == 0
    assert surface_colors(small)["texture"].shape == (256, 256, 3)
    assert main(["export", str(root / "run"), "--out", str(tmp_path / "vc.glb"), "--vertex-colors"]) == 0
    assert "vertex colours (COLOR_0)" in capsys.readouterr().out
    assert "vertex_colors" in surface_colors(tmp_path / "vc.glb")
    assert main(["export", str(root / "run"), "--out", str(tmp_path / "a.obj")]) == 2
    err = capsys.readouterr().err
    assert "must be a .glb" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main(["export", str(root / "run"), "--out", str(tmp_path / "b.glb"), "--motion", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
    # The explicit-texture baseline has no field to mesh: one line, exit 2, for export and for view.
    from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

    fit(exported[0], make_config("cpu-fast", overrides=[*TINY, "baseline=explicit_texture"]), tmp_path / "base")
    assert main(["export", str(tmp_path / "base"), "--out", str(tmp_path / "c.glb")]) == 2
    assert main(["view", str(tmp_path / "base"), "--out", str(tmp_path / "page")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("elicit ")]  # not the fit's log
    assert (
        len(err) == 2 and all("explicit-texture baseline" in line for line in err) and not (tmp_path / "c.glb").exists()
    )
    with pytest.raises(ExportError, match="no opaque region"):
        empty = Avatar.from_body(
            exported[0].body, exported[0].body_spec, 0.05, 0.1, occupancy_cell=0.04, weight_res=8, body_prior=False
        )
        export_glb(empty, tmp_path / "empty.glb")


class PageShots:
    """The viewer page in headless Chromium (Playwright driving the system's browser, software WebGL)."""

    def __init__(self, page: Path) -> None:
        from playwright.sync_api import sync_playwright

        self.playwright = sync_playwright().start()
        self.page = chromium_page(self.playwright, (320, 320))
        self.page.goto(page.as_uri())
        self.page.wait_for_function("document.title === 'avatar: loaded' && window.viewerFrames > 2", timeout=120_000)

    def shot(self, path: Path) -> np.ndarray:
        self.page.screenshot(path=str(path))
        return np.asarray(imageio.imread(path))[..., :3].astype(np.int16)

    def close(self) -> None:
        self.page.context.browser.close()
        self.playwright.stop()


def test_viewer_page_shows_the_avatar_and_plays_it(exported, tmp_path, capsys):
    _, _, root, _ = exported
    out = tmp_path / "page"
    assert main(["view", str(root / "avatar.glb"), "--out", str(out)]) == 0
    assert "index.html" in capsys.readouterr().out
    page = out / "index.html"
    text = page.read_text()
    assert (out / "avatar.glb").read_bytes() == (root / "avatar.glb").read_bytes()
    assert 'src="http' not in text and "<script src=" not in text  # everything is inlined: it opens offline
    shots = PageShots(page)
    try:
        early = shots.shot(tmp_path / "early.png")
        played = shots.page.evaluate("window.viewerTime")
        shots.page.wait_for_function(f"window.viewerTime > {played} + 0.3", timeout=120_000)
        late = shots.shot(tmp_path / "late.png")
        material = shots.page.evaluate("document.body.dataset.material")
    finally:
        shots.close()
    background = np.array([32, 32, 32])
    for shot in (early, late):
        avatar = np.abs(shot - background).sum(-1) > 30
        h, w = avatar.shape
        inside = avatar[h // 10 : 9 * h // 10, w // 4 : 3 * w // 4].mean()
        outside = np.concatenate([avatar[:, : w // 8].ravel(), avatar[:, -w // 8 :].ravel()]).mean()
        assert inside > 0.05 and outside < 0.01, (inside, outside)  # the avatar, centred in the view
    moved = (np.abs(early - late).sum(-1) > 30).mean()
    assert moved > 0.002, moved  # the animation advances
    # The page shows the baked texture (<body data-material> names it); a vertex-colour GLB's page, its colours.
    assert material == "texture 1024x1024"
    assert main(["view", str(root / "vertex_colors.glb"), "--out", str(tmp_path / "vc")]) == 0
    shots = PageShots(tmp_path / "vc" / "index.html")
    try:
        assert shots.page.evaluate("document.body.dataset.material") == "vertex colours"
    finally:
        shots.close()
    assert main(["view", str(root / "nothing.glb"), "--out", str(tmp_path / "p2")]) == 2
    assert "nothing.glb" in capsys.readouterr().err


def test_uv_rasteriser_covers_each_texel_once_with_its_barycentrics():
    """Two triangles tiling the unit square: every texel centre falls in one of them (edges shared without
    gaps), and its barycentric coordinates give back that centre."""
    from elicit_diffrender.outputs.texture import fill_seams, rasterize_uv

    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    texels = rasterize_uv(uvs, faces, 16)
    covered = np.zeros((16, 16), int)
    np.add.at(covered, (texels.rows, texels.cols), 1)
    assert covered.min() >= 1 and (covered > 1).sum() <= 16  # the shared diagonal may count twice
    centres = np.einsum("nk,nkc->nc", texels.barycentric, uvs[faces[texels.faces]]) * 16
    assert np.allclose(centres, np.stack([texels.cols + 0.5, texels.rows + 0.5], 1))
    # One triangle in a corner: only texels with centres inside it, then the fill reaches every texel.
    half = rasterize_uv(np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]]), np.array([[0, 1, 2]]), 16)
    assert len(half.rows) == 36 and ((half.rows + 0.5) + (half.cols + 0.5) <= 8).all()
    image = np.zeros((16, 16, 3))
    image[half.rows, half.cols] = 1.0
    mask = np.zeros((16, 16), bool)
    mask[half.rows, half.cols] = True
    assert fill_seams(image, mask).min() == 1.0


def test_every_bake_kind_gives_back_a_plain_field_colour(exported):
    """On a field of one colour every bake returns that colour at every surface point: the views bake's
    weights are normalised, each kind falls back to the point look-up where no ray turns opaque. The views
    bake's directions are unit vectors spread over the whole sphere."""
    import copy

    import torch

    from elicit_diffrender.body.template import vertex_normals
    from elicit_diffrender.outputs.export import canonical_mesh
    from elicit_diffrender.outputs.texture import BAKE_KINDS, VIEW_DIRECTIONS, Bake, surface_colors

    assert np.allclose(np.linalg.norm(VIEW_DIRECTIONS, axis=1), 1.0)
    assert (
        np.linalg.norm(VIEW_DIRECTIONS.mean(0)) < 0.05
        and (VIEW_DIRECTIONS @ VIEW_DIRECTIONS.T - np.eye(26)).max() < 0.9
    )
    avatar = copy.deepcopy(exported[1])
    mesh = canonical_mesh(avatar)
    normals = np.array(vertex_normals(mesh.vertices.astype(np.float64), mesh.faces))  # writable, as torch wants
    fitted = surface_colors(avatar, mesh.vertices, normals)
    assert fitted.std(0).min() > 0.02  # the fitted avatar is not plain
    with torch.no_grad():
        avatar.field.color.fill_(0.3)
    for kind in BAKE_KINDS:
        colours = surface_colors(avatar, mesh.vertices, normals, Bake(kind))
        assert np.allclose(colours, 1 / (1 + np.exp(-0.3)), atol=1e-5), kind
