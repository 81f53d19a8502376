"""An avatar as an animated glTF binary (``.glb``): mesh, colours, skeleton, skin weights and a motion.

* Geometry: marching cubes (scikit-image) at level 1 of :func:`.surface.surface_field` of the canonical
  density times the motion weights' foreground likelihood (density outside every bone's reach is not
  meshed): the depth where an axis-aligned ray turns half opaque, plus low-density fuzz (hair) that
  makes the volume's silhouette. Only components with at least ``MIN_COMPONENT`` of the largest one's
  faces are kept (floaters go); ``faces`` decimates (quadric); vertices within 10 micrometres are merged
  and the triangles left without area dropped.
* Appearance (default): a UV atlas and a ``texture_size``-square texture baked from the radiance field
  (:mod:`.texture`), stored as a PNG in the GLB: one material whose ``baseColorTexture`` reads
  ``TEXCOORD_0``, linear filtering with mip-maps, clamped at the edges. Vertices on chart seams are
  duplicated (same position and skin weights). With ``vertex_colors``: the canonical colour grid sampled
  at the vertices, as glTF vertex colours (``COLOR_0``, linear as glTF wants them: the grid holds the
  photos' sRGB values, converted), and no texture.
* Rig: one glTF joint per bone of the avatar's reduced skeleton, at its canonical (rest) transform,
  with inverse bind matrices; per vertex the 4 largest motion weights, normalised (``JOINTS_0``,
  ``WEIGHTS_0``). glTF skinning, ``v' = sum_j w_j J_j(t) IBM_j v``, is then the avatar's forward LBS,
  since ``J_j(t)`` is the bone's world transform at time ``t`` and ``IBM_j`` its canonical inverse.
* Motion: per frame and joint, the local (parent-relative) rotation and translation, as one glTF
  animation with linear samplers; a viewer plays it at the motion's frame rate.

Axes: glTF is y-up, right-handed, metres, like the project's world frame, so no conversion is needed.
"""

from __future__ import annotations

import json
import math
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ..body.template import vertex_normals
from ..core.errors import ElicitError
from ..core.io import atomic_write
from ..data.motions import Motion, load_motion
from ..model.avatar import Avatar, sample_grid
from ..model.field import grid_points
from .surface import surface_field
from .texture import DEFAULT_BAKE, Bake, bake_texture, uv_atlas

MIN_COMPONENT = 0.02  # keep mesh components with at least this share of the largest one's faces
MAX_JOINTS_PER_VERTEX = 4
MIN_FACE_AREA = 1e-10  # square metres; smaller triangles are dropped
MERGE_DIGITS = 5  # vertices equal to 10 micrometres are one


DEFAULT_TEXTURE_SIZE = 1024


class ExportError(ElicitError):
    """The avatar cannot be exported (nothing opaque, a motion that does not fit the body)."""


@dataclass
class AvatarMesh:
    """The canonical surface of an avatar, with its colours and skinning (and, once textured, its atlas)."""

    vertices: np.ndarray  # (V, 3) float32, canonical space, metres
    faces: np.ndarray  # (F, 3) int
    colors: np.ndarray  # (V, 3) float32 in [0, 1], linear (glTF's COLOR_0)
    joints: np.ndarray  # (V, 4) uint16 bone indices
    weights: np.ndarray  # (V, 4) float32, rows sum to 1
    uvs: np.ndarray | None = None  # (V, 2) float32, glTF's TEXCOORD_0 (v down)
    texture: np.ndarray | None = None  # (S, S, 3) uint8, sRGB


def textured_mesh(
    avatar: Avatar, mesh: AvatarMesh, size: int = DEFAULT_TEXTURE_SIZE, bake: Bake = DEFAULT_BAKE
) -> AvatarMesh:
    """``mesh`` charted into a UV atlas, with a ``size``-square texture baked from ``avatar`` (see :mod:`.texture`)."""
    atlas = uv_atlas(mesh.vertices, mesh.faces, size)
    keep = atlas.vertex_map
    normals = vertex_normals(mesh.vertices.astype(np.float64), mesh.faces)[keep]
    vertices = mesh.vertices[keep]
    texture = bake_texture(avatar, vertices, normals, atlas.faces, atlas.uvs, size, bake)
    return AvatarMesh(
        vertices, atlas.faces, mesh.colors[keep], mesh.joints[keep], mesh.weights[keep], atlas.uvs, texture
    )


