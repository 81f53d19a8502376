"""A textured 3D person (a scan, or any clothed mesh) as a synthetic subject's person: read, fitted, skinned.

The mesh is a Wavefront OBJ with its MTL file and textures (``f v/vt`` faces, one ``usemtl`` per material,
``map_Kd`` images), in metres with +y up and the person facing +z, as a 3D scan or a character exported from
Blender is. Every material's texture goes into one atlas (a grid of equal tiles, each framed by a copy of its
own border so that bilinear look-ups never mix two tiles) and the UVs move into their tile.

Anny is fitted to the person (:func:`~elicit_diffrender.body.fitting.fit_anny_to_views`): MediaPipe's landmarks
in renders from several cameras, triangulated, and the renders' silhouettes. Every mesh vertex then takes the
skinning weights of its nearest body vertices (inverse-distance blend of ``BIND_NEIGHBOURS``) and is unposed
to Anny's rest pose, so the person can be posed like a synthetic one: in the fitted pose it is the mesh as read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..body.anny_model import AnnyBody
from ..core.cameras import Camera
from ..core.checks import read_image
from ..core.errors import ElicitError
from ..data.mesh_render import MeshAppearance, MeshRenderer
from .synth import bone_motion, motion_after_input, render_subject, skin_to_pose

ATLAS_TILE = 1024  # pixels per material tile in the texture atlas (textures are resampled to it)
ATLAS_BORDER = 4  # pixels of each tile's frame, copied from the texture's own border
BIND_NEIGHBOURS = 4  # body vertices whose skinning weights a mesh vertex blends
BIND_BONES = 8  # bones kept per mesh vertex
FIT_VIEWS = 8  # cameras of the body fit, evenly round the person
MAX_MESH_VERTICES = 2_000_000


class ScanError(ElicitError):
    """A mesh that cannot be read or fitted."""


@dataclass
class TexturedMesh:
    vertices: np.ndarray  # (V, 3) one per distinct (position, uv) corner pair
    faces: np.ndarray  # (F, 3)
    uvs: np.ndarray  # (V, 2) in the atlas, v down from the top row (Mitsuba's bitmap layout)
    texture: np.ndarray  # (H, W, 3) the atlas, values as stored in the images (0..1)


def _floats(parts: list[str], n: int, where: str) -> list[float]:
    try:
        values = [float(x) for x in parts[:n]]
    except ValueError:
        raise ScanError(f"{where}: expected {n} numbers, got {' '.join(parts)!r}") from None
    if len(values) < n or not all(math.isfinite(v) for v in values):
        raise ScanError(f"{where}: expected {n} finite numbers, got {' '.join(parts)!r}")
    return values


def read_mtl(path: Path) -> dict[str, Path]:
    """Material name -> its ``map_Kd`` image, resolved inside the MTL file's folder."""
    textures: dict[str, Path] = {}
    current = None
    for line in path.read_text(errors="replace").splitlines():
        parts = line.strip().split(maxsplit=1)
        if len(parts) == 2 and parts[0] == "newmtl":
            current = parts[1].strip()
        elif len(parts) == 2 and parts[0] == "map_Kd" and current is not None:
            name = parts[1].split()[-1]
            image = (path.parent / name).resolve()
            if path.parent.resolve() not in image.parents:
                raise ScanError(f"{path}: texture {name!r} of material {current!r} lies outside the MTL's folder")
            textures[current] = image
    return textures


