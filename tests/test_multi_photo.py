"""Several photos of one person: the subject's input views, camera placement, the fit's observed views, prepare."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_fit import TINY  # noqa: I001 - the tiny fit settings are shared with the fit tests

from elicit_diffrender.core.io import write_image, write_json
from elicit_diffrender.data.subject import SubjectError, load_subject
from elicit_diffrender.fit.config import make_config
from elicit_diffrender.fit.objective import source_photos
from elicit_diffrender.fit.trainer import Trainer
from elicit_diffrender.fit.views import FitViews
from elicit_diffrender.inputs import prepare as prepare_module
from elicit_diffrender.inputs.mediapipe_bridge import mediapipe_python
from elicit_diffrender.inputs.prepare import MAX_SHAPE_DIFFERENCE_CM, PrepareError, camera_from_placements, prepare
from elicit_diffrender.inputs.synth import extra_photos, synthesize
from elicit_diffrender.model.load import load_avatar
from elicit_diffrender.outputs.evaluate import camera_error, psnr

HAS_MEDIAPIPE = mediapipe_python() is not None


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """A synthetic person seen by a ring of 4 cameras in its input frame, with a back (cam02, 180 degrees) and a
    side photo (cam01) in the motion's middle frame."""
    root = synthesize(
        5, tmp_path_factory.mktemp("multi") / "s", size=96, spp=4, n_cameras=4, texture_size=256, photos=True
    )
    return load_subject(root)


def with_inputs(truth, dest, inputs) -> object:
    """A copy of ``truth`` whose ``subject.json`` lists ``inputs`` (camera, frame) as its input views."""
    shutil.copytree(truth.root, dest)
    meta = json.loads((dest / "subject.json").read_text())
    meta["inputs"] = [{"camera": c, "frame": f} for c, f in inputs]
    write_json(dest / "subject.json", meta)
    return load_subject(dest)


