"""Motions: built-ins, motion.npz round trips and validation, AMASS and ZJU-MoCap sequences."""

import numpy as np
import pytest

from elicit_diffrender.body import load_body
from elicit_diffrender.data.motions import (
    BUILTIN_MOTIONS,
    Motion,
    MotionError,
    builtin_motion,
    load_motion,
    load_motion_npz,
)


@pytest.mark.parametrize("name", BUILTIN_MOTIONS)
def test_builtin_motions(anny_body, name):
    m = builtin_motion(name, anny_body)
    assert m.pose.shape[1:] == (104, 3) and np.isfinite(m.pose).all()
    if name != "rest":
        assert len(m) >= 24 and np.abs(m.pose).max() > 0.3
    posed = anny_body.pose(*m.frame(len(m) // 2))
    floor = anny_body.rest_vertices[:, 1].min()
    if name in ("walk_in_place", "squat", "turn_around"):
        assert abs(posed.vertices[:, 1].min() - floor) < 1e-6  # feet stay on the floor
    if name == "turn_around":
        assert np.allclose(m.global_orient[len(m) // 2], [0, np.pi, 0], atol=0.2)


def test_squat_lowers_the_pelvis_and_wave_raises_the_right_hand(anny_body):
    b = anny_body
    squat = builtin_motion("squat", b)
    mid = b.pose(*squat.frame(len(squat) // 2))
    rest = b.pose(b.zero_pose())
    pelvis = b.joint_index("root")
    assert mid.bone_transforms[pelvis, 1, 3] < rest.bone_transforms[pelvis, 1, 3] - 0.2
    wave = builtin_motion("wave", b)
    hand = b.joint_index(b.semantic["r_wrist"])
    up = b.pose(*wave.frame(0)).bone_transforms[hand, :3, 3]
    assert up[1] > rest.bone_transforms[b.joint_index(b.semantic["head"]), 1, 3]  # above the head joint
    assert up[0] < -0.2  # on the body's right side


def test_motion_npz_round_trip_and_placement(tmp_path, anny_body):
    m = builtin_motion("walk_in_place", anny_body, n_frames=12)
    path = m.save(tmp_path / "motion.npz")
    back = load_motion_npz(path, 104)
    np.testing.assert_allclose(back.pose, m.pose)
    np.testing.assert_array_equal(back.frame_ids, np.arange(12))
    rot = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    placed = m.placed(rot, np.array([0.0, 0.2, 3.0]))
    a = anny_body.pose(*m.frame(3)).vertices
    b = anny_body.pose(*placed.frame(3)).vertices
    np.testing.assert_allclose(b, a @ rot.T + [0.0, 0.2, 3.0], atol=1e-6)  # motions store float32


def test_bad_motion_files_name_the_field(tmp_path):
    good = dict(pose=np.zeros((3, 104, 3), np.float32), global_orient=np.zeros((3, 3)), transl=np.zeros((3, 3)))
    cases = {
        "missing": ({k: v for k, v in good.items() if k != "transl"}, "missing field 'transl'"),
        "shape": ({**good, "global_orient": np.zeros((2, 3))}, "'global_orient' must be"),
        "nan": ({**good, "pose": np.full((3, 104, 3), np.nan, np.float32)}, "'pose' contains NaN"),
        "joints": ({**good, "pose": np.zeros((3, 24, 3), np.float32)}, "24 joints"),
        "ids": ({**good, "frame_ids": np.arange(2)}, "'frame_ids' must be"),
    }
    for name, (data, message) in cases.items():
        np.savez(tmp_path / f"{name}.npz", **data)
        with pytest.raises(MotionError, match=message):
            load_motion_npz(tmp_path / f"{name}.npz", 104)
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(MotionError, match="not a readable"):
        load_motion_npz(tmp_path / "junk.npz")
    with pytest.raises(MotionError, match="neither a built-in"):
        load_motion("moonwalk", None)


def test_amass_and_zju_sequences(tmp_path, smpl_file):
    body = load_body({"model": "smpl", "model_path": str(smpl_file)})
    rng = np.random.default_rng(0)
    poses = 0.2 * rng.standard_normal((8, 156))
    trans = rng.standard_normal((8, 3))
    np.savez(tmp_path / "amass.npz", poses=poses, trans=trans, mocap_framerate=120.0, betas=np.zeros(16))
    m = load_motion(tmp_path / "amass.npz", body)
    assert m.pose.shape == (8, 24, 3) and m.fps == 120.0
    # z-up AMASS becomes y-up: the translation's z turns into y.
    np.testing.assert_allclose(m.transl[:, 1], trans[:, 2], atol=1e-6)
    np.testing.assert_allclose(m.pose[:, :22], poses[:, :66].reshape(8, 22, 3), atol=1e-6)
    params = tmp_path / "new_params"
    params.mkdir()
    for f in (0, 5, 10):
        np.save(
            params / f"{f}.npy",
            {
                "poses": 0.1 * rng.standard_normal((1, 72)),
                "Rh": rng.standard_normal((1, 3)),
                "Th": rng.standard_normal((1, 3)),
                "shapes": np.zeros((1, 10)),
            },
        )
    z = load_motion(params, body)
    assert z.frame_ids.tolist() == [0, 5, 10] and np.all(z.pose[:, 0] == 0)
    anny_like = Motion(np.zeros((1, 104, 3)), np.zeros((1, 3)), np.zeros((1, 3)))
    assert len(anny_like) == 1


def test_anny_walk_cycle_reaches_its_targets_and_loops(anny_body, smpl_file):
    from elicit_diffrender.body.anny_walk import anny_walk_cycle

    b = anny_body
    m, reach = anny_walk_cycle(b, 40)
    assert m.pose.shape == (40, 104, 3) and np.isfinite(m.pose).all() and np.isfinite(m.transl).all()
    # The IK lands the feet and hands on the clip's targets (Anny's legs differ slightly from MPFB's).
    for target in ("left_foot_ik", "right_foot_ik", "left_hand_ik", "right_hand_ik"):
        assert reach[target] < 0.05, (target, reach[target])
    posed = b.pose_batch(m.pose, m.global_orient, m.transl)
    l_ankle, r_ankle = (b.joint_index(b.semantic[k]) for k in ("l_ankle", "r_ankle"))
    stride = np.array([p.bone_transforms[l_ankle, 2, 3] - p.bone_transforms[r_ankle, 2, 3] for p in posed])
    assert stride.max() > 0.2 and stride.min() < -0.2  # the feet take turns in front (+z)
    # It loops: the last frame leads smoothly into the first.
    step = np.abs(np.diff(m.pose, axis=0)).max()
    assert np.abs(m.pose[0] - m.pose[-1]).max() < 2 * step
    floor = b.rest_vertices[:, 1].min()
    assert abs(min(p.vertices[:, 1].min() for p in posed) - floor) < 1e-6
    with pytest.raises(MotionError, match="Anny body"):
        builtin_motion("anny_walk", load_body({"model": "smpl", "model_path": str(smpl_file)}))
