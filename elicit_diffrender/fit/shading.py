"""The photo's light, estimated from the body it shows: an ambient term plus one directional light.

A photo shows radiance, not albedo: the side of a person facing the key light is brighter than the
side facing away, so colour copied from the seen front onto the unseen back is too bright there.
With the body's normals known, a Lambertian model with ambient light and one distant light,

    I_v = rho_v * S(n_v),    S(n) = 1 + k * max(0, n . l),

explains the seen vertices' colours. Albedo ``rho`` is shared by vertices of one cluster of
chromaticity (a light of one colour changes brightness, not hue), so the fit is over the light
direction ``l`` and the key-to-ambient ratio ``k`` only: a search over directions on a sphere and
ratios on a grid, each cluster's log albedo in closed form (its mean log residual), the worst
``TRIM`` of the residuals dropped in a second pass. A light that explains less than ``MIN_EXPLAINED``
of the brightness variation within the clusters (patterned clothes, folds, a body that fits the
photo loosely) is taken for flat, ``k = 0``, and then nothing is relit. Measured: the five shared real
photos explain 1-9%; the photo-path subjects, path-traced under one key light, 11-40% (scans
included), except a suit of one dark colour (none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..core.cameras import Camera

RATIOS = np.concatenate([[0.0], np.geomspace(0.05, 8.0, 40)])  # candidate key-to-ambient ratios
DIRECTIONS = 400  # candidate light directions on the sphere, then as many again within REFINE_DEGREES of the best
REFINE_DEGREES = 15.0
CLUSTERS = 8  # chromaticity clusters (albedo groups)
MIN_LUMA = 0.03  # per channel: darker samples carry no usable chromaticity
EDGE_FRACTION = 0.004  # samples closer than this share of the image size to the mask's edge mix with the background
MAX_SAMPLES = 3000  # seen vertices used by the fit (a fixed random subset)
TRIM = 0.1  # share of the worst residuals dropped in the second pass
MIN_EXPLAINED = 0.1  # a light that explains less of the brightness within albedo clusters is taken for flat


@dataclass
class Shading:
    """``S(n) = 1 + ratio * max(0, n . direction)``; ``direction`` points towards the light (world)."""

    direction: np.ndarray
    ratio: float
    residual: float = 0.0  # RMS log residual of the fit (after trimming)
    explained: float = 0.0  # share of the squared log residual of flat light that the light explains
    samples: int = 0

    def __call__(self, normals: np.ndarray) -> np.ndarray:
        return 1.0 + self.ratio * np.maximum(normals @ self.direction, 0.0)

    def to_dict(self) -> dict:
        return {
            "direction": [round(float(x), 4) for x in self.direction],
            "ratio": round(float(self.ratio), 4),
            "residual": round(float(self.residual), 4),
            "explained": round(float(self.explained), 4),
            "samples": int(self.samples),
        }


FLAT = Shading(np.array([0.0, 0.0, 1.0]), 0.0)


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], 1)


def _kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 20) -> np.ndarray:
    centres = x[rng.choice(len(x), size=min(k, len(x)), replace=False)]
    for _ in range(iters):
        label = ((x[:, None] - centres[None]) ** 2).sum(-1).argmin(1)
        centres = np.stack([x[label == c].mean(0) if (label == c).any() else centres[c] for c in range(len(centres))])
    return label


def seen_colors(
    image: np.ndarray, person: np.ndarray, camera: Camera, vertices: np.ndarray, seen: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the seen vertices that project well inside the mask, and their (N, 3) image colours."""
    h, w = person.shape
    inner = ndimage.binary_erosion(person, iterations=max(1, round(EDGE_FRACTION * max(h, w))))
    idx = np.nonzero(seen)[0]
    uv, _ = camera.project(vertices[idx])
    px = np.floor(uv).astype(int)
    ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    idx, px = idx[ok], px[ok]
    ok = inner[px[:, 1], px[:, 0]]
    return idx[ok], image[px[ok, 1], px[ok, 0]]


