"""Body models: Anny, SMPL from synthetic model files, parts, the reduced skeleton and axis conventions."""

import numpy as np
import pytest
import torch

from elicit_diffrender.body import PART_NAMES, BodyModelError, load_body
from elicit_diffrender.core.geometry import rigid_inverse
from elicit_diffrender.model.skinning import forward_lbs


def lbs_error(body, pose, orient=None, transl=None, reduced=False) -> float:
    """Max distance between the model's posed vertices and LBS of its rest mesh with its bone frames."""
    rest = body.pose(body.zero_pose())
    posed = body.pose(pose, orient, transl)
    if reduced:
        keep = [body.joint_index(n) for n in body.reduced_joints]
        w = body.reduced_weights()
        idx = np.tile(np.arange(w.shape[1]), (w.shape[0], 1))
        frames_p, frames_r = posed.bone_transforms[keep], rest.bone_transforms[keep]
    else:
        idx, w = body.skin_idx, body.skin_w
        frames_p, frames_r = posed.bone_transforms, rest.bone_transforms
    mats = torch.as_tensor(frames_p) @ rigid_inverse(torch.as_tensor(frames_r))
    v = forward_lbs(torch.as_tensor(rest.vertices), torch.as_tensor(idx), torch.as_tensor(w), mats).numpy()
    return float(np.abs(v - posed.vertices).max())


def test_anny_basics(anny_body):
    b = anny_body
    assert b.n_joints == 104 and b.rest_vertices.shape == (13718, 3)
    np.testing.assert_allclose(b.skin_w.sum(1), 1.0, atol=1e-9)
    height = np.ptp(b.rest_vertices[:, 1])
    assert 1.4 < height < 2.0
    lo, hi = b.rest_vertices.min(0), b.rest_vertices.max(0)
    assert abs(lo[0] + hi[0]) < 1e-3  # left-right symmetric about x = 0
    nose = b.rest_vertices[np.argmax(b.rest_vertices[:, 2] * (b.rest_vertices[:, 1] > 0.5))]
    assert nose[2] > 0.05  # the face points +z


def test_anny_parts_and_reduced_skeleton(anny_body):
    b = anny_body
    parts = b.vertex_parts()
    counts = np.bincount(parts, minlength=len(PART_NAMES))
    assert (counts > 200).all(), dict(zip(PART_NAMES, counts, strict=True))
    left = b.rest_vertices[parts == PART_NAMES.index("left_forearm")]
    assert (left[:, 0] > 0.1).all()  # the body's left is +x
    assert len(b.reduced_joints) == 21
    np.testing.assert_allclose(b.reduced_weights().sum(1), 1.0, atol=1e-9)


def test_anny_bone_frames_reproduce_its_skinning(anny_body):
    rng = np.random.default_rng(0)
    pose = 0.3 * rng.standard_normal((104, 3))
    assert lbs_error(anny_body, pose, np.array([0.1, 0.5, 0.2]), np.array([0.3, 0.1, -0.2])) < 4e-3


def test_reduced_skeleton_drives_kept_joints_exactly(anny_body):
    b = anny_body
    pose = b.zero_pose()
    for j, rv in (("l_knee", (0.8, 0, 0)), ("r_shoulder", (0, 0, -1.2)), ("spine_mid", (0.2, 0.3, 0))):
        b.set_semantic(pose, j, rv)
    assert lbs_error(b, pose, reduced=True) < 4e-3


@pytest.mark.parametrize("model", ["anny", "smpl"])
def test_semantic_axes_agree_across_models(model, anny_body, smpl_file):
    b = anny_body if model == "anny" else load_body({"model": "smpl", "model_path": str(smpl_file)})
    pose = b.zero_pose()
    b.set_semantic(pose, "l_knee", (np.radians(60), 0, 0))
    rest, bent = b.pose(b.zero_pose()), b.pose(pose)
    ankle = b.joint_index(b.semantic["l_ankle"])
    move = bent.bone_transforms[ankle, :3, 3] - rest.bone_transforms[ankle, :3, 3]
    assert move[2] < -0.05 and move[1] > 0.02  # a bent knee takes the foot backwards and up


def test_smpl_from_synthetic_model_file(smpl_file):
    b = load_body({"model": "smpl", "model_path": str(smpl_file), "betas": [0.5, -0.2]})
    assert b.n_joints == 24 and b.rest_vertices.shape == (192, 3)
    rng = np.random.default_rng(1)
    pose = 0.4 * rng.standard_normal((24, 3))
    assert lbs_error(b, pose, np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 2.0])) < 1e-7
    parts = b.vertex_parts()
    assert set(parts.tolist()) == set(range(len(PART_NAMES)))


def test_smpl_missing_files_give_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("ELICIT_SMPL_DIR", raising=False)
    with pytest.raises(BodyModelError, match="licensed"):
        load_body({"model": "smpl"})
    with pytest.raises(BodyModelError, match="SMPL_FEMALE"):
        load_body({"model": "smpl", "gender": "female", "model_path": str(tmp_path)})
    (tmp_path / "SMPL_NEUTRAL.pkl").write_bytes(b"not a pickle")
    with pytest.raises(BodyModelError, match="cannot load"):
        load_body({"model": "smpl", "model_path": str(tmp_path)})


def test_bad_body_parameters(anny_body):
    with pytest.raises(BodyModelError, match="phenotype"):
        load_body({"model": "anny", "phenotype": {"height": 3.0}})
    with pytest.raises(BodyModelError, match="unknown phenotype"):
        load_body({"model": "anny", "phenotype": {"hat": 0.5}})
    with pytest.raises(BodyModelError, match="NaN"):
        anny_body.pose(np.full((104, 3), np.nan))
    with pytest.raises(BodyModelError, match="unknown body model"):
        load_body({"model": "mano"})