def test_synth_photos_are_the_back_and_the_side_in_another_frame(truth):
    photos = {k: tuple(v) for k, v in truth.meta["synthetic"]["photos"].items()}
    assert (
        photos
        == extra_photos(4, len(truth.motion))
        == {
            "back": ("cam02", len(truth.motion) // 2),
            "side": ("cam01", len(truth.motion) // 2),
        }
    )
    for cam, frame in photos.values():
        assert truth.has_view(cam, frame) and truth.mask(cam, frame).any()
    assert truth.inputs == [("cam00", 0)]  # a subject without "inputs" has its one input view


def test_the_input_views_are_checked(truth, tmp_path):
    back = tuple(truth.meta["synthetic"]["photos"]["back"])
    two = with_inputs(truth, tmp_path / "two", [("cam00", 0), back])
    assert two.inputs == [("cam00", 0), back] and two.input_camera == "cam00"
    for k, (inputs, message) in enumerate(
        [
            ([("cam00", 0), ("nope", back[1])], r"inputs\[1\]"),
            ([("cam00", 0), ("cam02", 9999)], r"inputs\[1\]"),
            ([("cam00", 0), ("cam00", 0)], "lists a view twice"),
            ([back, ("cam00", 0)], "must start with the view that 'input' names"),
            ([("cam00", 0), ("cam01", 0), ("cam02", 3)], "images"),  # no photo there
        ]
    ):
        with pytest.raises(SubjectError, match=message):
            with_inputs(truth, tmp_path / f"bad{k}", inputs)


def test_a_camera_placed_by_two_placements_sees_the_body_as_its_fit_did():
    """The first photo's camera is the world; another photo's fit placed the body at (rot, t) in its camera: the
    camera from ``camera_from_placements`` sees the body, held at the first fit's placement, exactly there."""
    rng = np.random.default_rng(0)
    first = {"global_orient": rng.normal(size=3), "transl": rng.normal(size=3)}
    this = {"global_orient": rng.normal(size=3), "transl": rng.normal(size=3)}
    body = rng.normal(size=(50, 3))  # model-space points
    R, T = camera_from_placements(first, this)
    in_world = body @ Rotation.from_rotvec(first["global_orient"]).as_matrix().T + first["transl"]
    in_camera = body @ Rotation.from_rotvec(this["global_orient"]).as_matrix().T + this["transl"]
    np.testing.assert_allclose(in_world @ R.T + T, in_camera, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def back_psnr(avatar, subject, view) -> float:
    cam, frame = view
    out = avatar.render_pose(subject.cameras[cam], *subject.motion.frame(subject.frame_index(frame)), 32)
    mask = subject.mask(cam, frame)  # the person's pixels
    return psnr(np.clip(out["rgb"], 0, 1), subject.image(cam, frame) * mask[..., None], mask)


def test_a_back_photo_is_reconstructed_not_guessed(truth, tmp_path):
    """With the back photo as a second observed view, the avatar renders that photo better than an avatar
    fitted to the front alone (150 steps here); as a semantic reference only (``multi_photo=reference``) it is
    not reconstructed. Every input pose gets its own learned correction, kept in the avatar file."""
    back = tuple(truth.meta["synthetic"]["photos"]["back"])
    two = with_inputs(truth, tmp_path / "two", [("cam00", 0), back])
    settings = ["steps=150", "refine_input_pose=true", "pose_lr=0.003"]
    scores = {}
    for name, subject, extra in (
        ("one", truth, []),
        ("two", two, []),
        ("reference", two, ["multi_photo=reference"]),
    ):
        cfg = make_config("cpu-fast", None, TINY + settings + extra)
        trainer = Trainer(subject, cfg, tmp_path / name)
        views = trainer.views
        assert len(views.observed) == (2 if name == "two" else 1)
        assert len(views.references) == (1 if name == "reference" else 0)
        trainer.run()
        avatar = load_avatar(tmp_path / name)
        scores[name] = back_psnr(avatar, two, back)
        if name == "two":
            assert avatar.pose_delta.shape[0] == 2 and avatar.pose_delta[1].abs().max() > 1e-4
            raw = avatar.bone_transforms(*two.motion.frame(two.frame_index(back[1])), refine=False)
            torch.testing.assert_close(
                avatar.bone_transforms(*two.motion.frame(two.frame_index(back[1]))), avatar.refined(raw, 1)
            )
    # Measured: 20.07 against 18.68 on the person's pixels (17.96 before photo patches left the cells on the
    # body's far side to the completion).
    assert scores["two"] > scores["one"] + 1.0, scores
    assert scores["two"] > scores["reference"] + 1.0, scores


def test_a_back_photo_keeps_the_far_side_layer_inside_its_mask(truth, tmp_path):
    """With front + back photos the far side's layer is the cells the front photo cannot see that the back
    photo's mask holds: none where the back photo shows only background, the front photo's alone where its mask
    covers everything (without the mask no cell lies behind the body in both photos, so a front + back fit had no
    layer: front views 0.2 dB below one photo's on ``bench_multi_photo``)."""
    back = tuple(truth.meta["synthetic"]["photos"]["back"])
    two = with_inputs(truth, tmp_path / "two", [("cam00", 0), back])
    trainer = Trainer(two, make_config("cpu-fast", None, TINY + ["far_side_layer=0.03"]), tmp_path / "run")
    objective, photo = trainer.objective, trainer.views.observed[1]
    layer = objective.far_side
    assert layer.sum() > 20

    def layer_with(person: np.ndarray) -> np.ndarray:
        photo.person = person
        return objective._far_side_layer(two.body, trainer.avatar.body_sdf, 0.03)

    mask = photo.person.copy()
    everywhere = layer_with(np.ones_like(mask))
    nowhere = layer_with(np.zeros_like(mask))
    assert not (layer & ~everywhere).any() and everywhere.sum() > layer.sum()
    assert nowhere.sum() < 0.1 * layer.sum(), (nowhere.sum(), layer.sum())
    assert (layer_with(mask) == layer).all()


def test_a_vertex_takes_its_colour_from_a_photo_that_shows_it_clear_of_the_hands():
    """A chest vertex the front photo sees squarely but behind a held folder, and a side photo sees clear, takes
    the side photo's colour (with the front's, a held_folder avatar from front + side photos wore the folder on its
    back); one that only the front shows behind the folder stays held; one seen clear by both takes the squarer."""
    seen = np.array([[True, True, True, False], [True, False, True, False]])
    held = np.array([[True, True, False, False], [False, False, False, False]])
    facing = np.array([[0.9, 0.9, 0.2, -0.5], [0.3, -0.2, 0.8, -0.1]])
    best, held_everywhere = source_photos(seen, held, facing)
    assert best[:3].tolist() == [1, 0, 1]
    assert held_everywhere.tolist() == [False, True, False, False]


def test_fit_views_of_every_photo_come_before_the_motion(truth, tmp_path):
    side = tuple(truth.meta["synthetic"]["photos"]["side"])
    two = with_inputs(truth, tmp_path / "two", [("cam00", 0), side])
    views = FitViews.build(two, make_config("cpu-fast", None, TINY), torch.device("cpu"))
    assert [v.pose for v in views.observed] == [0, two.frame_index(side[1])]
    assert views.poses[2][:2] == [0, two.frame_index(side[1])]
    # The side camera sees the body's side: its yaw is about 90 degrees from the front's.
    gap = abs((views.observed[1].yaw - views.observed[0].yaw + 180) % 360 - 180)
    assert 70 < gap < 110, gap


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "elicit_diffrender.apps.cli", *args], capture_output=True, text=True)


def test_prepare_needs_one_mask_per_photo(truth, tmp_path):
    back = truth.meta["synthetic"]["photos"]["back"]
    photos = [str(truth.image_path("cam00", 0)), str(truth.image_path(*back))]
    done = run_cli("prepare", *photos, "--mask", str(truth.mask_path("cam00", 0)), "--out", str(tmp_path / "o"))
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "--mask: given 1 times for 2 photos" in done.stderr
    done = run_cli(
        "prepare", *photos, "--focal", "100", "--focal", "200", "--focal", "300", "--out", str(tmp_path / "o")
    )
    assert done.returncode == 2 and "--focal: given 3 times for 2 photos" in done.stderr
    assert not (tmp_path / "o").exists()
    # A second photo without a person stops before any body fit, naming that photo.
    write_image(tmp_path / "empty.png", np.zeros((96, 96, 3)))
    write_image(tmp_path / "empty_mask.png", np.zeros((96, 96)))
    masks = ["--mask", str(truth.mask_path("cam00", 0)), "--mask", str(tmp_path / "empty_mask.png")]
    done = run_cli("prepare", photos[0], str(tmp_path / "empty.png"), *masks, "--out", str(tmp_path / "o"))
    assert done.returncode == 2 and done.stderr.strip().count("\n") == 0, done.stderr
    assert "empty.png: no person found" in done.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(not HAS_MEDIAPIPE, reason="MediaPipe environment not installed (scripts/setup.sh creates it)")
def test_prepare_two_photos_places_the_second_camera(tmp_path_factory, monkeypatch):
    """A front photo and a back photo (another pose) of a synthetic person: one shape, two poses, and the back
    camera behind the person where the true one is, after aligning its body onto the true body. Measured here:
    49 cm and 9.1 degrees off at 3 m (the front camera, placed by the same kind of fit: 12 cm, 2.3 degrees);
    the bounds catch a camera on the wrong side or turned away, not the 10 cm and 5 degrees aimed for."""
    root = synthesize(
        11, tmp_path_factory.mktemp("two") / "s", size=384, spp=8, n_cameras=4, texture_size=512, photos=True
    )
    s = load_subject(root)
    back = tuple(s.meta["synthetic"]["photos"]["back"])
    focal = float(s.cameras["cam00"].K[0, 0])
    out = tmp_path_factory.mktemp("prepared") / "two"
    report = prepare(
        [s.image_path("cam00", 0), s.image_path(*back)],
        out,
        [s.mask_path("cam00", 0), s.mask_path(*back)],
        focal=focal,
    )
    assert [p["camera"] for p in report["photos"]] == ["input", "input1"]
    assert all(p["silhouette_iou"] > 0.75 for p in report["photos"]), [p["silhouette_iou"] for p in report["photos"]]
    assert 0.0 < report["photos"][1]["shape_difference_cm"] < MAX_SHAPE_DIFFERENCE_CM
    prepared = load_subject(out)
    assert prepared.inputs == [("input", 0), ("input1", 1)]
    metres, degrees = camera_error(prepared, ("input1", 1), s, back)
    assert metres < CAMERA_METRES and degrees < CAMERA_DEGREES, (metres, degrees)
    # A photo whose own shape fit differs too much is refused in one line naming it, and nothing is written.
    # Monocular shape fits barely tell people apart (seed 79 against this one: 2.4 cm, their true bodies 8.6
    # cm apart; a child of this person's phenotype: 6.5 cm, truly 16), so the limit is lowered here to reach
    # that path with two ordinary people.
    monkeypatch.setattr(prepare_module, "MAX_SHAPE_DIFFERENCE_CM", 1.0)
    other = load_subject(synthesize(79, tmp_path_factory.mktemp("other") / "s", size=384, spp=8, n_cameras=1,
                                     texture_size=512))  # fmt: skip
    refused = tmp_path_factory.mktemp("x") / "o"
    with pytest.raises(PrepareError, match=r"000000.png: the body fitted to it differs from .* by \d+\.\d cm"):
        prepare([s.image_path("cam00", 0), other.image_path("cam00", 0)], refused,
                [s.mask_path("cam00", 0), other.mask_path("cam00", 0)], focal=focal)  # fmt: skip
    assert not refused.exists()


CAMERA_METRES, CAMERA_DEGREES = 0.75, 15.0  # a quarter of the camera's distance; the aim is 0.10 m, 5 degrees
