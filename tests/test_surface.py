"""The exported surface of a soft volume: where rays turn half opaque, and fuzz that makes the silhouette."""

from __future__ import annotations

import math

import numpy as np
from skimage.measure import marching_cubes

from elicit_diffrender.outputs.surface import FUZZ_DENSITY, FUZZ_DEPTH, line_depths, line_directions, surface_field

N = 32
CENTRE = (N - 1) / 2


def ball(radius: float, density: float) -> np.ndarray:
    """A ball of constant density per voxel on an N^3 grid of 1-voxel spacing."""
    idx = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1)
    r = np.linalg.norm(idx - CENTRE, axis=-1)
    return np.where(r <= radius, density, 0.0)


def mean_radius(field: np.ndarray) -> float:
    verts, _, _, _ = marching_cubes(field, level=1.0)
    return float(np.linalg.norm(verts - CENTRE, axis=1).mean())


def test_a_line_through_a_uniform_ball_has_its_chord_times_the_density() -> None:
    volume = ball(10.0, 0.3)
    c = int(round(CENTRE))
    at = np.ravel_multi_index(([c, 0], [c, 0], [c, 0]), volume.shape)  # the centre and a corner
    depth = np.min(list(line_depths(volume, (1.0, 1.0, 1.0), 1.0, line_directions(), at)), axis=0)
    # Through the centre every line is a diameter: 2 R sigma (the ball's nodes are voxelised, so within a voxel).
    assert abs(depth[0] - 2 * 10.0 * 0.3) < 0.3 * 1.5
    assert depth[1] < 1e-9  # a corner's lines miss the ball


def test_a_dense_ball_is_meshed_at_its_edge() -> None:
    volume = ball(8.0, 50.0)
    radius = mean_radius(surface_field(volume, (1.0, 1.0, 1.0), 1.0))
    assert 7.5 < radius < 9.0  # between the last node inside and the first outside


def test_fuzz_is_meshed_where_every_line_through_it_is_opaque() -> None:
    """A ball of density 0.3 per voxel (below the old level, 0.45): a node at radius r is fuzz when the
    shortest chord through it, 2 sqrt(R^2 - r^2), holds optical depth FUZZ_DEPTH."""
    R, sigma = 10.0, 0.3
    assert sigma >= FUZZ_DENSITY
    expected = math.sqrt(R**2 - (FUZZ_DEPTH / (2 * sigma)) ** 2)  # 9.73 voxels
    radius = mean_radius(surface_field(ball(R, sigma), (1.0, 1.0, 1.0), 1.0))
    assert abs(radius - expected) < 0.6
    # Thinner fuzz is not meshed by itself: only where rays from outside turn half opaque.
    thin = mean_radius(surface_field(ball(R, 0.1), (1.0, 1.0, 1.0), 1.0))
    assert thin < R - math.log(2) / 0.1 + 1.5  # 3.07 voxels on the axes, a little more between them


def test_sparse_fuzz_around_a_core_is_meshed_out_to_the_silhouette() -> None:
    """A dense ball (radius 4) in a shell of sparse fuzz (radius 6 to 10, 0.15 per voxel: below
    FUZZ_DENSITY, so no line rule alone meshes it). A ray at distance r from the centre that misses the
    core holds 2 sqrt(R^2 - r^2) sigma, half opaque out to r = 9.73: the volume's silhouette, from every
    side. The mesh reaches it there, and leaves the empty gap around the core empty."""
    from elicit_diffrender.outputs.surface import SPARSE_DENSITY

    R, sigma = 10.0, 0.15
    assert SPARSE_DENSITY <= sigma < FUZZ_DENSITY
    idx = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1)
    r = np.linalg.norm(idx - CENTRE, axis=-1)
    volume = np.where(r <= 4.0, 50.0, 0.0) + np.where((r >= 6.0) & (r <= R), sigma, 0.0)
    field = surface_field(volume, (1.0, 1.0, 1.0), 1.0)
    verts, _, _, _ = marching_cubes(field, level=1.0)
    radius = np.linalg.norm(verts - CENTRE, axis=1)
    silhouette = math.sqrt(R**2 - (math.log(2) / (2 * sigma)) ** 2)  # 9.73 voxels
    assert abs(radius.max() - silhouette) < 0.8, radius.max()
    assert abs(np.percentile(radius, 90) - silhouette) < 1.0
    assert field[int(round(CENTRE)) + 5, int(round(CENTRE)), int(round(CENTRE))] < 1.0  # the gap, r = 5
