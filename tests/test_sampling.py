"""Hybrid sampling: the reference code's probabilities, direction tables and yaw sectors."""

import numpy as np
import pytest

from elicit_diffrender.body import PART_NAMES
from elicit_diffrender.data.rigs import ring_cameras
from elicit_diffrender.fit.hybrid_sampling import (
    DIRECTIONS,
    PART_PROBS,
    body_yaw,
    crop_window,
    direction_probs,
    plan_novel_view,
    sample_direction,
    sample_part,
    sector,
)

N = 20000


def within(count: int, p: float, n: int = N) -> bool:
    return abs(count / n - p) <= 4 * np.sqrt(p * (1 - p) / n) + 1e-9


def test_part_frequencies_match_the_table():
    rng = np.random.default_rng(0)
    draws = [sample_part(rng) for _ in range(N)]
    assert set(PART_PROBS) == {"full", "head", "torso", *PART_NAMES[2:]}
    assert abs(sum(PART_PROBS.values()) - 1) < 1e-9
    for part, p in PART_PROBS.items():
        assert within(draws.count(part), p), (part, draws.count(part) / N, p)


@pytest.mark.parametrize("part", ["head", "full", "torso", "left_forearm", "right_shin"])
def test_direction_frequencies_match_the_table(part):
    rng = np.random.default_rng(1)
    draws = [sample_direction(part, rng) for _ in range(N)]
    for d, p in zip(DIRECTIONS, direction_probs(part), strict=True):
        assert within(draws.count(d), p), (part, d, draws.count(d) / N, p)
    if part.startswith("left"):
        assert draws.count("right") == 0
    if part.startswith("right"):
        assert draws.count("left") == 0


def test_yaw_sectors_and_body_yaw():
    assert [sector(y) for y in (-45, 0, 44.9, 45, 134.9, 135, 180, -180, -135, -135.1, -45.1)] == [
        "back",
        "back",
        "back",
        "right",
        "right",
        "front",
        "front",
        "front",
        "left",
        "front",
        "left",
    ]
    cams = ring_cameras(n=4)  # front, left side (+x), back, right side
    yaws = [body_yaw(c, np.eye(3)) for c in cams]
    assert [sector(y) for y in yaws] == ["front", "left", "back", "right"]
    turned = np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])  # the body turned around
    assert sector(body_yaw(cams[0], turned)) == "back"


def test_crop_window_padding():
    mask = np.zeros((100, 100), bool)
    mask[20:40, 30:70] = True
    x0, y0, side = crop_window(mask, "torso")
    assert side == pytest.approx(40 * 1.1) and x0 + side / 2 == pytest.approx(50)
    assert crop_window(mask, "head")[2] == pytest.approx(40 * 2)
    assert crop_window(np.zeros((4, 4), bool), "full") is None


def test_references_follow_the_paper():
    cams = ring_cameras(n=8)
    yaws = np.array([body_yaw(c, np.eye(3)) for c in cams])
    labels = [np.zeros((64, 64), np.int16) - 1 for _ in cams]
    for lab in labels:
        for k in range(len(PART_NAMES)):
            lab[4 + 5 * k : 8 + 5 * k, 10:50] = k  # every part visible, 160 pixels each
    rng = np.random.default_rng(3)
    seen = set()
    for _ in range(2000):
        v = plan_novel_view(rng, yaws, labels, min_pixels=50)
        seen.add((v.part == "head", v.direction, v.reference))
        if v.direction == "back":
            assert v.reference == "render" and sector(yaws[v.ref_camera]) in ("left", "right")
        elif v.part == "head" and v.direction in ("left", "right"):
            assert v.reference == "render" and sector(yaws[v.ref_camera]) == "front"
        else:
            assert v.reference == "input" and v.ref_camera == -1
        assert sector(yaws[v.camera]) == v.direction
    assert (True, "left", "render") in seen and (False, "front", "input") in seen
    # Too few pixels for any part: after ten redraws the whole body is used.
    tiny = [np.where(lab >= 0, lab, -1) for lab in labels]
    v = plan_novel_view(np.random.default_rng(0), yaws, tiny, min_pixels=10_000)
    assert v.part == "full"
    plain = plan_novel_view(np.random.default_rng(0), yaws, labels, min_pixels=50, hybrid=False)
    assert plain.part == "full" and plain.reference == "input"