def _cap(direction: np.ndarray, degrees: float, n: int) -> np.ndarray:
    """``n`` unit vectors within ``degrees`` of ``direction`` (a Fibonacci cap around it)."""
    i = np.arange(n) + 0.5
    cos_t = 1 - (1 - np.cos(np.radians(degrees))) * i / n
    sin_t = np.sqrt(1 - cos_t**2)
    theta = np.pi * (1 + 5**0.5) * i
    a = np.cross(direction, [1.0, 0.0, 0.0] if abs(direction[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(direction, a)
    return cos_t[:, None] * direction + sin_t[:, None] * (np.cos(theta)[:, None] * a + np.sin(theta)[:, None] * b)


def _search(log_y, normals, group, weight, dirs):
    """The (cost, ratio, direction index, residuals) of least weighted squares over ``RATIOS`` x ``dirs``.

    With ``L = log(1 + k cos)`` (N, D) for a ratio ``k``, the residual ``r = log_y - L`` minus its cluster's weighted
    mean (its log albedo) costs ``sum_i w_i r_i^2 - sum_c S_c^2 / n_c`` (``S_c = sum_{i in c} w_i r_i``, ``n_c =
    sum_{i in c} w_i``): per ratio, one product of the clusters' weights and ``w log_y`` (C + 1, N) with ``L`` and
    one of ``w`` with ``L^2``; the (N, D) residuals are never formed."""
    onehot = np.eye(group.max() + 1)[group] * weight[:, None]
    counts = np.maximum(onehot.sum(0), 1e-9)
    cos = np.maximum(normals @ dirs.T, 0.0)  # (N, D)
    sums_y = onehot.T @ log_y  # (C,)
    square_y = float(weight @ log_y**2)
    left = np.concatenate([onehot, (weight * log_y)[:, None]], 1).T  # (C + 1, N)
    best = None
    for k in RATIOS:
        light = np.log1p(k * cos)
        products = left @ light  # (C + 1, D)
        sums = sums_y[:, None] - products[:-1]  # S_c for every direction
        cost = square_y - 2 * products[-1] + weight @ light**2 - (sums**2 / counts[:, None]).sum(0)
        d = int(cost.argmin())
        if best is None or cost[d] < best[0]:
            best = (float(cost[d]), float(k), d)
    cost, k, d = best
    r = log_y - np.log1p(k * cos[:, d])
    return cost, k, d, r - ((onehot.T @ r) / counts)[group]


def estimate_shading(
    image: np.ndarray, person: np.ndarray, camera: Camera, vertices: np.ndarray, normals: np.ndarray, seen: np.ndarray
) -> Shading:
    """Fit ``S`` to the (H, W, 3) ``image`` (linear in [0, 1], the person inside the (H, W) ``person`` mask) at the
    ``seen`` of the posed ``vertices`` (world) with their ``normals``; ``FLAT`` when too little is seen."""
    idx, rgb = seen_colors(image, person, camera, vertices, seen)
    keep = (rgb > MIN_LUMA).all(1)
    idx, rgb = idx[keep], rgb[keep]
    if len(idx) < 50:
        return FLAT
    rng = np.random.default_rng(0)
    if len(idx) > MAX_SAMPLES:
        pick = np.sort(rng.choice(len(idx), MAX_SAMPLES, replace=False))
        idx, rgb = idx[pick], rgb[pick]
    luma = rgb.sum(1)
    group = _kmeans(rgb[:, :2] / luma[:, None], CLUSTERS, rng)
    log_y, n = np.log(luma), normals[idx]
    weight = np.ones(len(idx))
    for _ in range(2):  # all samples, then without the worst TRIM of the residuals
        _, _, d, _ = coarse = _search(log_y, n, group, weight, fibonacci_sphere(DIRECTIONS))
        direction = fibonacci_sphere(DIRECTIONS)[d]
        fine_dirs = _cap(direction, REFINE_DEGREES, DIRECTIONS)
        fine = _search(log_y, n, group, weight, fine_dirs)
        _, ratio, d, res = fine if fine[0] < coarse[0] else coarse
        direction = fine_dirs[d] if fine[0] < coarse[0] else direction
        weight = (np.abs(res) <= np.quantile(np.abs(res), 1 - TRIM)).astype(np.float64)
    cost = float((weight * res**2).sum())
    onehot = np.eye(group.max() + 1)[group] * weight[:, None]
    flat = log_y - ((onehot.T @ log_y) / np.maximum(onehot.sum(0), 1e-9))[group]  # albedo alone, no light
    explained = 1.0 - cost / max(float((weight * flat**2).sum()), 1e-12)
    rms = float(np.sqrt(cost / max(weight.sum(), 1.0)))
    ratio = ratio if explained >= MIN_EXPLAINED else 0.0
    return Shading(direction / np.linalg.norm(direction), ratio, rms, explained, len(idx))
