"""glTF export: a valid animated GLB whose skinned mesh matches the volume render of the same avatar."""

import json
import shutil
import subprocess
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pygltflib
import pytest
import trimesh
from gltf_skinning import posed_mesh, silhouette

from elicit_diffrender.apps.cli import main
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
    """A small fitted avatar of a synthetic subject (the fit tests' tiny settings) and its GLB with the
    subject's motion."""
    from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

    root = tmp_path_factory.mktemp("export")
    subject = load_subject(synthesize(5, root / "subject", size=96, spp=2, n_cameras=3, texture_size=256))
    fit(subject, make_config("cpu-fast", overrides=[*TINY, "init_steps=150", "steps=60"]), root / "run")
    avatar = load_avatar(root / "run")
    summary = export_glb(avatar, root / "avatar.glb", subject.motion)
    return subject, avatar, root, summary


def test_the_glb_validates_and_opens(exported):
    subject, avatar, root, summary = exported
    glb = root / "avatar.glb"
    if shutil.which("node") is None:
        pytest.fail("node is missing: run scripts/setup.sh (it installs nodejs and the glTF validator)")
    done = subprocess.run(
        ["node", str(ROOT / "scripts" / "validate_gltf.mjs"), str(glb)], capture_output=True, text=True, check=False
    )
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert done.returncode == 0 and report["errors"] == 0, report["messages"]
    assert report["warnings"] == 0, report["messages"]

    scene = trimesh.load(glb)
    meshes = list(scene.geometry.values())
    assert len(meshes) == 1 and len(meshes[0].vertices) == summary["vertices"]
    gltf = pygltflib.GLTF2().load(str(glb))
    assert len(gltf.skins[0].joints) == len(avatar.parents) == summary["joints"]
    assert len(gltf.animations) == 1
    times = gltf.accessors[gltf.animations[0].samplers[0].input]
    n = len(subject.motion)
    assert times.count == n and abs(times.max[0] - (n - 1) / subject.motion.fps) < 1e-4


def test_skinned_mesh_matches_the_volume_render_at_three_poses(exported):
    subject, avatar, root, _ = exported
    ring = place_ring(subject, 8, 192)
    n = len(subject.motion)
    for frame, cam in ((0, ring[0]), (n // 2, ring[3]), (n - 1, ring[6])):
        verts, faces, colors = posed_mesh(root / "avatar.glb", frame)
        mesh_mask = silhouette(cam, verts, faces)
        render = avatar.render_pose(cam, *subject.motion.frame(frame))
        volume_mask = render["alpha"] > 0.5
        iou = (mesh_mask & volume_mask).sum() / (mesh_mask | volume_mask).sum()
        assert iou >= 0.9, (frame, iou)
        # Colour: each pixel inside both silhouettes, the mesh's nearest vertex colour against the render.
        uv, _ = cam.project(verts)
        ys, xs = np.nonzero(mesh_mask & volume_mask)
        nearest = np.argmin((uv[None, :, 0] - xs[:, None] - 0.5) ** 2 + (uv[None, :, 1] - ys[:, None] - 0.5) ** 2, 1)
        srgb = np.where(colors <= 0.0031308, 12.92 * colors, 1.055 * np.maximum(colors, 0) ** (1 / 2.4) - 0.055)
        mse = float(((srgb[nearest] - render["rgb"][ys, xs]) ** 2).mean())
        psnr = -10 * np.log10(max(mse, 1e-10))
        print(f"frame {frame}: silhouette IoU {iou:.3f}, colour PSNR {psnr:.1f} dB")
        assert psnr > 15.0


def test_export_command(exported, tmp_path, capsys):
    _, _, root, _ = exported
    out = tmp_path / "a.glb"
    assert main(["export", str(root / "run"), "--out", str(out), "--motion", "wave", "--faces", "4000"]) == 0
    text = capsys.readouterr().out
    assert "wrote" in text and "frames of wave" in text and "vertex colours" in text
    assert len(trimesh.load(out).geometry) == 1
    assert len(next(iter(trimesh.load(out).geometry.values())).faces) <= 4400
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


def screenshot(page: Path, out: Path, budget_ms: int) -> np.ndarray:
    """A headless-Chromium screenshot (software WebGL) of ``page`` after ``budget_ms`` of virtual time."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.fail("chromium is missing: run scripts/setup.sh (it installs Debian's chromium)")
    cmd = [
        browser,
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--hide-scrollbars",
        "--window-size=320,320",
        f"--virtual-time-budget={budget_ms}",
        f"--screenshot={out}",
        page.as_uri(),
    ]
    subprocess.run(cmd, capture_output=True, timeout=180, check=False)
    assert out.is_file(), f"no screenshot from {' '.join(cmd)}"
    return np.asarray(imageio.imread(out))[..., :3].astype(np.int16)


def test_viewer_page_shows_the_avatar_and_plays_it(exported, tmp_path, capsys):
    _, _, root, _ = exported
    out = tmp_path / "page"
    assert main(["view", str(root / "avatar.glb"), "--out", str(out)]) == 0
    assert "index.html" in capsys.readouterr().out
    page = out / "index.html"
    text = page.read_text()
    assert (out / "avatar.glb").read_bytes() == (root / "avatar.glb").read_bytes()
    assert 'src="http' not in text and "<script src=" not in text  # everything is inlined: it opens offline
    early = screenshot(page, tmp_path / "early.png", 1500)
    late = screenshot(page, tmp_path / "late.png", 3000)
    background = np.array([32, 32, 32])
    for shot in (early, late):
        avatar = np.abs(shot - background).sum(-1) > 30
        h, w = avatar.shape
        inside = avatar[h // 10 : 9 * h // 10, w // 4 : 3 * w // 4].mean()
        outside = np.concatenate([avatar[:, : w // 8].ravel(), avatar[:, -w // 8 :].ravel()]).mean()
        assert inside > 0.05 and outside < 0.01, (inside, outside)  # the avatar, centred in the view
    moved = (np.abs(early - late).sum(-1) > 30).mean()
    assert moved > 0.002, moved  # the animation advances
    assert main(["view", str(root / "nothing.glb"), "--out", str(tmp_path / "p2")]) == 2
    assert "nothing.glb" in capsys.readouterr().err