def read_obj(path: str | Path) -> TexturedMesh:
    """A textured OBJ (with its MTL and images) as one mesh with an atlas texture."""
    path = Path(path)
    if not path.is_file():
        raise ScanError(f"{path}: mesh file not found")
    positions, texcoords, corners, materials = [], [], [], []
    mtl: dict[str, Path] = {}
    current = ""
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        where = f"{path}:{number}"
        if parts[0] == "v":
            positions.append(_floats(parts[1:], 3, where))
        elif parts[0] == "vt":
            texcoords.append(_floats(parts[1:], 2, where))
        elif parts[0] == "f":
            refs = []
            for ref in parts[1:]:
                fields = ref.split("/")
                try:
                    v, t = int(fields[0]), int(fields[1])
                except (ValueError, IndexError):
                    raise ScanError(f"{where}: faces must be 'v/vt' references, got {ref!r}") from None
                refs.append((v - 1 if v > 0 else len(positions) + v, t - 1 if t > 0 else len(texcoords) + t))
            for k in range(1, len(refs) - 1):  # a fan of triangles
                corners.append((refs[0], refs[k], refs[k + 1]))
                materials.append(current)
        elif parts[0] == "usemtl":
            current = " ".join(parts[1:])
        elif parts[0] == "mtllib":
            mtl_path = (path.parent / " ".join(parts[1:])).resolve()
            if path.parent.resolve() not in mtl_path.parents or not mtl_path.is_file():
                raise ScanError(f"{where}: material library {' '.join(parts[1:])!r} not found beside the mesh")
            mtl.update(read_mtl(mtl_path))
        if len(positions) > MAX_MESH_VERTICES:
            raise ScanError(f"{path}: more than {MAX_MESH_VERTICES} vertices")
    if not corners:
        raise ScanError(f"{path}: no faces")
    pos, tex = np.asarray(positions, dtype=np.float64), np.asarray(texcoords, dtype=np.float64)
    refs = np.asarray(corners, dtype=np.int64)  # (F, 3, 2)
    if (
        (refs[..., 0] < 0).any()
        or (refs[..., 0] >= len(pos)).any()
        or (refs[..., 1] < 0).any()
        or (refs[..., 1] >= len(tex)).any()
    ):
        raise ScanError(f"{path}: a face refers to a vertex or texture coordinate that does not exist")
    names = sorted(set(materials))
    missing = [n for n in names if n not in mtl]
    if missing:
        raise ScanError(f"{path}: materials without a texture (map_Kd): {missing}")
    atlas = texture_atlas([mtl[n] for n in names])
    face_tile = np.array([names.index(m) for m in materials])
    # One render vertex per distinct (position, texture coordinate, tile) corner.
    keys = np.stack([refs[..., 0], refs[..., 1], np.repeat(face_tile[:, None], 3, 1)], -1).reshape(-1, 3)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    uv = np.mod(tex[uniq[:, 1]], 1.0)
    return TexturedMesh(pos[uniq[:, 0]], inverse.reshape(-1, 3), atlas_uvs(uv, uniq[:, 2], atlas.shape[0]), atlas)


def texture_atlas(images: list[Path]) -> np.ndarray:
    """The images resampled into the tiles of a square grid, row by row (image ``k`` in tile ``k``), every tile
    framed by ``ATLAS_BORDER`` pixels of its own border."""
    from PIL import Image

    n = math.ceil(math.sqrt(len(images)))
    inner = ATLAS_TILE - 2 * ATLAS_BORDER
    atlas = np.zeros((n * ATLAS_TILE, n * ATLAS_TILE, 3), dtype=np.float32)
    for k, path in enumerate(images):
        rgb, _ = read_image(path, "texture", error=ScanError)
        small = (
            np.asarray(
                Image.fromarray((rgb * 255).round().astype(np.uint8)).resize((inner, inner), Image.BILINEAR),
                dtype=np.float32,
            )
            / 255.0
        )
        r, c = divmod(k, n)
        framed = np.pad(small, ((ATLAS_BORDER, ATLAS_BORDER), (ATLAS_BORDER, ATLAS_BORDER), (0, 0)), mode="edge")
        atlas[r * ATLAS_TILE : (r + 1) * ATLAS_TILE, c * ATLAS_TILE : (c + 1) * ATLAS_TILE] = framed
    return atlas


def atlas_uvs(uv: np.ndarray, tile: np.ndarray, atlas_size: int) -> np.ndarray:
    """OBJ texture coordinates (v up) of a tile's image as coordinates of that tile in the atlas, in Mitsuba's
    bitmap layout (v down from the top row)."""
    n = atlas_size // ATLAS_TILE
    rows, cols = np.divmod(tile, n)
    inner = (ATLAS_TILE - 2 * ATLAS_BORDER) / ATLAS_TILE
    x = (cols + ATLAS_BORDER / ATLAS_TILE + uv[:, 0] * inner) / n
    y_down = (rows + ATLAS_BORDER / ATLAS_TILE + (1.0 - uv[:, 1]) * inner) / n
    return np.stack([x, y_down], 1)


def centred(vertices: np.ndarray) -> np.ndarray:
    """The mesh moved so that its bounding box is centred on the origin (where the shipped rigs look)."""
    return vertices - (vertices.min(0) + vertices.max(0)) / 2


def landmarks_in_views(renderer: MeshRenderer, vertices: np.ndarray, cameras: list[Camera]) -> tuple[list, list]:
    """Masks and MediaPipe's landmarks of the mesh rendered (flat colour) over grey from ``cameras``."""
    import tempfile

    from ..core.io import write_image
    from .mediapipe_bridge import detect_pose

    out = renderer.render(vertices, cameras, ("color", "mask"), spp=4)
    masks, landmarks = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k, cam in enumerate(cameras):
            mask = out["mask"][k] > 0.5
            image = np.where(mask[..., None], np.clip(out["color"][k], 0.0, 1.0), 0.5)
            found = detect_pose(write_image(Path(tmp) / f"{cam.name}.png", image)).landmarks
            masks.append(mask)
            landmarks.append(np.zeros((33, 3)) if found is None else found)
    return masks, landmarks


