"""A UV atlas for an exported mesh and a colour texture baked from the avatar's radiance field.

* Atlas: xatlas charts the mesh and packs the charts into one square atlas (``ATLAS_PADDING`` texels
  between charts). Vertices on a chart seam are split: ``vertex_map`` names the mesh vertex each atlas
  vertex copies, so positions and skin weights carry over unchanged.
* UV convention (glTF's): ``u`` to the right, ``v`` down, ``(0, 0)`` the image's top-left corner; texel
  ``(row, col)`` has its centre at ``((col + 0.5) / size, (row + 0.5) / size)``.
* Rasterisation: every texel centre inside a triangle in UV space gets that triangle's barycentric
  coordinates ``(b0, b1, b2)``, hence a canonical surface point ``p = sum b_i x_i`` and normal
  ``n = normalize(sum b_i n_i)``.
* Bake (:class:`Bake`): a texel's colour is what the volume renderer composites along short rays that
  cross the surface at ``p``: each ray runs from ``p + L d`` to ``p - L d`` (``L = reach`` voxels,
  ``RAY_SAMPLES`` samples) with the renderer's ``alpha_k = fg_k (1 - exp(-sigma_k delta / voxel))``,
  ``T_k = prod_{j<k} (1 - alpha_j)``, ``c(d) = sum T_k alpha_k c_k / sum T_k alpha_k``, and its density:
  ``sigma_k = activate(trilinear(raw)(x_k))``, the raw grid looked up first (looking up activated nodes
  puts more density between nodes, so rays stop short of where the renderer's do).

  - ``"views"`` (the default): the mean over ``VIEW_DIRECTIONS`` (evenly spread over the sphere) that face
    the surface, ``c = sum w_d c(d) / sum w_d`` with ``w_d = (n . d)^VIEW_POWER``: the colour that views
    from all around see at ``p`` (a camera sees a texel over an area ``~ n . d``; the square favours the
    views that see it squarely, whose composite is sharpest).
  - ``"normal"``: one ray along the normal, ``d = n``.
  - ``"point"``: the colour grid at ``p`` (what the vertex colours sample, per texel).

  A ray that stays nearly transparent (``sum T_k alpha_k < MIN_RAY_ALPHA``) counts for nothing; a texel with
  no opaque ray takes the point look-up.
* Seams (``fill``): texels outside every chart take the colour of the nearest texel inside one (a
  Euclidean distance transform), so bilinear filtering and mip-maps at a chart's border read that
  chart's colours, not the empty background.

``docs/benchmarks/texture_export.md`` measures these choices against the volume render.

Colours stay as the field holds them, sRGB-encoded, which is what glTF's ``baseColorTexture`` expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from ..model.avatar import Avatar, CanonicalLookup

ATLAS_PADDING = 4  # texels between charts in the packed atlas
RAY_SAMPLES = 16
MIN_RAY_ALPHA = 0.05
VIEW_COUNT = 26  # directions of the "views" bake, evenly spread over the sphere
VIEW_POWER = 2.0  # weight of a direction: (n . d) to this power, for directions that face the surface
MIN_FACING = 0.05  # n . d below this: the direction sees the texel edge-on and is left out
BAKE_KINDS = ("views", "normal", "point")
CHUNK = 1 << 16  # texels per look-up batch


@dataclass(frozen=True)
class Bake:
    """How texels take their colour: ``kind`` (one of ``BAKE_KINDS``, see the module docstring), the rays'
    half length ``reach`` in voxels, and whether to ``fill`` the texels between charts."""

    kind: str = "views"
    reach: float = 2.0
    fill: bool = True

    def __post_init__(self) -> None:
        if self.kind not in BAKE_KINDS:
            raise ValueError(f"bake kind must be one of {BAKE_KINDS}, got {self.kind!r}")


DEFAULT_BAKE = Bake()


def sphere_directions(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice, y up)."""
    i = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * i / count)
    azimuth = math.pi * (1 + math.sqrt(5)) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], 1)


VIEW_DIRECTIONS = sphere_directions(VIEW_COUNT)


@dataclass
class UVAtlas:
    """A chart layout of a mesh: per atlas vertex the mesh vertex it copies and its UV; atlas faces."""

    vertex_map: np.ndarray  # (V', ) int64 mesh vertex of each atlas vertex
    faces: np.ndarray  # (F, 3) int64 atlas-vertex indices (the mesh's faces, in order)
    uvs: np.ndarray  # (V', 2) float32 in [0, 1], glTF convention (v down)


@dataclass
class TexelSamples:
    """The texels that lie inside a chart: where they are in the image and on the mesh."""

    rows: np.ndarray  # (N,) int64
    cols: np.ndarray  # (N,) int64
    faces: np.ndarray  # (N,) int64 atlas face
    barycentric: np.ndarray  # (N, 3) float64


