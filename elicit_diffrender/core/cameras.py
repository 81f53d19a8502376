"""OpenCV pinhole cameras: projection, rays, crops and look-at construction.

Convention: ``x_cam = R @ x_world + T`` and ``pixel = K @ x_cam / z``; x right, y down, z forward;
world units are metres. Pixel (column i, row j) covers [i, i+1) x [j, j+1), so its centre is at
(i + 0.5, j + 0.5), as in Mitsuba and most NeRF code.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class Camera:
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (3, 3)
    T: np.ndarray  # (3,)
    width: int
    height: int
    name: str = ""
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.T = np.asarray(self.T, dtype=np.float64).reshape(3)
        self.width, self.height = int(self.width), int(self.height)

    @property
    def center(self) -> np.ndarray:
        """Camera position in world coordinates."""
        return -self.R.T @ self.T

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.T

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixel coordinates (N, 2) and camera depth z (N,)."""
        cam = self.world_to_camera(points)
        z = cam[:, 2]
        uv = cam @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return uv[:, :2] / z[:, None], z

    def pixels(self, points: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (N, 3) -> the (N, 2) integer pixel (column, row) each falls in, camera depth z (N,), and
        (N,) bool: in front of the camera and inside an image of ``shape`` (H, W) there."""
        uv, z = self.project(points)
        px = np.floor(uv).astype(int)
        h, w = shape[:2]
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h) & (z > 0)
        return px, z, inside

    def pixel_grid(self) -> np.ndarray:
        """Centres of all pixels, row-major, (H*W, 2)."""
        j, i = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        return np.stack([i.ravel() + 0.5, j.ravel() + 0.5], axis=1)

    def rays(
        self, pixels: np.ndarray | None = None, device: torch.device | str = "cpu", dtype=torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space ray origins and unit directions through pixel coordinates (default: all centres)."""
        px = self.pixel_grid() if pixels is None else np.asarray(pixels, dtype=np.float64)
        homo = np.concatenate([px, np.ones((px.shape[0], 1))], axis=1)
        d_cam = homo @ np.linalg.inv(self.K).T
        d_world = d_cam @ self.R  # R^T d for row vectors
        d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
        origins = np.broadcast_to(self.center, d_world.shape)
        return (
            torch.as_tensor(np.ascontiguousarray(origins), dtype=dtype, device=device),
            torch.as_tensor(d_world, dtype=dtype, device=device),
        )

    def crop(self, x0: float, y0: float, w: float, h: float, out_w: int, out_h: int | None = None) -> Camera:
        """The camera that renders the window [x0, x0+w) x [y0, y0+h) of this image at out_w x out_h."""
        out_h = out_w if out_h is None else out_h
        sx, sy = out_w / w, out_h / h
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        K[0, 2] = (self.K[0, 2] - x0) * sx
        K[1, 2] = (self.K[1, 2] - y0) * sy
        return Camera(K, self.R.copy(), self.T.copy(), out_w, out_h, f"{self.name}[crop]")

    def scaled(self, factor: float) -> Camera:
        """The same camera with the image resized by ``factor``."""
        w, h = round(self.width * factor), round(self.height * factor)
        return self.crop(0.0, 0.0, self.width, self.height, w, h)

    def to_dict(self) -> dict:
        return {
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "T": self.T.tolist(),
            "width": self.width,
            "height": self.height,
        }


def look_at(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray, focal: float, width: int, height: int, name: str = ""
) -> Camera:
    """A camera at ``eye`` looking at ``target`` with image-up along ``up``; principal point centred."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # image right = forward x up (y points down in the image)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the up vector is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K, R, -R @ eye, width, height, name)