def png_bytes(image: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG file bytes."""
    import io

    import imageio.v3 as iio

    out = io.BytesIO()
    iio.imwrite(out, image, extension=".png")
    return out.getvalue()


def canonical_mesh(avatar: Avatar, resolution: float | None = None, faces: int | None = None) -> AvatarMesh:
    """The avatar's canonical surface (see the module docstring). ``resolution``: marching-cubes voxel in
    metres (default: the avatar's grid); ``faces``: decimate to about this many faces."""
    import trimesh
    from skimage.measure import marching_cubes

    f = avatar.field
    box = f.box.detach().cpu().double()
    voxel = float(resolution or f.voxel_size)
    shape = tuple(max(2, int(math.ceil(float(e) / voxel)) + 1) for e in (box[1] - box[0]))
    nodes = grid_points(box, shape).reshape(-1, 3).float()
    grids = avatar.canonical_lookup()
    with torch.no_grad():
        sigma, fg = grids.density(nodes)
    volume = (sigma * fg).reshape(shape).double().numpy()
    spacing = tuple(float(box[1, a] - box[0, a]) / (shape[a] - 1) for a in range(3))
    field = surface_field(volume, spacing, float(f.voxel_size))
    if field.max() <= 1.0:
        raise ExportError("the avatar has no opaque region to mesh (no ray through it turns half opaque)")
    verts, tris, _, _ = marching_cubes(field, level=1.0, spacing=spacing)
    mesh = trimesh.Trimesh(verts + box[0].numpy(), tris[:, ::-1], process=True)
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        largest = max(len(p.faces) for p in parts)
        mesh = trimesh.util.concatenate([p for p in parts if len(p.faces) >= MIN_COMPONENT * largest])
    if faces is not None and len(mesh.faces) > faces:
        mesh = mesh.simplify_quadric_decimation(face_count=int(faces))
    # Slivers: marching cubes puts vertices micrometres apart where the surface grazes a grid node; they are
    # merged, and the triangles left with no area (a renderer's NaN normals) dropped.
    mesh.merge_vertices(digits_vertex=MERGE_DIGITS)
    stored = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)[mesh.faces]  # as the GLB holds them
    area = np.linalg.norm(np.cross(stored[:, 1] - stored[:, 0], stored[:, 2] - stored[:, 0]), axis=1) / 2
    mesh.update_faces(area > MIN_FACE_AREA)
    mesh.remove_unreferenced_vertices()
    v = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    with torch.no_grad():
        srgb = grids.srgb(v).numpy()
        w = sample_grid(avatar.motion_weights().detach().cpu(), avatar.motion_weights.box.cpu(), v).numpy()
    colors = srgb_to_linear(srgb)
    top = np.argsort(-w, axis=1)[:, :MAX_JOINTS_PER_VERTEX]
    tw = np.take_along_axis(w, top, 1)
    tw = tw / np.maximum(tw.sum(1, keepdims=True), 1e-8)
    return AvatarMesh(
        np.asarray(mesh.vertices, dtype=np.float32),
        np.asarray(mesh.faces, dtype=np.int64),
        colors.astype(np.float32),
        top.astype(np.uint16),
        tw.astype(np.float32),
    )


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] (the photos' and the renders' colours) to linear ones (glTF's ``COLOR_0``)."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """The inverse of :func:`srgb_to_linear`: linear values in [0, 1] to sRGB-encoded ones."""
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.maximum(c, 0) ** (1 / 2.4) - 0.055)


def local_transforms(world: np.ndarray, parents: list[int]) -> np.ndarray:
    """(..., B, 4, 4) parent-relative transforms of (..., B, 4, 4) world transforms."""
    local = world.copy()
    for b, p in enumerate(parents):
        if p >= 0:
            local[..., b, :, :] = np.linalg.inv(world[..., p, :, :]) @ world[..., b, :, :]
    return local


