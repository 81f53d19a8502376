"""``elicit eval``: novel-view and novel-pose metrics in the Neural Body protocol.

* novel view: the input frame from every camera except the input one;
* novel pose: the input camera at every other frame.

PSNR is taken over the pixels inside the projected 3D box of the posed body (padded by
``BOX_PADDING`` metres on every side: the convex hull of its 8 projected corners); SSIM
(scikit-image) over that region's bounding rectangle; LPIPS(VGG) when its weights are available,
otherwise ``null`` with the reason. Renders and ground truth are compared on black.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from skimage.draw import polygon
from skimage.metrics import structural_similarity
from tqdm import tqdm

from .cameras import Camera
from .io import write_image, write_json
from .subject import Subject

BOX_PADDING = 0.05


def box_mask(camera: Camera, vertices: np.ndarray, padding: float = BOX_PADDING) -> np.ndarray:
    """Pixels inside the projection of the body's padded axis-aligned 3D box."""
    lo, hi = vertices.min(0) - padding, vertices.max(0) + padding
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, z = camera.project(corners)
    mask = np.zeros((camera.height, camera.width), dtype=bool)
    if (z <= 0).any():
        mask[:] = True
        return mask
    from scipy.spatial import ConvexHull

    hull = uv[ConvexHull(uv).vertices]
    rr, cc = polygon(hull[:, 1] - 0.5, hull[:, 0] - 0.5, shape=mask.shape)
    mask[rr, cc] = True
    return mask


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    err = ((a[mask] - b[mask]) ** 2).mean()
    return float(10 * np.log10(1.0 / max(err, 1e-10)))


def ssim_in_rect(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    ys, xs = np.nonzero(mask)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    win = min(7, y1 - y0, x1 - x0)
    win -= 1 - win % 2
    return float(
        structural_similarity(a[y0:y1, x0:x1], b[y0:y1, x0:x1], channel_axis=-1, data_range=1.0, win_size=max(3, win))
    )


class Lpips:
    """LPIPS(VGG) on the bounding rectangle of the evaluated region, or None without its weights."""

    def __init__(self) -> None:
        from .losses import load_lpips

        self.model, self.reason = load_lpips()

    def __call__(self, a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float | None:
        if self.model is None:
            return None
        import torch

        ys, xs = np.nonzero(mask)
        crop = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
        t = [torch.as_tensor(x[crop]).permute(2, 0, 1)[None].float() * 2 - 1 for x in (a, b)]
        with torch.no_grad():
            return float(self.model(*t))


Renderer = Callable[[Camera, int], np.ndarray]


def evaluate(
    subject: Subject, render: Renderer, out_dir: str | Path, scale: float = 0.5, max_views: int | None = None
) -> dict:
    """Metrics of ``render(camera, frame_index) -> (H, W, 3)`` against the subject's ground truth."""
    out_dir = Path(out_dir)
    lp = Lpips()
    body = subject.body
    splits = {
        "novel_view": [
            (c, subject.input_frame)
            for c in subject.cameras
            if c != subject.input_camera and subject.has_view(c, subject.input_frame)
        ],
        "novel_pose": [
            (subject.input_camera, int(f))
            for f in subject.motion.frame_ids
            if f != subject.input_frame and subject.has_view(subject.input_camera, int(f))
        ],
    }
    result: dict = {"box_padding_m": BOX_PADDING, "scale": scale, "lpips_reason": lp.reason or None}
    for split, views in splits.items():
        if max_views is not None and len(views) > max_views:
            views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).astype(int)]
        rows, tiles = [], []
        for cam_name, frame in tqdm(views, desc=split, unit="view", leave=False):
            cam = subject.cameras[cam_name]
            small = cam.scaled(scale)
            gt = subject.image(cam_name, frame) * subject.mask(cam_name, frame)[..., None]
            gt = _resize(gt, (small.height, small.width))
            index = int(np.nonzero(subject.motion.frame_ids == frame)[0][0])
            pred = np.clip(render(small, index), 0.0, 1.0)
            mask = box_mask(small, body.pose(*subject.motion.frame(index)).vertices)
            row = {
                "camera": cam_name,
                "frame": frame,
                "psnr": psnr(pred, gt, mask),
                "ssim": ssim_in_rect(pred, gt, mask),
                "lpips": lp(pred, gt, mask),
            }
            rows.append(row)
            err = np.abs(pred - gt).mean(-1, keepdims=True)
            tiles.append(np.concatenate([gt, pred, np.clip(err * 3, 0, 1).repeat(3, -1)], 1))
        mean = {
            k: (float(np.mean([r[k] for r in rows])) if rows and rows[0][k] is not None else None)
            for k in ("psnr", "ssim", "lpips")
        }
        result[split] = {**mean, "views": len(rows), "per_view": rows}
        if tiles:
            grid = np.concatenate(tiles[:8], 0)
            write_image(out_dir / f"{split}_grid.png", grid)
    return result


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import torch
    import torch.nn.functional as F

    t = torch.as_tensor(image).permute(2, 0, 1)[None]
    return F.interpolate(t, size=size, mode="area")[0].permute(1, 2, 0).numpy()


def evaluate_run(
    run: str | Path,
    subject: Subject,
    out: str | Path,
    scale: float = 0.5,
    max_views: int | None = None,
    n_samples: int = 64,
) -> dict:
    """Evaluate a fitted avatar (``run`` folder) and write ``metrics.json`` + grids next to ``out``."""
    import json

    from .animate import load_avatar

    run = Path(run)
    avatar = load_avatar(run)

    def render(camera: Camera, index: int) -> np.ndarray:
        return avatar.render_pose(camera, *subject.motion.frame(index), n_samples)["rgb"]

    out = Path(out)
    metrics = evaluate(subject, render, out.parent, scale, max_views)
    report = json.loads((run / "run.json").read_text()) if (run / "run.json").is_file() else {}
    metrics["encoder"] = (report.get("encoder") or {}).get("name")
    metrics["fit_seconds"] = (report.get("seconds") or {}).get("total")
    write_json(out, metrics)
    return metrics
