"""ELICIT's hybrid sampling: body-part-aware crops and rotation-aware camera directions.

Numbers are the reference code's: part probabilities, the per-part direction table and the yaw
sectors of the body-relative camera. The reference image follows the paper: a rear camera takes a
no-grad render from the nearest side camera as its reference (any part), and a side view of the
head takes one from the nearest front camera; every other case uses the matching crop of the input
image. (The released code restricts rear references to the head and the legs.)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..body import PART_NAMES
from ..core.cameras import Camera

PART_PROBS = {"full": 0.1, "head": 0.3, "torso": 0.2, **{p: 0.05 for p in PART_NAMES[2:]}}
DIRECTIONS = ("front", "left", "right", "back")
DIRECTION_TABLE = {
    "head": (0.7, 0.05, 0.05, 0.2),
    "full": (0.35, 0.3, 0.3, 0.05),
    "torso": (0.25, 0.25, 0.25, 0.25),
    "left": (0.2, 0.6, 0.0, 0.2),
    "right": (0.2, 0.0, 0.6, 0.2),
}
MAX_PART_TRIES = 10


def direction_probs(part: str) -> tuple[float, ...]:
    if part in ("head", "full", "torso"):
        return DIRECTION_TABLE[part]
    return DIRECTION_TABLE["left" if part.startswith("left") else "right"]


def body_yaw(camera: Camera, body_rotation: np.ndarray) -> float:
    """Yaw (degrees) of the body's facing seen from the camera: ``atan2(R[0, 2], R[2, 2])`` of
    ``R = R_camera @ R_body``. 0 means the camera sees the back, +-180 the front, -90 the left side."""
    rel = camera.R @ np.asarray(body_rotation)
    return float(np.degrees(np.arctan2(rel[0, 2], rel[2, 2])))


def sector(yaw: float) -> str:
    """back [-45, 45), left [-135, -45), right [45, 135), front |yaw| >= 135."""
    if -45.0 <= yaw < 45.0:
        return "back"
    if -135.0 <= yaw < -45.0:
        return "left"
    if 45.0 <= yaw < 135.0:
        return "right"
    return "front"


def sample_part(rng: np.random.Generator) -> str:
    names = list(PART_PROBS)
    return names[rng.choice(len(names), p=np.array(list(PART_PROBS.values())))]


def sample_direction(part: str, rng: np.random.Generator) -> str:
    return DIRECTIONS[rng.choice(4, p=np.array(direction_probs(part)))]


def part_pixels(labels: np.ndarray, part: str) -> np.ndarray:
    """Boolean mask of a part (``full`` = the whole body) in a label image (-1 = background)."""
    if part == "full":
        return labels >= 0
    return labels == PART_NAMES.index(part)


def crop_window(mask: np.ndarray, part: str) -> tuple[float, float, float] | None:
    """Square window (x0, y0, side) around a part's pixels: 5% padding, 50% for the head."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return None
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    pad = 0.5 if part == "head" else 0.05
    side = max(x1 - x0, y1 - y0) * (1 + 2 * pad)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return float(cx - side / 2), float(cy - side / 2), float(side)


@dataclass
class NovelView:
    camera: int  # ring camera index
    part: str
    direction: str
    window: tuple[float, float, float]  # square in the label image of that camera
    reference: str  # "input" or "render"
    ref_camera: int  # ring camera of a rendered reference (-1 for the input image)


def nearest_in_sector(yaws: np.ndarray, target_yaw: float, wanted: tuple[str, ...]) -> int:
    """The camera in one of the ``wanted`` sectors whose yaw is closest to ``target_yaw``."""
    best, best_d = -1, np.inf
    for j, y in enumerate(yaws):
        if sector(y) in wanted:
            d = abs((y - target_yaw + 180.0) % 360.0 - 180.0)
            if d < best_d:
                best, best_d = j, d
    return best


def plan_novel_view(
    rng: np.random.Generator,
    yaws: np.ndarray,
    labels: Sequence[np.ndarray],
    min_pixels: int,
    hybrid: bool = True,
) -> NovelView | None:
    """Draw a part, a direction and a camera of one pose; ``yaws``/``labels`` are that pose's per ring camera.

    A part with fewer than ``min_pixels`` pixels is redrawn; after ten tries the whole body is used.
    Without ``hybrid`` (the ablation) the part is always the whole body, the camera uniform and the
    reference the input image.
    """
    n_cams = len(yaws)
    if not hybrid:
        cam = int(rng.integers(n_cams))
        window = crop_window(part_pixels(labels[cam], "full"), "full")
        return None if window is None else NovelView(cam, "full", sector(yaws[cam]), window, "input", -1)
    for attempt in range(MAX_PART_TRIES + 1):
        part = sample_part(rng) if attempt < MAX_PART_TRIES else "full"
        direction = sample_direction(part, rng)
        in_sector = [j for j in range(n_cams) if sector(yaws[j]) == direction]
        if not in_sector:
            continue
        cam = int(rng.choice(in_sector))
        mask = part_pixels(labels[cam], part)
        if mask.sum() < min_pixels and part != "full":
            continue
        window = crop_window(mask, part)
        if window is None:
            continue
        reference, ref_cam = "input", -1
        if direction == "back":
            ref_cam = nearest_in_sector(yaws, yaws[cam], ("left", "right"))
        elif part == "head" and direction in ("left", "right"):
            ref_cam = nearest_in_sector(yaws, yaws[cam], ("front",))
        if ref_cam >= 0:
            reference = "render"
        return NovelView(cam, part, direction, window, reference, ref_cam)
    return None
