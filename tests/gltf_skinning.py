"""A small, independent glTF 2.0 reader for the tests: a GLB's mesh, posed by its skin and animation."""

from __future__ import annotations

import numpy as np
import pygltflib

COMPONENTS = {5126: np.float32, 5123: np.uint16, 5125: np.uint32, 5121: np.uint8}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    n = WIDTH[acc.type]
    dtype = COMPONENTS[acc.componentType]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    data = np.frombuffer(blob, dtype=dtype, count=acc.count * n, offset=start)
    return data.reshape(acc.count, n) if n > 1 else data


def quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def surface_colors(path) -> dict:
    """The first primitive's colours as stored: ``{"vertex_colors": (V, 3) linear}`` (``COLOR_0``) or
    ``{"uvs": (V, 2), "texture": (H, W, 3) sRGB in [0, 1]}`` (``TEXCOORD_0`` and its material's PNG)."""
    import io

    import imageio.v3 as iio

    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    if prim.attributes.COLOR_0 is not None:
        return {"vertex_colors": accessor(gltf, blob, prim.attributes.COLOR_0)}
    texture = gltf.textures[gltf.materials[prim.material].pbrMetallicRoughness.baseColorTexture.index]
    view = gltf.bufferViews[gltf.images[texture.source].bufferView]
    png = blob[view.byteOffset : view.byteOffset + view.byteLength]
    image = iio.imread(io.BytesIO(png), extension=".png")[..., :3].astype(np.float32) / 255
    return {"uvs": accessor(gltf, blob, prim.attributes.TEXCOORD_0), "texture": image}


def posed_mesh(path, frame: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (posed by glTF skinning at animation keyframe ``frame``, or at rest with None) and faces."""
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    verts = accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
    faces = accessor(gltf, blob, prim.indices).reshape(-1, 3)
    joints = accessor(gltf, blob, prim.attributes.JOINTS_0).astype(np.int64)
    weights = accessor(gltf, blob, prim.attributes.WEIGHTS_0).astype(np.float64)
    skin = gltf.skins[0]
    ibm = accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
    trs = {
        i: (np.array(n.translation or [0, 0, 0], float), np.array(n.rotation or [0, 0, 0, 1], float))
        for i, n in enumerate(gltf.nodes)
    }
    if frame is not None:
        anim = gltf.animations[0]
        for ch in anim.channels:
            s = anim.samplers[ch.sampler]
            value = accessor(gltf, blob, s.output)[frame].astype(float)
            t, r = trs[ch.target.node]
            trs[ch.target.node] = (value, r) if ch.target.path == "translation" else (t, value)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}

    def world(node: int) -> np.ndarray:
        t, r = trs[node]
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = quat_matrix(r), t
        return m if node not in parent else world(parent[node]) @ m

    mats = np.stack([world(j) @ ibm[k] for k, j in enumerate(skin.joints)])  # (J, 4, 4)
    homog = np.concatenate([verts, np.ones((len(verts), 1))], 1)
    per_joint = np.einsum("vkij,vj->vki", mats[joints], homog)[..., :3]
    return (weights[..., None] * per_joint).sum(1), faces


def silhouette(camera, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(H, W) bool coverage of the mesh's triangles seen by ``camera``."""
    from skimage.draw import polygon

    uv, z = camera.project(verts)
    mask = np.zeros((camera.height, camera.width), bool)
    for f in faces:
        if (z[f] > 0).all():
            rr, cc = polygon(uv[f, 1] - 0.5, uv[f, 0] - 0.5, mask.shape)
            mask[rr, cc] = True
    return mask


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """glTF's linear vertex colours to sRGB, written here rather than taken from the exporter, which it checks."""
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.maximum(c, 0) ** (1 / 2.4) - 0.055)
