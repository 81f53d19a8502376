"""``elicit eval``: novel-view and novel-pose metrics in the Neural Body protocol.

* novel view: the input frame from every camera except the input one; ``front`` summarises the cameras
  up to the first of ``SIDE_DEGREES`` from the input camera around the body's vertical axis, ``side``
  those within ``SIDE_DEGREES``, ``rear`` those more than ``REAR_DEGREES`` from it (the side a single
  photo never shows);
* novel pose: the input camera at every other frame.

A run fitted on another subject of the same person (the photo path: ``elicit prepare`` on a
synthetic subject's input image) is evaluated with ``align``: a single photo fixes neither scale
nor depth, so the run's frame is mapped onto the ground truth's by the similarity (rotation,
translation, scale; Umeyama) that best maps its input-pose body's vertices onto the ground-truth
body's (both Anny meshes, so vertices correspond). The alignment is for evaluation only; the pose
error that remains counts. Only the novel-view split is evaluated then (the fitted subject has its
own motion).

PSNR is taken over the pixels inside the projected 3D box of the posed body (padded by
``BOX_PADDING`` metres on every side: the convex hull of its 8 projected corners); SSIM
(scikit-image) over that region's bounding rectangle; LPIPS(VGG) when its weights are available,
otherwise ``null`` with the reason. Renders and ground truth are compared on black. How solid the
avatar is against the true mask ``M``, with ``A`` the render's ``alpha > 0.5``: ``silhouette_iou``
``|A & M| / |A | M|``, ``hole_fraction`` ``|M & ~A| / |M|`` (gaps: the person is there, the avatar is not)
and ``spill`` ``|A & ~M| / |M|`` (the avatar where the person is not).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from skimage.draw import polygon
from skimage.metrics import structural_similarity
from tqdm import tqdm

from ..core.cameras import Camera
from ..core.io import write_image, write_json
from ..data.subject import Subject

BOX_PADDING = 0.05
REAR_DEGREES = 120.0
SIDE_DEGREES = (60.0, 120.0)  # a side view: more than the first, at most the second, from the input camera
GRID_ROWS = 8  # views in each split's grid, evenly spaced through the split


def angle_around_body(camera: Camera, reference: Camera, centre: np.ndarray, up: np.ndarray) -> float:
    """Degrees between two cameras' directions from ``centre``, seen along the ``up`` axis (0..180)."""
    dirs = []
    for cam in (camera, reference):
        d = cam.center - centre
        d = d - (d @ up) * up
        dirs.append(d / max(np.linalg.norm(d), 1e-9))
    return float(np.degrees(np.arccos(np.clip(dirs[0] @ dirs[1], -1.0, 1.0))))


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


