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
