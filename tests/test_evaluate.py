"""Evaluation geometry: the Umeyama alignment of the photo path, cameras carried across it, rear views."""

import numpy as np
import torch

from elicit_diffrender.core.cameras import look_at
from elicit_diffrender.core.geometry import axis_angle_to_matrix
from elicit_diffrender.outputs.evaluate import angle_around_body, camera_in_frame, umeyama


def _similarity(seed: int):
    rng = np.random.default_rng(seed)
    rot = axis_angle_to_matrix(torch.as_tensor(rng.normal(size=(1, 3)))).numpy()[0]
    return float(rng.uniform(0.5, 2.0)), rot, rng.normal(size=3)


def test_umeyama_recovers_a_similarity_and_cameras_see_the_same_image():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(200, 3))
    s, rot, t = _similarity(1)
    dst = s * src @ rot.T + t
    s2, rot2, t2 = umeyama(src, dst)
    assert abs(s2 - s) < 1e-9 and np.allclose(rot2, rot, atol=1e-9) and np.allclose(t2, t, atol=1e-9)
    # Noise: still the least-squares answer, near the truth.
    s3, rot3, _ = umeyama(src, dst + 0.01 * rng.normal(size=dst.shape))
    assert abs(s3 - s) < 0.01 and np.allclose(rot3, rot, atol=0.02)
    # A camera of the destination frame, carried into the source frame, projects src where it projects dst.
    cam = look_at(np.array([0.0, 1.0, 6.0]), dst.mean(0), np.array([0.0, 1.0, 0.0]), 400.0, 128, 96)
    moved = camera_in_frame(cam, s, rot, t)
    uv_dst, z_dst = cam.project(dst)
    uv_src, z_src = moved.project(src)
    assert np.allclose(uv_src, uv_dst, atol=1e-8) and np.allclose(z_src * s, z_dst, atol=1e-8)


def test_angle_around_the_body_ignores_height():
    up = np.array([0.0, 1.0, 0.0])
    centre = np.zeros(3)
    front = look_at(np.array([0.0, 0.0, 3.0]), centre, up, 300.0, 64, 64)
    back_high = look_at(np.array([0.0, 2.0, -3.0]), centre, up, 300.0, 64, 64)
    side = look_at(np.array([3.0, -1.0, 0.0]), centre, up, 300.0, 64, 64)
    assert abs(angle_around_body(back_high, front, centre, up) - 180.0) < 1e-6
    assert abs(angle_around_body(side, front, centre, up) - 90.0) < 1e-6


def test_silhouette_metrics_count_holes_and_spill_against_the_mask():
    from elicit_diffrender.outputs.evaluate import silhouette_metrics

    mask = np.zeros((20, 20), dtype=bool)
    mask[5:15, 5:15] = True  # 100 pixels
    alpha = np.zeros((20, 20))
    alpha[5:15, 5:13] = 0.9  # 80 of them covered: 20 holes
    alpha[0:2, 0:5] = 0.6  # 10 spilt outside
    alpha[14, 14] = 0.4  # under half: not solid
    m = silhouette_metrics(alpha, mask)
    assert m["hole_fraction"] == 0.2 and m["spill"] == 0.1 and abs(m["silhouette_iou"] - 80 / 110) < 1e-12


def test_lean_angles_read_a_lean_towards_the_camera_and_errors_compare_two_bodies(anny_body):
    """A body tipped 20 degrees towards a level camera in front reads 20 degrees more towards it, torso and shins;
    seen from its left, the same tip is sideways in the image; the error between the two bodies is 20 degrees."""
    from elicit_diffrender.outputs.evaluate import lean_angles, lean_errors

    pose = anny_body.zero_pose()
    tipped = (pose, np.array([np.radians(20.0), 0.0, 0.0]), None)  # about +x (the body's left): top forwards
    upright = (pose, None, None)
    front = look_at(np.array([0.0, 0.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 500.0, 64, 64)
    a, b = lean_angles(anny_body, tipped, front), lean_angles(anny_body, upright, front)
    for segment in ("torso", "left_shin", "right_shin"):
        assert abs(a[segment]["towards_camera"] - b[segment]["towards_camera"] - 20.0) < 1e-6
        assert abs(a[segment]["sideways"] - b[segment]["sideways"]) < 1.0  # (a splayed shin tips a little sideways)
    side = look_at(np.array([3.0, 0.0, 0.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]), 500.0, 64, 64)
    c, d = lean_angles(anny_body, tipped, side), lean_angles(anny_body, upright, side)
    assert abs(abs(c["torso"]["sideways"] - d["torso"]["sideways"]) - 20.0) < 0.5
    errors = lean_errors(a, b)
    assert all(abs(errors[s] - 20.0) < 0.5 for s in ("torso", "left_shin", "right_shin"))
    assert max(lean_errors(a, a).values()) < 1e-6