def silhouette_metrics(alpha: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """IoU of ``alpha > 0.5`` against the true ``mask``, the share of the mask it leaves empty (holes) and
    what it covers outside the mask, as a share of the mask (spill)."""
    solid = alpha > 0.5
    area = max(int(mask.sum()), 1)
    return {
        "silhouette_iou": float((solid & mask).sum() / max(int((solid | mask).sum()), 1)),
        "hole_fraction": float((mask & ~solid).sum() / area),
        "spill": float((solid & ~mask).sum() / area),
    }


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
        from ..model.losses import load_lpips

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


Renderer = Callable[[Camera, int], dict[str, np.ndarray]]  # (camera, frame index) -> {"rgb", "alpha"}
SPLITS = ("novel_view", "novel_pose")


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``dst ~ s R src + t`` of least squares between corresponding (N, 3) points."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(d) @ vt
    scale = float((sig * d).sum() / (a**2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def camera_in_frame(camera: Camera, scale: float, rot: np.ndarray, transl: np.ndarray) -> Camera:
    """``camera`` (of the frame ``x' = s R x + t``) as a camera of the frame of ``x``: same image."""
    return Camera(
        camera.K.copy(),
        camera.R @ rot,
        (camera.R @ transl + camera.T) / scale,
        camera.width,
        camera.height,
        camera.name,
    )


LEAN_SEGMENTS = {"torso": ("pelvis", "neck"), "left_shin": ("l_knee", "l_ankle"), "right_shin": ("r_knee", "r_ankle")}


def lean_angles(body, pose: tuple, camera: Camera) -> dict[str, dict[str, float]]:
    """Each of ``LEAN_SEGMENTS``' direction, in the frame of the input ``camera`` held level (up: the image's
    up, towards: the camera, right: the image's right): its angle from vertical, its lean towards the camera
    (the one a photo cannot see; positive: top nearer the camera) and its lean to the image's right, degrees."""
    posed = body.pose(*pose)
    joint = {n: posed.bone_transforms[body.joint_index(body.semantic[n]), :3, 3] for n in body.semantic}
    up, right = -camera.R[1], camera.R[0]
    towards = np.cross(right, up)  # -camera.R[2]: from the body back to the camera, horizontal
    out = {}
    for name, (a, b) in LEAN_SEGMENTS.items():
        d = joint[b] - joint[a] if name == "torso" else joint[a] - joint[b]  # pointing up the body
        d = d / max(np.linalg.norm(d), 1e-9)
        out[name] = {
            "from_vertical": float(np.degrees(np.arccos(np.clip(d @ up, -1.0, 1.0)))),
            "towards_camera": float(np.degrees(np.arctan2(d @ towards, d @ up))),
            "sideways": float(np.degrees(np.arctan2(d @ right, d @ up))),
            "_direction": [float(d @ right), float(d @ up), float(d @ towards)],
        }
    return out


def lean_errors(fitted: dict, truth: dict) -> dict[str, float]:
    """Degrees between each segment's direction in the fitted body and the true one (both in their own input
    camera's level frame, so no alignment enters)."""
    return {
        name: float(np.degrees(np.arccos(np.clip(np.dot(fitted[name]["_direction"], truth[name]["_direction"]),
                                                 -1.0, 1.0))))
        for name in LEAN_SEGMENTS
    }  # fmt: skip


@dataclass
class BodyAlignment:
    """A body fitted on another subject of the same person against the true body, both at their input poses."""

    similarity: tuple[float, np.ndarray, np.ndarray]  # (s, R, t): the fitted frame onto the true one
    residual: np.ndarray  # (V,) metres between each aligned vertex and its true place
    fitted_lean: dict[str, dict[str, float]]  # lean_angles of each body, in its own input camera's level frame
    true_lean: dict[str, dict[str, float]]

    @property
    def lean_error(self) -> dict[str, float]:
        return lean_errors(self.fitted_lean, self.true_lean)


def align_bodies(fitted: Subject, truth: Subject) -> BodyAlignment:
    """The similarity (:func:`umeyama`) that maps ``fitted``'s input-pose body onto ``truth``'s, the vertex error
    left after it, and both bodies' lean; the same body model is needed for both."""
    from ..data.subject import SubjectError

    pose, true_pose = fitted.motion.frame(fitted.input_index), truth.motion.frame(truth.input_index)
    src, dst = fitted.body.pose(*pose).vertices, truth.body.pose(*true_pose).vertices
    if src.shape != dst.shape:
        raise SubjectError(
            f"{fitted.root}: its body has {len(src)} vertices and {truth.root}'s {len(dst)}; --align needs the same "
            "body model for both"
        )
    sim = umeyama(src, dst)
    residual = np.linalg.norm(sim[0] * src @ sim[1].T + sim[2] - dst, axis=1)
    return BodyAlignment(
        sim,
        residual,
        lean_angles(fitted.body, pose, fitted.cameras[fitted.input_camera]),
        lean_angles(truth.body, true_pose, truth.cameras[truth.input_camera]),
    )


def camera_error(
    fitted: Subject, fitted_view: tuple[str, int], truth: Subject, true_view: tuple[str, int]
) -> tuple[float, float]:
    """How far a prepared input camera lies from the true one, after the similarity (:func:`umeyama`) that maps
    the prepared body in that view's pose onto the true body in its pose: metres between the centres and degrees
    between the orientations. A photo fixes only where its camera is against the body, which this measures."""
    bodies = []
    for subject, (_, frame) in ((fitted, fitted_view), (truth, true_view)):
        bodies.append(subject.body.pose(*subject.motion.frame(subject.frame_index(frame))).vertices)
    scale, rot, transl = umeyama(*bodies)
    camera, true_camera = fitted.cameras[fitted_view[0]], truth.cameras[true_view[0]]
    centre = scale * rot @ camera.center + transl
    relative = true_camera.R @ (camera.R @ rot.T).T
    cos = (np.trace(relative) - 1.0) / 2.0
    return float(np.linalg.norm(centre - true_camera.center)), float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def evaluate(
    subject: Subject,
    render: Renderer,
    out_dir: str | Path,
    scale: float = 0.5,
    max_views: int | None = None,
    splits: tuple[str, ...] = SPLITS,
) -> dict:
    """Metrics of ``render(camera, frame_index) -> {"rgb": (H, W, 3), "alpha": (H, W)}`` against the subject's
    ground truth."""
    out_dir = Path(out_dir)
    lp = Lpips()
    body = subject.body
    views_of = {
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
    for split, views in views_of.items():
        if split not in splits:
            continue
        if max_views is not None and len(views) > max_views:
            views = [views[i] for i in np.linspace(0, len(views) - 1, max_views).astype(int)]
        rows, tiles = [], []
        for cam_name, frame in tqdm(views, desc=split, unit="view", leave=False):
            cam = subject.cameras[cam_name]
            small = cam.scaled(scale)
            true_mask = subject.mask(cam_name, frame)
            gt = _resize(subject.image(cam_name, frame) * true_mask[..., None], (small.height, small.width))
            true_mask = _resize(true_mask[..., None].astype(np.float32), (small.height, small.width))[..., 0] > 0.5
            index = int(np.nonzero(subject.motion.frame_ids == frame)[0][0])
            out = render(small, index)
            pred = np.clip(out["rgb"], 0.0, 1.0)
            posed = body.pose(*subject.motion.frame(index)).vertices
            mask = box_mask(small, posed)
            row = {
                "camera": cam_name,
                "frame": frame,
                "psnr": psnr(pred, gt, mask),
                "ssim": ssim_in_rect(pred, gt, mask),
                "lpips": lp(pred, gt, mask),
                **silhouette_metrics(out["alpha"], true_mask),
            }
            if split == "novel_view":
                ref = subject.cameras[subject.input_camera]
                row["degrees_from_input"] = angle_around_body(cam, ref, posed.mean(0), -ref.R[1])
            rows.append(row)
            err = np.abs(pred - gt).mean(-1, keepdims=True)
            tiles.append(np.concatenate([gt, pred, np.clip(err * 3, 0, 1).repeat(3, -1)], 1))
        result[split] = {**summary(rows), "per_view": rows}
        if split == "novel_view":
            lo, hi = SIDE_DEGREES
            result[split]["front"] = {
                "degrees": [0.0, lo],
                **summary([r for r in rows if r["degrees_from_input"] <= lo]),
            }
            result[split]["side"] = {
                "degrees": list(SIDE_DEGREES),
                **summary([r for r in rows if lo < r["degrees_from_input"] <= hi]),
            }
            result[split]["rear"] = {
                "degrees": REAR_DEGREES,
                **summary([r for r in rows if r["degrees_from_input"] > REAR_DEGREES]),
            }
        if tiles:
            shown = np.unique(np.linspace(0, len(tiles) - 1, GRID_ROWS).round().astype(int))  # all round, back included
            grid = np.concatenate([tiles[i] for i in shown], 0)
            write_image(out_dir / f"{split}_grid.png", grid)
    return result


METRICS = ("psnr", "ssim", "lpips", "silhouette_iou", "hole_fraction", "spill")


def summary(rows: list[dict]) -> dict:
    """The mean of every metric over ``rows`` (None for a metric that is missing, or with no rows) and their count."""
    return {
        "views": len(rows),
        **{k: (float(np.mean([r[k] for r in rows])) if rows and rows[0][k] is not None else None) for k in METRICS},
    }


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
    align: bool = False,
) -> dict:
    """Evaluate a fitted avatar (``run`` folder) and write ``metrics.json`` + grids next to ``out``;
    with ``align``, a run fitted on another subject of the same person (see the module's docstring)."""
    from ..core.io import read_json
    from ..data.subject import SubjectError, load_subject
    from ..model.load import load_avatar

    run = Path(run)
    report = read_json(run / "run.json", SubjectError) if (run / "run.json").is_file() else {}
    if not isinstance(report, dict):
        raise SubjectError(f"{run / 'run.json'}: the top level must be an object")
    avatar = load_avatar(run)
    extra: dict = {}
    if align:
        if not isinstance(report.get("subject"), str):
            raise SubjectError(f"{run}: --align needs the run's run.json, which names the subject it was fitted on")
        fitted = load_subject(report["subject"])
        pose = fitted.motion.frame(fitted.input_index)
        aligned = align_bodies(fitted, subject)
        sim, residual = aligned.similarity, aligned.residual
        extra["alignment"] = {
            "fitted_subject": str(report["subject"]),
            "scale": sim[0],
            "vertex_error_m": {"mean": float(residual.mean()), "max": float(residual.max())},
            "lean_deg": {
                "fitted": {
                    k: {a: b for a, b in v.items() if a != "_direction"} for k, v in aligned.fitted_lean.items()
                },
                "true": {k: {a: b for a, b in v.items() if a != "_direction"} for k, v in aligned.true_lean.items()},
                "error": aligned.lean_error,
            },
        }

        def render(camera: Camera, index: int) -> dict[str, np.ndarray]:
            return avatar.render_pose(camera_in_frame(camera, *sim), *pose, n_samples)

        splits: tuple[str, ...] = ("novel_view",)
    else:

        def render(camera: Camera, index: int) -> dict[str, np.ndarray]:
            return avatar.render_pose(camera, *subject.motion.frame(index), n_samples)

        splits = SPLITS
    out = Path(out)
    metrics = evaluate(subject, render, out.parent, scale, max_views, splits)
    metrics.update(extra)
    encoder, seconds = report.get("encoder"), report.get("seconds")
    metrics["encoder"] = encoder.get("name") if isinstance(encoder, dict) else None
    metrics["fit_seconds"] = seconds.get("total") if isinstance(seconds, dict) else None
    write_json(out, metrics)
    return metrics
