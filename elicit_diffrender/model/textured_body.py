"""The paper's "body mesh with explicit texture" baseline: per-vertex colours fitted to the input view only.

Every body vertex visible from the input camera takes the input image's colour where it projects
(the least-squares optimum of the input-view reconstruction for a per-vertex texture); hidden
vertices take the colour of the nearest visible vertex of the same body part. The result animates
with the body model's own skinning and renders through Mitsuba (no light transport).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..body import BodyModel, load_body
from ..core.cameras import Camera
from ..core.errors import ElicitError
from ..core.io import write_tensors
from ..data.mesh_render import MeshAppearance, MeshRenderer
from ..data.subject import Subject

FORMAT = "elicit-textured-body/2"  # a safetensors file, like elicit-avatar/2
LEGACY_FORMAT = "elicit-textured-body/1"  # avatar.pt of earlier versions


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample an (H, W, C) image at pixel coordinates (N, 2) (centres at +0.5), clamped to the border."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


class TexturedBody:
    """The body mesh with per-vertex colours; same rendering interface as :class:`Avatar`."""

    def __init__(self, body_spec: dict, vertex_colors: np.ndarray, body: BodyModel | None = None) -> None:
        self.body_spec = dict(body_spec)
        self.vertex_colors = np.asarray(vertex_colors, dtype=np.float32)
        self._body = body
        self._renderer: MeshRenderer | None = None

    @property
    def body(self) -> BodyModel:
        if self._body is None:
            self._body = load_body(self.body_spec)
        return self._body

    @classmethod
    def fit(cls, subject: Subject) -> TexturedBody:
        body = subject.body
        cam = subject.cameras[subject.input_camera]
        image = subject.image(subject.input_camera, subject.input_frame)
        mask = subject.mask(subject.input_camera, subject.input_frame)
        posed = body.pose(*subject.motion.frame(subject.input_index))
        depth = MeshRenderer(body.faces).render(posed.vertices, [cam], ("depth",))["depth"][0]
        uv, z = cam.project(posed.vertices)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height) & (z > 0)
        px = np.clip(uv[:, 0].astype(int), 0, cam.width - 1)
        py = np.clip(uv[:, 1].astype(int), 0, cam.height - 1)
        surface = depth[py, px]
        visible = inside & (surface > 0) & (z <= surface + 0.01) & mask[py, px]
        colors = np.zeros((posed.vertices.shape[0], 3), dtype=np.float32)
        colors[visible] = bilinear(image, uv[visible])
        parts = body.vertex_parts()
        rest = body.rest_vertices
        fallback = colors[visible].mean(0) if visible.any() else np.full(3, 0.5)
        for p in np.unique(parts):
            hidden = (parts == p) & ~visible
            seen = (parts == p) & visible
            if not hidden.any():
                continue
            if seen.any():
                _, idx = cKDTree(rest[seen]).query(rest[hidden])
                colors[hidden] = colors[seen][idx]
            else:
                colors[hidden] = fallback
        return cls(subject.body_spec, colors, body)

    def render_pose(
        self, camera: Camera, pose: np.ndarray, orient: np.ndarray, transl: np.ndarray, n_samples: int = 0
    ) -> dict[str, np.ndarray]:
        """(H, W, 3) colour on black and (H, W) alpha of the posed textured body."""
        del n_samples  # a mesh has no ray samples
        if self._renderer is None:
            self._renderer = MeshRenderer(self.body.faces, MeshAppearance(vertex_colors=self.vertex_colors))
        out = self._renderer.render(self.body.pose(pose, orient, transl).vertices, [camera], ("color", "alpha"), spp=4)
        alpha = out["alpha"][0]
        return {"rgb": out["color"][0] * alpha[..., None], "alpha": alpha}

    def save(self, path: str | Path) -> Path:
        data = {"format": FORMAT, "body": self.body_spec, "vertex_colors": torch.as_tensor(self.vertex_colors)}
        return write_tensors(path, data)

    @classmethod
    def from_state(cls, data: dict) -> TexturedBody:
        if data.get("format") not in (FORMAT, LEGACY_FORMAT):
            raise ElicitError(f"not an {FORMAT} file")
        colors = data.get("vertex_colors")
        if not isinstance(data.get("body"), dict) or not isinstance(colors, torch.Tensor) or colors.ndim != 2:
            raise ElicitError(f"an {data['format']} file needs 'body' and (V, 3) 'vertex_colors'")
        return cls(data["body"], colors.numpy())
