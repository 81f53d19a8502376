"""Where a soft volume's surface lies: the scalar field whose level 1 the export meshes.

The volume renderer makes a ray opaque by accumulating optical depth, ``alpha = 1 - exp(-tau)`` with
``tau = int sigma ds / voxel``; its silhouette is ``tau > ln 2`` along each pixel's whole ray. A surface at
one density level cannot follow that: where the density rises steeply it sits too far out (colours slide
across the surface at oblique views), and where it is low but deep (hair) it cuts off what rays see as
opaque. The field is the largest of three parts, each ``>= 1`` inside:

* **depth from outside**: ``tau_min(x) / ln 2``, the smallest optical depth from the grid's border to ``x``
  along the six axis directions (midpoint rule): the point where an axis-aligned ray turns half opaque,
  the volume's median depth, where its colour is seen.
* **fuzz**: ``min(sigma(x) / FUZZ_DENSITY, T(x) / FUZZ_DEPTH)``, where ``T(x)`` is the smallest optical
  depth of the whole *line* through ``x`` over ``LINE_DIRECTIONS``: density of at least ``FUZZ_DENSITY``
  per voxel whose every line is at least 75% opaque (``FUZZ_DEPTH = 2 ln 2``) makes the silhouette too.
* **sparse fuzz** (hair that side rays see as opaque and front rays see through), away from the core
  (the nodes where the depth from outside reaches ``ln 2``, grown by ``CORE_MARGIN`` nodes):
  ``min(sigma(x) / SPARSE_DENSITY, median_d T_d(x) / ln 2)`` over the directions ``d`` whose line
  through ``x`` misses the core. A view whose ray through ``x`` misses the body sees ``x`` inside the
  silhouette when ``T_d(x) > ln 2``, and a mesh can only be in or out for all views at once: in, when most
  of the views that it decides see it so. Lines through the core are the core's to decide.

Measured in ``docs/benchmarks/texture_export.md`` (the surface's IoU against the volume's silhouette and
the colours' PSNR); ``FUZZ_DENSITY`` and ``FUZZ_DEPTH`` were chosen on three held-out photo-path avatars
(long_hair, seated, man_in_suit), not on the benchmark's; ``SPARSE_DENSITY`` and ``CORE_MARGIN`` on those
three and the benchmark's three together (``docs/benchmarks/history.md``: every one of the six gained).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
from scipy.ndimage import binary_dilation

HALF_OPAQUE = math.log(2.0)  # optical depth at which a ray is half opaque
FUZZ_DENSITY = 0.2  # density per voxel below which matter is never meshed by itself
FUZZ_DEPTH = 2 * HALF_OPAQUE  # a fuzz node's lines must all reach this optical depth (75% opaque)
SPARSE_DENSITY = 0.1  # density per voxel below which sparse fuzz is never meshed
CORE_MARGIN = 1  # nodes the core grows by: lines that pass this close to it are the core's to decide


def line_directions(horizontal: int = 8) -> np.ndarray:
    """Unit line directions (y up): ``horizontal`` over 180 degrees, the vertical, and a ring at 45 degrees
    elevation with ``horizontal`` azimuths over 360 degrees (a line and its reverse are the same line)."""
    azimuth = np.arange(horizontal) * math.pi / horizontal
    ring = np.arange(horizontal) * 2 * math.pi / horizontal
    e = math.pi / 4
    dirs = [np.stack([np.sin(azimuth), np.zeros(horizontal), np.cos(azimuth)], 1), np.array([[0.0, 1.0, 0.0]])]
    dirs.append(np.stack([np.sin(ring) * math.cos(e), np.full(horizontal, math.sin(e)), np.cos(ring) * math.cos(e)], 1))
    return np.concatenate(dirs)


LINE_DIRECTIONS = line_directions()


def depth_from_outside(volume: np.ndarray, steps: tuple[float, float, float]) -> np.ndarray:
    """Per node, the smallest optical depth from a face of the grid along +-x, +-y, +-z:
    ``cumsum(sigma) * step - sigma * step / 2`` (midpoint rule); ``volume`` holds density per voxel, ``steps``
    the node spacing in voxels."""
    best = np.full(volume.shape, np.inf)
    for axis in range(3):
        half = 0.5 * volume * steps[axis]
        best = np.minimum(best, np.cumsum(volume, axis=axis) * steps[axis] - half)
        best = np.minimum(best, np.flip(np.cumsum(np.flip(volume, axis), axis=axis), axis) * steps[axis] - half)
    return best


def bilinear_corners(fu: np.ndarray, fv: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The four (column, row, weight) corners of bilinear interpolation at continuous bin coordinates, one at
    a time (a full grid's corners together would hold twelve arrays)."""
    iu, iv = np.floor(fu).astype(np.int64), np.floor(fv).astype(np.int64)
    du, dv = fu - iu, fv - iv
    del fu, fv  # a whole grid's coordinates: not kept while the corners are used
    yield iu, iv, (1 - du) * (1 - dv)
    yield iu + 1, iv, du * (1 - dv)
    yield iu, iv + 1, (1 - du) * dv
    yield iu + 1, iv + 1, du * dv