def uv_atlas(vertices: np.ndarray, faces: np.ndarray, size: int) -> UVAtlas:
    """Chart and pack ``faces`` over ``vertices`` with xatlas for a ``size`` x ``size`` texture."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = ATLAS_PADDING
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    vertex_map, atlas_faces, uvs = atlas[0]
    return UVAtlas(vertex_map.astype(np.int64), atlas_faces.astype(np.int64), uvs.astype(np.float32))


def rasterize_uv(uvs: np.ndarray, faces: np.ndarray, size: int) -> TexelSamples:
    """Every texel of a ``size`` x ``size`` image whose centre lies inside a triangle of ``faces`` in UV space."""
    px = uvs.astype(np.float64) * size  # texel units: x = u size (columns), y = v size (rows)
    tri = px[faces]  # (F, 3, 2)
    lo = np.clip(np.ceil(tri.min(1) - 0.5), 0, size - 1).astype(np.int64)
    hi = np.clip(np.floor(tri.max(1) - 0.5), 0, size - 1).astype(np.int64)
    extent = np.maximum(hi - lo + 1, 0)
    count = extent[:, 0] * extent[:, 1]
    face = np.repeat(np.arange(len(faces)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    cols = lo[face, 0] + local % extent[face, 0]
    rows = lo[face, 1] + local // extent[face, 0]
    p = np.stack([cols + 0.5, rows + 0.5], 1)
    a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    safe = np.where(np.abs(area) > 1e-12, area, 1.0)
    w0 = ((b[:, 0] - p[:, 0]) * (c[:, 1] - p[:, 1]) - (b[:, 1] - p[:, 1]) * (c[:, 0] - p[:, 0])) / safe
    w1 = ((c[:, 0] - p[:, 0]) * (a[:, 1] - p[:, 1]) - (c[:, 1] - p[:, 1]) * (a[:, 0] - p[:, 0])) / safe
    bary = np.stack([w0, w1, 1.0 - w0 - w1], 1)
    inside = (np.abs(area) > 1e-12) & (bary >= -1e-9).all(1)
    return TexelSamples(rows[inside], cols[inside], face[inside], bary[inside])


def _composite(grids: CanonicalLookup, voxel: float, points: torch.Tensor, dirs: torch.Tensor, reach: float):
    """Colour ``c(d)`` and opacity ``sum T_k alpha_k`` of the short rays through ``points`` along ``dirs``."""
    t = torch.linspace(reach, -reach, RAY_SAMPLES)  # from outside in
    delta = 2 * reach / (RAY_SAMPLES - 1)
    x = (points[:, None, :] + t[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    sigma, fg = grids.density(x)
    alpha = (fg * (1 - torch.exp(-sigma * delta / voxel))).reshape(len(points), RAY_SAMPLES)
    trans = torch.cumprod(torch.cat([torch.ones(len(points), 1), 1 - alpha[:, :-1]], 1), 1)
    w = trans * alpha
    rgb = grids.srgb(x).reshape(len(points), RAY_SAMPLES, 3)
    total = w.sum(1, keepdim=True)
    return (w[..., None] * rgb).sum(1) / total.clamp(min=1e-6), total


@torch.no_grad()
def surface_colors(avatar: Avatar, points: np.ndarray, normals: np.ndarray, bake: Bake = DEFAULT_BAKE) -> np.ndarray:
    """(N, 3) sRGB colours in [0, 1] of canonical surface ``points`` with outward unit ``normals`` (see the
    module docstring for the kinds of ``bake``)."""
    grids = avatar.canonical_lookup()
    voxel = float(avatar.field.voxel_size)
    reach = bake.reach * voxel
    directions = torch.as_tensor(VIEW_DIRECTIONS, dtype=torch.float32)
    out = np.empty((len(points), 3), dtype=np.float32)
    for s in range(0, len(points), CHUNK):
        p = torch.as_tensor(points[s : s + CHUNK], dtype=torch.float32)
        point_rgb = grids.srgb(p)
        if bake.kind == "point":
            out[s : s + CHUNK] = point_rgb.numpy()
            continue
        n = torch.as_tensor(normals[s : s + CHUNK], dtype=torch.float32)
        if bake.kind == "normal":
            rgb, total = _composite(grids, voxel, p, n, reach)
            out[s : s + CHUNK] = torch.where(total >= MIN_RAY_ALPHA, rgb, point_rgb).numpy()
            continue
        acc, weight = torch.zeros(len(p), 3), torch.zeros(len(p), 1)
        for d in directions:
            facing = n @ d
            rows = torch.nonzero(facing > MIN_FACING)[:, 0]
            if not len(rows):
                continue
            rgb, total = _composite(grids, voxel, p[rows], d.expand(len(rows), 3), reach)
            w = facing[rows, None] ** VIEW_POWER * (total >= MIN_RAY_ALPHA)
            acc.index_add_(0, rows, w * rgb)
            weight.index_add_(0, rows, w)
        out[s : s + CHUNK] = torch.where(weight > 0, acc / weight.clamp(min=1e-12), point_rgb).numpy()
    return out


def fill_seams(image: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """``image`` with every texel outside ``covered`` (H, W) set to the nearest covered texel's colour."""
    if covered.all() or not covered.any():
        return image
    _, (rows, cols) = distance_transform_edt(~covered, return_indices=True)
    return image[rows, cols]


def bake_texture(
    avatar: Avatar,
    vertices: np.ndarray,
    normals: np.ndarray,
    faces: np.ndarray,
    uvs: np.ndarray,
    size: int,
    bake: Bake = DEFAULT_BAKE,
) -> np.ndarray:
    """A (size, size, 3) uint8 sRGB texture of the avatar's colour over an atlas: canonical ``vertices``, unit
    ``normals`` and ``uvs`` per atlas vertex, ``faces`` over them."""
    texels = rasterize_uv(uvs, faces, size)
    corners = faces[texels.faces]  # (N, 3)
    points = np.einsum("nk,nkc->nc", texels.barycentric, vertices[corners].astype(np.float64))
    texel_normals = np.einsum("nk,nkc->nc", texels.barycentric, normals[corners].astype(np.float64))
    texel_normals /= np.maximum(np.linalg.norm(texel_normals, axis=1, keepdims=True), 1e-12)
    image = np.zeros((size, size, 3), dtype=np.float32)
    covered = np.zeros((size, size), dtype=bool)
    image[texels.rows, texels.cols] = surface_colors(avatar, points, texel_normals, bake)
    covered[texels.rows, texels.cols] = True
    if bake.fill:
        image = fill_seams(image, covered)
    return np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)