def _quaternions(mats: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w quaternions of (N, 4, 4) rigid matrices, sign-continuous along N."""
    q = Rotation.from_matrix(mats[:, :3, :3]).as_quat()
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q


class _Buffer:
    """The GLB binary chunk, with its buffer views and accessors."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None, bounds: bool = False) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        raw = np.ascontiguousarray(array).tobytes()
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target is not None:
            view["target"] = target
        self.data += raw
        self.views.append(view)
        acc = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": int(array.shape[0]),
            "type": kind,
        }
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            acc["min"] = flat.min(0).tolist()
            acc["max"] = flat.max(0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


FLOAT, UINT16, UINT32 = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LINEAR, LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE = 9729, 9987, 33071


def glb_document(avatar: Avatar, mesh: AvatarMesh, motion: Motion | None, name: str = "avatar") -> tuple[dict, bytes]:
    """The glTF JSON and binary chunk of an avatar mesh with its skeleton and (optionally) a motion."""
    buf = _Buffer()
    rest = avatar.canonical_bones.detach().cpu().double().numpy()  # (B, 4, 4) world, canonical pose
    parents = list(avatar.parents)
    n_bones = len(parents)
    attributes = {"POSITION": buf.add(mesh.vertices.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER, bounds=True)}
    if mesh.texture is None:
        attributes["COLOR_0"] = buf.add(mesh.colors.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER)
    else:
        attributes["TEXCOORD_0"] = buf.add(mesh.uvs.astype(np.float32), FLOAT, "VEC2", ARRAY_BUFFER)
    jnt = buf.add(mesh.joints.astype(np.uint16), UINT16, "VEC4", ARRAY_BUFFER)
    wgt = buf.add(mesh.weights.astype(np.float32), FLOAT, "VEC4", ARRAY_BUFFER)
    idx = buf.add(mesh.faces.astype(np.uint32).reshape(-1), UINT32, "SCALAR", ELEMENT_ARRAY_BUFFER)
    ibm = np.linalg.inv(rest).astype(np.float32)
    ibm_acc = buf.add(np.ascontiguousarray(ibm.transpose(0, 2, 1)).reshape(n_bones, 16), FLOAT, "MAT4")

    local_rest = local_transforms(rest, parents)
    nodes: list[dict] = [{"name": name, "mesh": 0, "skin": 0}]
    rest_rotations = Rotation.from_matrix(local_rest[:, :3, :3]).as_quat()
    for b in range(n_bones):
        node = {
            "name": avatar.reduced_joints[b],
            "translation": local_rest[b, :3, 3].tolist(),
            "rotation": rest_rotations[b].tolist(),
        }
        children = [1 + c for c, p in enumerate(parents) if p == b]
        if children:
            node["children"] = children
        nodes.append(node)
    roots = [1 + b for b, p in enumerate(parents) if p < 0]
    doc: dict = {
        "asset": {"version": "2.0", "generator": "elicit-diffrender"},
        "scene": 0,
        "scenes": [{"nodes": [0, *roots]}],
        "nodes": nodes,
        "meshes": [
            {
                "name": name,
                "primitives": [
                    {
                        "attributes": {**attributes, "JOINTS_0": jnt, "WEIGHTS_0": wgt},
                        "indices": idx,
                        "material": 0,
                    }
                ],
            }
        ],
        "materials": [
            {
                "name": "vertex colour" if mesh.texture is None else "baked texture",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [1, 1, 1, 1],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
                "doubleSided": True,
            }
        ],
        "skins": [{"joints": [1 + b for b in range(n_bones)], "inverseBindMatrices": ibm_acc, "skeleton": roots[0]}],
    }
    if mesh.texture is not None:
        png = png_bytes(mesh.texture)
        while len(buf.data) % 4:
            buf.data.append(0)
        buf.views.append({"buffer": 0, "byteOffset": len(buf.data), "byteLength": len(png)})
        buf.data += png
        doc["images"] = [{"name": "base colour", "bufferView": len(buf.views) - 1, "mimeType": "image/png"}]
        doc["samplers"] = [
            {"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": CLAMP_TO_EDGE, "wrapT": CLAMP_TO_EDGE}
        ]
        doc["textures"] = [{"sampler": 0, "source": 0}]
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0, "texCoord": 0}
    if motion is not None:
        world = np.stack(
            [avatar.bone_transforms(*motion.frame(i)).detach().cpu().double().numpy() for i in range(len(motion))]
        )
        local = local_transforms(world, parents)  # (T, B, 4, 4)
        times = (np.arange(len(motion), dtype=np.float32) / np.float32(motion.fps)).astype(np.float32)
        t_acc = buf.add(times, FLOAT, "SCALAR", bounds=True)
        channels, samplers = [], []
        for b in range(n_bones):
            trans = local[:, b, :3, 3].astype(np.float32)
            rot = _quaternions(local[:, b]).astype(np.float32)
            for path, values, kind in (("translation", trans, "VEC3"), ("rotation", rot, "VEC4")):
                samplers.append({"input": t_acc, "output": buf.add(values, FLOAT, kind), "interpolation": "LINEAR"})
                channels.append({"sampler": len(samplers) - 1, "target": {"node": 1 + b, "path": path}})
        doc["animations"] = [{"name": motion.name or "motion", "channels": channels, "samplers": samplers}]
    while len(buf.data) % 4:
        buf.data.append(0)
    doc["buffers"] = [{"byteLength": len(buf.data)}]
    doc["bufferViews"] = buf.views
    doc["accessors"] = buf.accessors
    return doc, bytes(buf.data)


