"""Mitsuba 3 renders of a posed triangle mesh from OpenCV cameras, computing only the channels asked for.

Channels:
    ``color``   surface colour (vertex colours or a UV texture), no light transport
    ``mask``    hard silhouette, 1 where a camera ray hits the mesh
    ``alpha``   anti-aliased coverage
    ``labels``  exact integer per-face labels (-1 = background), from ``prim_index`` at pixel centres
    ``depth``   camera-space z of the first hit (0 = background)
    ``shaded``  path-traced colour under an ambient sky and a key light (synthetic photos, reference)

All cameras of one call must share an image size; they render in a single launch through Mitsuba's
``batch`` sensor. ``labels``/``mask``/``depth`` use one sample at each pixel centre with a box filter,
so labels are exact; ``color``/``alpha``/``shaded`` use ``spp`` jittered samples per pixel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..core.cameras import Camera
from ..core.errors import ElicitError
from ..core.mitsuba_variant import mitsuba
from .rigs import sensor_params

if TYPE_CHECKING:
    import torch

CHANNELS = ("color", "mask", "alpha", "labels", "depth", "shaded")


class RenderError(ElicitError):
    """Mitsuba cannot run here, or a render request is malformed."""


@dataclass
class MeshAppearance:
    """How the mesh is coloured: per-vertex colours or a UV texture (with per-vertex UVs)."""

    vertex_colors: np.ndarray | None = None  # (V, 3) in [0, 1]
    uvs: np.ndarray | None = None  # (V, 2), v down: v = 0 samples the texture's top row
    texture: np.ndarray | None = None  # (H, W, 3) in [0, 1]


class MeshRenderer:
    """Renders one mesh topology in any pose from any cameras.

    Args:
        faces: (F, 3) triangle vertex indices.
        appearance: colours for the ``color`` and ``shaded`` channels.
        face_labels: (F,) integer label per face for the ``labels`` channel.
    """

    def __init__(
        self, faces: np.ndarray, appearance: MeshAppearance | None = None, face_labels: np.ndarray | None = None
    ) -> None:
        self.faces = np.ascontiguousarray(faces, dtype=np.uint32)
        self.n_vertices = int(self.faces.max()) + 1
        self.appearance = appearance or MeshAppearance()
        self.face_labels = None if face_labels is None else np.asarray(face_labels, dtype=np.int32)
        if self.face_labels is not None and self.face_labels.shape != (self.faces.shape[0],):
            raise RenderError(f"face_labels must be ({self.faces.shape[0]},), got {self.face_labels.shape}")
        app = self.appearance
        if app.vertex_colors is not None and app.vertex_colors.shape != (self.n_vertices, 3):
            raise RenderError(f"vertex_colors must be ({self.n_vertices}, 3), got {app.vertex_colors.shape}")
        if app.texture is not None and (app.uvs is None or app.uvs.shape != (self.n_vertices, 2)):
            raise RenderError(f"a texture needs per-vertex uvs of shape ({self.n_vertices}, 2)")
        self._meshes: dict[bool, tuple] = {}

    def _reflectance(self) -> dict:
        mi = mitsuba()
        app = self.appearance
        if app.texture is not None:
            bitmap = mi.Bitmap(np.ascontiguousarray(app.texture, dtype=np.float32))
            return {"type": "bitmap", "bitmap": bitmap, "filter_type": "bilinear", "raw": True}
        if app.vertex_colors is not None:
            return {"type": "mesh_attribute", "name": "vertex_color"}
        return {"type": "rgb", "value": [0.7, 0.7, 0.7]}

    def _posed_mesh(self, vertices: np.ndarray, emissive: bool = False):
        """The Mitsuba mesh (built once per kind) moved to ``vertices``.

        The diffuse mesh serves the exact channels and ``shaded``; the emissive one carries the
        surface colour as its radiance, so ``color`` is one direct-visibility pass (path, depth 1)
        with exact coverage in alpha and no light transport at all.
        """
        mi = mitsuba()
        if emissive not in self._meshes:
            app = self.appearance
            has_uv = app.uvs is not None
            props = mi.Properties()
            if emissive:
                props["emitter"] = mi.load_dict({"type": "area", "radiance": self._reflectance()})
            mesh = mi.Mesh("body", self.n_vertices, self.faces.shape[0], props, has_vertex_texcoords=has_uv)
            params = mi.traverse(mesh)
            params["faces"] = mi.UInt32(self.faces.ravel())
            if has_uv:
                params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(app.uvs, dtype=np.float32).ravel())
            if app.vertex_colors is not None:
                colors = np.ascontiguousarray(app.vertex_colors, dtype=np.float32).ravel()
                mesh.add_attribute("vertex_color", 3, mi.Float(colors))
            reflectance = {"type": "rgb", "value": [0.0, 0.0, 0.0]} if emissive else self._reflectance()
            # Two-sided: a folded garment (a synthetic skirt) shows its inside lit, not black.
            diffuse = {"type": "diffuse", "reflectance": reflectance}
            mesh.set_bsdf(mi.load_dict({"type": "twosided", "material": diffuse}))
            self._meshes[emissive] = (mesh, params)
        mesh, params = self._meshes[emissive]
        params["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices, dtype=np.float32).ravel())
        params.update()
        return mesh

    def _render(self, mesh, cameras: Sequence[Camera], integrator: dict, spp: int, exact: bool) -> np.ndarray:
        """One batch-sensor launch; returns (N, H, W, C): RGBA (when rendered) then the AOVs."""
        mi = mitsuba()
        width, height = cameras[0].width, cameras[0].height
        sensors = {}
        for k, cam in enumerate(cameras):
            p = sensor_params(cam)
            sensors[f"s{k:03d}"] = {
                "type": "perspective",
                "fov": p["fov"],
                "fov_axis": "x",
                "principal_point_offset_x": p["principal_point_offset_x"],
                "principal_point_offset_y": p["principal_point_offset_y"],
                "near_clip": 1e-3,
                "to_world": mi.ScalarTransform4f(p["to_world"].tolist()),
            }
        film = {
            "type": "hdrfilm",
            "width": width * len(cameras),
            "height": height,
            "pixel_format": "rgba",
            "rfilter": {"type": "box"},
        }
        sampler = (
            {"type": "stratified", "sample_count": 1, "jitter": False}
            if exact
            else {"type": "independent", "sample_count": spp}
        )
        scene = {
            "type": "scene",
            "integrator": integrator,
            "body": mesh,
            "sensor": {"type": "batch", **sensors, "film": film, "sampler": sampler},
        }
        if integrator["type"] == "path" and integrator.get("max_depth", 1) > 1:
            scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.55}}
            scene["key"] = {
                "type": "directional",
                "direction": [-0.4, -0.7, -0.6],
                "irradiance": {"type": "rgb", "value": 1.6},
            }
        img = np.array(mi.render(mi.load_dict(scene), spp=1 if exact else spp))
        return img.reshape(height, len(cameras), width, -1).transpose(1, 0, 2, 3)  # the film's tiles, as a view

    def render(
        self, vertices: np.ndarray, cameras: Sequence[Camera], channels: Sequence[str], spp: int = 8
    ) -> dict[str, np.ndarray]:
        """Render the mesh posed at ``vertices`` (V, 3) from ``cameras``; returns (N, H, W[, C]) arrays."""
        unknown = set(channels) - set(CHANNELS)
        if unknown:
            raise RenderError(f"unknown channels {sorted(unknown)}; choose from {CHANNELS}")
        if not cameras:
            raise RenderError("no cameras to render")
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) != 1:
            raise RenderError(f"all cameras of one render must share an image size, got {sorted(sizes)}")
        vertices = np.asarray(vertices)
        if vertices.shape != (self.n_vertices, 3):
            raise RenderError(f"vertices must be ({self.n_vertices}, 3), got {vertices.shape}")
        if "labels" in channels and self.face_labels is None:
            raise RenderError("the 'labels' channel needs face_labels")
        out: dict[str, np.ndarray] = {}
        exact = [c for c in ("labels", "mask", "depth") if c in channels]
        if exact:
            aovs = "dd:depth" + (",pi:prim_index" if "labels" in exact else "")
            img = self._render(self._posed_mesh(vertices), cameras, {"type": "aov", "aovs": aovs}, 1, exact=True)
            dist = img[..., 0]  # an aov integrator without an inner one returns just its AOVs
            hit = dist > 0
            if "mask" in channels:
                out["mask"] = hit.astype(np.float32)
            if "depth" in channels:
                out["depth"] = self._z_depth(dist, cameras)
            if "labels" in channels:
                prim = np.clip(np.rint(img[..., 1]).astype(np.int64), 0, len(self.face_labels) - 1)
                out["labels"] = np.where(hit, self.face_labels[prim], -1).astype(np.int16)
        if "color" in channels or "alpha" in channels:
            mesh = self._posed_mesh(vertices, emissive="color" in channels)
            img = self._render(mesh, cameras, {"type": "path", "max_depth": 1}, spp, exact=False)
            alpha = np.clip(img[..., 3], 0.0, 1.0)
            if "color" in channels:
                color = np.divide(img[..., :3], np.maximum(alpha, 1e-6)[..., None])
                color[alpha == 0] = 0.0  # no coverage, no colour
                out["color"] = color
            if "alpha" in channels:
                out["alpha"] = alpha
        if "shaded" in channels:
            integrator = {"type": "path", "max_depth": 3, "hide_emitters": True}
            img = self._render(self._posed_mesh(vertices), cameras, integrator, spp, exact=False)
            out["shaded"] = np.clip(img[..., :3], 0.0, None)
            out.setdefault("alpha", np.clip(img[..., 3], 0.0, 1.0))
        return out

    @staticmethod
    def _z_depth(dist: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
        """Ray distance -> camera z: z = t * d_z for each pixel's unit ray."""
        out = np.zeros_like(dist)
        for k, cam in enumerate(cameras):
            px = cam.pixel_grid()
            homo = np.concatenate([px, np.ones((px.shape[0], 1))], 1) @ np.linalg.inv(cam.K).T
            dz = (1.0 / np.linalg.norm(homo, axis=1)).reshape(cam.height, cam.width)
            out[k] = dist[k] * dz
        return out.astype(np.float32)