def line_depths(
    volume: np.ndarray, spacing: tuple[float, float, float], voxel: float, directions: np.ndarray, at: np.ndarray
) -> Iterator[np.ndarray]:
    """Per direction, the optical depth of the whole line through each node of the flat index ``at``.

    The density is projected onto the plane across the direction (bilinear splats into bins of the mean
    spacing ``b``: a node carries ``sigma * sx sy sz / (b^2 voxel)``) and read back at the nodes.
    """
    spacing = np.asarray(spacing, dtype=np.float64)
    b = float(spacing.mean())
    occupied = np.nonzero(volume > 1e-4)
    if not occupied[0].size:
        for _ in directions:
            yield np.zeros(len(at))
        return
    mass = volume[occupied] * float(np.prod(spacing)) / (b * b * voxel)
    points = np.stack(occupied, 1) * spacing
    nodes = np.stack(np.unravel_index(at, volume.shape), 1) * spacing
    for d in directions:
        d = d / np.linalg.norm(d)
        u_axis = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        u_axis /= np.linalg.norm(u_axis)
        v_axis = np.cross(d, u_axis)
        pu, pv = points @ u_axis / b, points @ v_axis / b
        u0, v0 = math.floor(pu.min()) - 1, math.floor(pv.min()) - 1
        width, height = math.ceil(pu.max() - u0) + 3, math.ceil(pv.max() - v0) + 3
        image = np.zeros(width * height)
        for iu, iv, w in bilinear_corners(pu - u0, pv - v0):
            image += np.bincount(iu * height + iv, weights=mass * w, minlength=width * height)
        image = image.reshape(width, height)
        fu, fv = nodes @ u_axis / b - u0, nodes @ v_axis / b - v0
        inside = (fu >= 0) & (fv >= 0) & (fu < width - 1) & (fv < height - 1)
        values = np.zeros(len(at))  # nodes outside the projection: their lines miss the density
        for iu, iv, w in bilinear_corners(fu[inside], fv[inside]):
            values[inside] += image[iu, iv] * w
        yield values


def sparse_fuzz(
    volume: np.ndarray,
    grown_core: np.ndarray,
    at: np.ndarray,
    depths: np.ndarray,
    spacing: tuple[float, float, float],
    voxel: float,
) -> np.ndarray:
    """Per node, the sparse fuzz term (see the module docstring): ``grown_core`` (bool, per node) the core grown
    by ``CORE_MARGIN``, ``at`` the flat index of the nodes outside it that hold density, ``depths`` (directions,
    nodes of ``at``) their lines' optical depths over ``LINE_DIRECTIONS``; 0 elsewhere."""
    out = np.zeros(volume.size)
    if not len(at):
        return out.reshape(volume.shape)
    depths = depths.copy()
    core_nodes = grown_core.astype(np.float64)  # a line's "depth" through it: how many core nodes it meets
    for k, met in enumerate(line_depths(core_nodes, spacing, voxel, LINE_DIRECTIONS, at)):
        depths[k, met >= 0.5] = np.nan  # this line passes through the core: not this term's to decide
    median = np.zeros(len(at))
    some = ~np.isnan(depths).all(0)  # nodes with at least one line that misses the core
    if some.any():
        median[some] = np.nanmedian(depths[:, some], axis=0)
    out[at] = np.minimum(volume.reshape(-1)[at] / SPARSE_DENSITY, median / HALF_OPAQUE)
    return out.reshape(volume.shape)


def surface_field(volume: np.ndarray, spacing: tuple[float, float, float], voxel: float) -> np.ndarray:
    """The field whose level 1 is the surface (see the module docstring): ``volume`` is density per voxel
    (foreground included) at nodes ``spacing`` metres apart, ``voxel`` the density's voxel in metres."""
    steps = tuple(float(s) / voxel for s in spacing)
    median_depth = depth_from_outside(volume, steps) / HALF_OPAQUE
    grown_core = binary_dilation(median_depth >= 1, iterations=CORE_MARGIN)
    sparse_at = np.flatnonzero(~grown_core & (volume > 1e-4))
    # One pass over the lines serves both fuzz terms: the smallest depth per node, all depths at sparse_at.
    smallest = np.full(volume.size, np.inf)
    sparse_depths = np.empty((len(LINE_DIRECTIONS), len(sparse_at)), dtype=np.float32)
    for k, depth in enumerate(line_depths(volume, spacing, voxel, LINE_DIRECTIONS, np.arange(volume.size))):
        smallest = np.minimum(smallest, depth)
        sparse_depths[k] = depth[sparse_at]
    fuzz = np.minimum(volume / FUZZ_DENSITY, smallest.reshape(volume.shape) / FUZZ_DEPTH)
    sparse = sparse_fuzz(volume, grown_core, sparse_at, sparse_depths, spacing, voxel)
    return np.maximum(np.maximum(median_depth, fuzz), sparse)