def glb_bytes(doc: dict, binary: bytes) -> bytes:
    """A GLB container: header, JSON chunk (space-padded), BIN chunk (zero-padded)."""
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (
        struct.pack("<III", 0x46546C67, 2, total)
        + struct.pack("<II", len(js), 0x4E4F534A)
        + js
        + struct.pack("<II", len(binary), 0x004E4942)
        + binary
    )


def export_glb(
    avatar: Avatar,
    out: str | Path,
    motion: Motion | None = None,
    resolution: float | None = None,
    faces: int | None = None,
    texture_size: int | None = DEFAULT_TEXTURE_SIZE,
) -> dict:
    """Write ``out`` (a .glb) and return a summary: vertices, faces, joints, frames, appearance, bytes, seconds.
    ``texture_size`` None: vertex colours instead of a baked texture."""
    start = time.perf_counter()
    if Path(out).suffix.lower() != ".glb":
        raise ExportError(f"{out}: the output must be a .glb file")
    if texture_size is not None and texture_size < 1:
        raise ExportError(f"the texture size must be a positive number of pixels, got {texture_size}")
    mesh = canonical_mesh(avatar, resolution, faces)
    if texture_size is not None:
        mesh = textured_mesh(avatar, mesh, texture_size)
    doc, binary = glb_document(avatar, mesh, motion)
    data = glb_bytes(doc, binary)
    path = atomic_write(Path(out), lambda tmp: tmp.write_bytes(data))
    return {
        "path": str(path),
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "joints": len(avatar.parents),
        "frames": 0 if motion is None else len(motion),
        "appearance": "vertex colours (COLOR_0)"
        if texture_size is None
        else f"{texture_size}x{texture_size} baked texture (PNG, TEXCOORD_0)",
        "bytes": len(data),
        "seconds": time.perf_counter() - start,
    }


def export_run(
    run: str | Path,
    out: str | Path,
    motion: str = "walk_in_place",
    resolution: float | None = None,
    faces: int | None = None,
    texture_size: int | None = DEFAULT_TEXTURE_SIZE,
) -> dict:
    """:func:`export_glb` of a run folder's (or avatar file's) avatar, with a motion by name or file
    (``"none"``: no animation); the explicit-texture baseline has no field to mesh and is refused."""
    from ..model.load import load_avatar

    avatar = load_avatar(run)
    if not isinstance(avatar, Avatar):
        raise ExportError(f"{run}: the explicit-texture baseline has no radiance field to export")
    chosen = None if motion == "none" else load_motion(motion, avatar.body)
    return export_glb(avatar, out, chosen, resolution, faces, texture_size)
