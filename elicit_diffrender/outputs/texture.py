"""A UV atlas for an exported mesh and a colour texture baked from the avatar's radiance field.

* Atlas: xatlas charts the mesh and packs the charts into one square atlas (``ATLAS_PADDING`` texels
  between charts). Vertices on a chart seam are split: ``vertex_map`` names the mesh vertex each atlas
  vertex copies, so positions and skin weights carry over unchanged.
* UV convention (glTF's): ``u`` to the right, ``v`` down, ``(0, 0)`` the image's top-left corner; texel
  ``(row, col)`` has its centre at ``((col + 0.5) / size, (row + 0.5) / size)``.
* Rasterisation: every texel centre inside a triangle in UV space gets that triangle's barycentric
  coordinates ``(b0, b1, b2)``, hence a canonical surface point ``p = sum b_i x_i`` and normal
  ``n = normalize(sum b_i n_i)``.
* Bake (:class:`Bake`; ``"ray"``, the default): the colour the volume renderer composites along a short
  ray that crosses the surface against its normal, from ``p + L n`` to ``p - L n`` (``L = reach`` voxels,
  ``RAY_SAMPLES`` samples), with the renderer's ``alpha_k = fg_k (1 - exp(-sigma_k delta / voxel))``,
  ``T_k = prod_{j<k} (1 - alpha_j)``, ``c = sum T_k alpha_k c_k / sum T_k alpha_k``. A texel whose ray
  stays nearly transparent (``sum < MIN_RAY_ALPHA``) takes the point look-up. ``"point"``: the colour
  grid at ``p`` (what the vertex colours sample, per texel).
* Seams (``fill``): texels outside every chart take the colour of the nearest texel inside one (a
  Euclidean distance transform), so bilinear filtering and mip-maps at a chart's border read that
  chart's colours, not the empty background.

``docs/benchmarks/texture_export.md`` measures these choices against the volume render.

Colours stay as the field holds them, sRGB-encoded, which is what glTF's ``baseColorTexture`` expects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from ..model.avatar import Avatar, sample_grid

ATLAS_PADDING = 4  # texels between charts in the packed atlas
RAY_SAMPLES = 16
MIN_RAY_ALPHA = 0.05
CHUNK = 1 << 16  # texels per look-up batch (the motion weights have one channel per bone)


@dataclass(frozen=True)
class Bake:
    """How texels take their colour: ``kind`` "ray" or "point", the ray's half length ``reach`` in voxels,
    and whether to ``fill`` the texels between charts."""

    kind: str = "ray"
    reach: float = 2.0
    fill: bool = True

    def __post_init__(self) -> None:
        if self.kind not in ("ray", "point"):
            raise ValueError(f"bake kind must be 'ray' or 'point', got {self.kind!r}")


DEFAULT_BAKE = Bake()


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


@torch.no_grad()
def surface_colors(avatar: Avatar, points: np.ndarray, normals: np.ndarray, bake: Bake = DEFAULT_BAKE) -> np.ndarray:
    """(N, 3) sRGB colours in [0, 1] of canonical surface ``points`` with outward unit ``normals`` (see the
    module docstring for the two kinds of ``bake``)."""
    f = avatar.field
    box = f.box.detach().cpu()
    color = f.color.detach().permute(3, 0, 1, 2).cpu()
    density = f.activated_density()[None].detach().cpu()
    weights = avatar.motion_weights().detach().cpu()
    weights_box = avatar.motion_weights.box.cpu()
    voxel = float(f.voxel_size)
    reach = bake.reach * voxel
    t = torch.linspace(reach, -reach, RAY_SAMPLES)  # from outside in
    delta = 2 * reach / (RAY_SAMPLES - 1)
    out = np.empty((len(points), 3), dtype=np.float32)
    for s in range(0, len(points), CHUNK):
        p = torch.as_tensor(points[s : s + CHUNK], dtype=torch.float32)
        point_rgb = torch.sigmoid(sample_grid(color, box, p))
        if bake.kind == "point":
            out[s : s + CHUNK] = point_rgb.numpy()
            continue
        n = torch.as_tensor(normals[s : s + CHUNK], dtype=torch.float32)
        x = (p[:, None, :] + t[None, :, None] * n[:, None, :]).reshape(-1, 3)
        sigma = sample_grid(density, box, x)[:, 0]
        fg = avatar.foreground(sample_grid(weights, weights_box, x).sum(1))
        alpha = (fg * (1 - torch.exp(-sigma * delta / voxel))).reshape(len(p), RAY_SAMPLES)
        trans = torch.cumprod(torch.cat([torch.ones(len(p), 1), 1 - alpha[:, :-1]], 1), 1)
        w = trans * alpha
        rgb = (w[..., None] * torch.sigmoid(sample_grid(color, box, x)).reshape(len(p), RAY_SAMPLES, 3)).sum(1)
        total = w.sum(1, keepdim=True)
        ray_rgb = rgb / total.clamp(min=1e-6)
        out[s : s + CHUNK] = torch.where(total >= MIN_RAY_ALPHA, ray_rgb, point_rgb).numpy()
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