class DifferentiableSilhouette:
    """A mesh's anti-aliased silhouette through one camera, differentiable with respect to the vertices.

    Mitsuba's ``direct_projective`` integrator renders the mesh as a unit emitter (no shading, no light
    transport; triangles are seen from their front, as a closed body's are) and samples the visibility
    discontinuities at its outline, so the gradient reaches vertices on the silhouette;
    ``torch`` tensors go in and come out through ``dr.wrap``.
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, camera: Camera, spp: int = 4) -> None:
        import torch

        mi = mitsuba()
        import drjit as dr

        props = mi.Properties()
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": 1.0}})
        mesh = mi.Mesh("body", n_vertices, faces.shape[0], props)
        mesh_params = mi.traverse(mesh)
        mesh_params["faces"] = mi.UInt32(np.ascontiguousarray(faces, dtype=np.uint32).ravel())
        mesh_params.update()
        p = sensor_params(camera)
        self.scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "direct_projective", "sppi": 0},  # no indirect discontinuities here
                "body": mesh,
                "sensor": {
                    "type": "perspective",
                    "fov": p["fov"],
                    "fov_axis": "x",
                    "principal_point_offset_x": p["principal_point_offset_x"],
                    "principal_point_offset_y": p["principal_point_offset_y"],
                    "near_clip": 1e-3,
                    "to_world": mi.ScalarTransform4f(p["to_world"].tolist()),
                    "film": {
                        "type": "hdrfilm",
                        "width": camera.width,
                        "height": camera.height,
                        "pixel_format": "rgb",
                        "rfilter": {"type": "box"},
                        "sample_border": True,  # the outline may move across the image border
                    },
                    "sampler": {"type": "independent", "sample_count": spp},
                },
            }
        )
        self.params = mi.traverse(self.scene)
        self.spp = spp
        self.calls = 0
        params, scene = self.params, self.scene

        @dr.wrap(source="torch", target="drjit")
        def render(flat_vertices, seed: int):
            params["body.vertex_positions"] = flat_vertices.array
            params.update()
            return mi.render(scene, params, spp=spp, seed=seed)[..., 0]

        self._render = render
        self._torch = torch

    def __call__(self, vertices: torch.Tensor) -> torch.Tensor:
        """(V, 3) torch vertices in world space -> (H, W) torch coverage in [0, 1]."""
        self.calls += 1
        flat = vertices.to(self._torch.float32).reshape(-1).contiguous()
        return self._render(flat, self.calls)