@dataclass
class ScanPerson:
    """A textured mesh skinned to a fitted Anny body; the same posing interface as a synthetic person."""

    body: AnnyBody
    rest: np.ndarray  # (V, 3) the mesh unposed to the body's rest pose
    skin_idx: np.ndarray  # (V, BIND_BONES)
    skin_w: np.ndarray  # (V, BIND_BONES)
    renderer: MeshRenderer
    texture: np.ndarray
    fitted: dict  # pose, global_orient, transl of the mesh as read, and the fit's report

    def clothed_vertices(self, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray) -> np.ndarray:
        """The mesh's vertices with the body posed (linear blend skinning of the bound weights)."""
        return skin_to_pose(self.body, self.rest, self.skin_idx, self.skin_w, pose, orient, transl)


def bind_to_body(
    body: AnnyBody, vertices: np.ndarray, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Skinning weights for mesh ``vertices`` that lie on the body posed at (pose, orient, transl), and the
    vertices unposed to the rest pose: (V, 3) rest positions, (V, BIND_BONES) bone indices and weights."""
    from scipy.spatial import cKDTree

    posed = body.pose(pose, orient, transl)
    dist, near = cKDTree(posed.vertices).query(vertices, k=BIND_NEIGHBOURS)
    share = 1.0 / np.maximum(dist, 1e-4)
    share /= share.sum(1, keepdims=True)
    dense = np.zeros((len(vertices), body.n_joints))
    for j in range(BIND_NEIGHBOURS):
        np.add.at(dense, (np.arange(len(vertices))[:, None], body.skin_idx[near[:, j]]),
                  body.skin_w[near[:, j]] * share[:, j : j + 1])  # fmt: skip
    idx = np.argsort(-dense, axis=1)[:, :BIND_BONES]
    w = np.take_along_axis(dense, idx, 1)
    w /= w.sum(1, keepdims=True)
    mats = bone_motion(body, pose, orient, transl).numpy()
    blend = np.einsum("vk,vkij->vij", w, mats[idx])  # (V, 4, 4) rest -> posed per vertex
    rest = np.einsum("vij,vj->vi", np.linalg.inv(blend), np.concatenate([vertices, np.ones((len(vertices), 1))], 1))
    return rest[:, :3], idx, w


def make_scan_person(path: str | Path, n_views: int = FIT_VIEWS, size: int = 512) -> ScanPerson:
    """Read a textured OBJ, fit Anny to it from ``n_views`` renders and bind the mesh to the body."""
    from ..body.fitting import fit_anny_to_views
    from ..data.rigs import ring_cameras

    mesh = read_obj(path)
    vertices = centred(mesh.vertices)
    renderer = MeshRenderer(mesh.faces, MeshAppearance(uvs=mesh.uvs, texture=mesh.texture))
    cameras = ring_cameras(n=n_views, focal=650.0 * size / 512.0, width=size, height=size)
    masks, landmarks = landmarks_in_views(renderer, vertices, cameras)
    try:
        fit = fit_anny_to_views([(c.K, c.R, c.T) for c in cameras], masks, landmarks)
    except ValueError as exc:
        raise ScanError(f"{path}: the body fit failed ({exc})") from None
    body = AnnyBody({k: round(v, 4) for k, v in fit["phenotype"].items()})  # as the subject will store it
    rest, idx, w = bind_to_body(body, vertices, fit["pose"], fit["global_orient"], fit["transl"])
    fitted = {k: fit[k] for k in ("pose", "global_orient", "transl", "report")}
    return ScanPerson(body, rest, idx, w, renderer, mesh.texture, fitted)


def synthesize_scan(
    mesh: str | Path,
    out: str | Path,
    motion_name: str = "walk_in_place",
    size: int = 512,
    spp: int = 32,
    n_cameras: int = 23,
    force: bool = False,
) -> Path:
    """``elicit synth --mesh``: a subject of a textured 3D person, written as a whole like a synthetic one: the
    mesh as read at the input frame (from the ring), then the mesh posed by the motion (from the input camera)."""
    import time

    from ..core.io import folder_in_place

    start = time.perf_counter()
    person = make_scan_person(mesh, size=size)
    fitted = person.fitted
    motion = motion_after_input(person.body, (fitted["pose"], fitted["global_orient"], fitted["transl"]), motion_name)
    spec = {"model": "anny", "phenotype": person.body.phenotype}
    extra = {"mesh": str(Path(mesh).resolve()), "motion": motion_name, "body_fit": fitted["report"]}
    with folder_in_place(out, force) as tmp:
        render_subject(tmp, person, spec, motion, size, spp, n_cameras, f"synth {Path(mesh).name}", extra, start)
    return Path(out)
