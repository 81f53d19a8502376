"""``elicit prepare``: from one or more photos of a person to an ``elicit-subject/1`` folder (masks, cameras,
an Anny body fit).

* Mask: ``--mask``, else the image's alpha channel, else MediaPipe's pose segmentation.
* Camera: focal from ``--focal``, else ``--params`` (CLIFF's ``focal_l``), else EXIF
  (``FocalLengthIn35mmFilm``), else CLIFF's default ``f = sqrt(W^2 + H^2)``; principal point at the
  image centre; identity extrinsics (the subject lives in camera space).
* Body: Anny fitted to MediaPipe's 33 landmarks and the silhouette; with ``pred_joints`` in
  ``--params`` (camera-space SMPL joints) those are fitted too.
* Several photos (same person, same clothes, any poses and directions): one shape, the first photo's;
  a pose per photo; each other photo's camera placed by its body fit (:func:`prepare`).
* Output: the subject (motion: the photos' poses, then a built-in motion placed where the person
  stands), ``overlay.png`` and ``fit_report.json`` (keypoint error, silhouette IoU, time; per photo).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..body.fitting import FIT_STEPS, SilhouetteFactory, fit_anny_to_image
from ..core.cameras import Camera
from ..core.checks import MAX_MEGAPIXELS, numeric, read_image, read_mask
from ..core.errors import ElicitError
from ..core.io import folder_in_place, write_image, write_json
from ..core.safe_load import load_npz
from ..data.motions import Motion
from ..data.subject import write_subject
from .mediapipe_bridge import MediaPipeUnavailable, PoseDetection, detect_pose

MASK_SUFFIX = "_mask"  # photo.jpg's person mask, if given, is photo_mask.png beside it
RENDER_SIZE = 160  # longer image side of the body fit's differentiable silhouette, pixels
# Two photos whose own shape fits differ by more than this (mean rest-pose vertex distance) show different people
MAX_SHAPE_DIFFERENCE_CM = 6.0


class PrepareError(ElicitError):
    """A photo that cannot be turned into a subject."""


def exif_focal(path: Path, width: int, height: int) -> float | None:
    """Focal length in pixels from EXIF's 35 mm-equivalent focal length (36 mm across the long side)."""
    try:
        from PIL import Image

        with Image.open(path) as img:
            exif = img.getexif()
            value = exif.get_ifd(0x8769).get(0xA405) or exif.get(0xA405)  # FocalLengthIn35mmFilm
    except Exception:  # unreadable or absent EXIF: fall through to the default
        return None
    if not value:
        return None
    return float(value) / 36.0 * max(width, height)


def check_single_person(mask: np.ndarray, photo: Path) -> None:
    if mask.sum() < 0.005 * mask.size:
        raise PrepareError(f"{photo}: no person found (the person mask is empty)")
    labels, n = ndimage.label(mask)
    if n > 1:
        sizes = np.sort(np.bincount(labels.ravel())[1:])[::-1]
        if sizes[1] > 0.15 * sizes[0]:
            raise PrepareError(
                f"{photo}: several people found ({int((sizes > 0.15 * sizes[0]).sum())} large "
                f"regions in the person mask); crop the photo to one person"
            )


def check_not_cut_off(mask: np.ndarray, landmarks: np.ndarray | None, photo: Path) -> None:
    h, w = mask.shape
    for name, row in (("top", mask[0]), ("bottom", mask[-1])):
        if row.sum() > 0.02 * w:
            raise PrepareError(
                f"{photo}: the person is cut off by the {name} image border; a full-body photo is needed"
            )
    if landmarks is not None:
        for idx, part in ((0, "head"), (27, "left ankle"), (28, "right ankle")):
            x, y, vis = landmarks[idx]
            if not (0 <= x < w and 0 <= y < h):
                raise PrepareError(f"{photo}: the person's {part} is outside the image; a full-body photo is needed")
        # Seen from the side, one ankle hides behind the other: only a hidden head or two hidden ankles stop.
        for part, ids in (("head is", (0,)), ("ankles are", (27, 28))):
            if all(landmarks[i, 2] < 0.3 for i in ids):
                raise PrepareError(f"{photo}: the person's {part} hidden; a full-body photo is needed")


def largest_component(mask: np.ndarray) -> np.ndarray:
    labels, n = ndimage.label(mask)
    if n <= 1:
        return mask
    return labels == (np.argmax(np.bincount(labels.ravel())[1:]) + 1)


def mitsuba_silhouette(camera: Camera, size: int) -> SilhouetteFactory:
    """The body fit's differentiable silhouette: Mitsuba's, through ``camera`` with its longer side at ``size``."""
    from ..data.mesh_render import DifferentiableSilhouette

    small = camera.scaled(min(1.0, size / max(camera.width, camera.height)))
    return lambda faces, n_vertices: DifferentiableSilhouette(faces, n_vertices, small)


def read_params(path: Path) -> dict:
    """``--params``: CLIFF's ``focal_l`` (positive) and ``pred_joints`` (camera-space SMPL joints), checked."""
    from .importers import smpl_joints

    if not path.is_file():
        raise PrepareError(f"{path}: parameter file not found")
    data = load_npz(path, PrepareError)
    params = {}
    if "focal_l" in data:
        focal = numeric(data["focal_l"], f"{path} field 'focal_l'", error=PrepareError).ravel()
        if focal.size != 1 or focal[0] <= 0:
            raise PrepareError(f"{path}: field 'focal_l' must be one positive number, got {focal.tolist()}")
        params["focal_l"] = float(focal[0])
    if "pred_joints" in data:
        params["pred_joints"] = smpl_joints(data, path, PrepareError)
    return params


def person_mask(
    photo: Path, rgb: np.ndarray, alpha: np.ndarray | None, mask_path: Path | None
) -> tuple[np.ndarray, PoseDetection | None, str, Exception | None]:
    """The person's mask, MediaPipe's detection (None when MediaPipe is missing) and where the mask came from.

    With a mask (``--mask`` or the alpha channel) the keypoints are detected on the photo composited over
    neutral grey outside it, so a dark or busy background cannot hide the person; without one, the mask is
    MediaPipe's, and a photo of several people stops with a message.
    """
    h, w = rgb.shape[:2]
    mask, source = None, ""
    if mask_path is not None:
        mask, source = read_mask(mask_path, "mask", (h, w), error=PrepareError), f"file {mask_path}"
    elif alpha is not None and alpha.min() < 1.0:
        mask, source = alpha > 0.5, "alpha channel"
    detection, missing = None, None
    try:  # MediaPipe sees the pixels as read (EXIF orientation applied), on grey outside a given mask
        with tempfile.TemporaryDirectory() as tmp:
            shown = rgb if mask is None else np.where(mask[..., None], rgb, 0.5)
            detection = detect_pose(write_image(Path(tmp) / "person.png", shown))
    except MediaPipeUnavailable as exc:
        missing = exc
    if mask is None:
        if detection is None:
            raise PrepareError(f"{photo}: no --mask and no alpha channel, and {missing}")
        check_single_person(detection.people > 0.5, photo)
        check_single_person(detection.segmentation > 0.5, photo)
        mask, source = largest_component(detection.segmentation > 0.5), "MediaPipe pose segmentation"
    return mask, detection, source, missing


@dataclass
class Photo:
    """One photo read and checked: pixels, person mask, keypoints and camera intrinsics."""

    path: Path
    rgb: np.ndarray  # (H, W, 3) float
    mask: np.ndarray  # (H, W) bool
    detection: PoseDetection | None
    missing: Exception | None  # why MediaPipe is missing, if it is
    K: np.ndarray
    sources: dict[str, str]

    @property
    def landmarks(self) -> np.ndarray | None:
        return self.detection.landmarks if self.detection is not None else None


def read_photo(
    path: Path, mask_path: Path | None, focal: float | None, params: dict, params_path, max_megapixels: float
) -> Photo:
    """Read one photo, find its person mask and keypoints, check it shows one whole person, pick its focal."""
    rgb, alpha = read_image(path, "photo", max_megapixels=max_megapixels, error=PrepareError)
    h, w = rgb.shape[:2]
    mask, detection, mask_source, missing = person_mask(path, rgb, alpha, mask_path)
    sources = {"mask": mask_source}
    check_single_person(mask, path)
    check_not_cut_off(mask, detection.landmarks if detection is not None else None, path)
    if focal is not None:
        sources["focal"] = "--focal"
    elif "focal_l" in params:
        focal, sources["focal"] = params["focal_l"], f"{params_path} focal_l"
    elif (f := exif_focal(path, w, h)) is not None:
        focal, sources["focal"] = f, "EXIF FocalLengthIn35mmFilm"
    else:
        focal, sources["focal"] = float(np.hypot(w, h)), "default sqrt(W^2 + H^2) (CLIFF's)"
    K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    has_landmarks = detection is not None and detection.landmarks is not None
    sources["keypoints"] = "MediaPipe pose (33 landmarks)" if has_landmarks else "none"
    has_world = detection is not None and detection.world is not None
    sources["body_directions"] = "MediaPipe metric landmarks" if has_world else "keypoints and silhouette only"
    return Photo(path, rgb, mask, detection, missing, K, sources)


def fit_body(photo: Photo, joints3d, steps: int | None, phenotype: dict | None = None) -> dict:
    """Anny fitted to one photo in its camera's space (``phenotype``: a shape held fixed)."""
    if photo.landmarks is None and joints3d is None:
        if photo.detection is None:
            raise PrepareError(f"{photo.path}: keypoints are needed for the body fit and {photo.missing}")
        raise PrepareError(f"{photo.path}: no person found by MediaPipe")
    h, w = photo.mask.shape
    camera = Camera(photo.K, np.eye(3), np.zeros(3), w, h, "input")
    detection = photo.detection
    return fit_anny_to_image(
        photo.K,
        photo.mask,
        photo.landmarks,
        joints3d,
        FIT_STEPS if steps is None else steps,
        mitsuba_silhouette(camera, RENDER_SIZE),
        world_landmarks=detection.world if detection is not None else None,
        phenotype=phenotype,
    )


def shape_difference_cm(body, other) -> float:
    """Mean distance between two bodies' rest-pose vertices (each centred on its mean), in centimetres: how far
    the shapes fitted to two photos disagree."""
    a, b = body.pose(body.zero_pose()).vertices, other.pose(other.zero_pose()).vertices
    return float(np.linalg.norm((a - a.mean(0)) - (b - b.mean(0)), axis=1).mean() * 100.0)


def camera_from_placements(first: dict, this: dict) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, T) of a photo whose body fit placed the body at ``this`` (``global_orient``,
    ``transl`` in its camera's space) when the world holds that body at ``first``'s placement (the first photo's,
    whose camera is the world): ``x_cam = R x_world + T`` with ``R = rot_this rot_first^T`` and
    ``T = t_this - R t_first``."""
    from scipy.spatial.transform import Rotation

    rot_first = Rotation.from_rotvec(first["global_orient"]).as_matrix()
    rot_this = Rotation.from_rotvec(this["global_orient"]).as_matrix()
    R = rot_this @ rot_first.T
    return R, np.asarray(this["transl"]) - R @ np.asarray(first["transl"])


def mask_beside(photo: Path) -> Path | None:
    """``photo.jpg``'s person mask ``photo_mask.png`` beside it, if there is one."""
    mask = photo.with_name(photo.stem + MASK_SUFFIX + ".png")
    return mask if mask.is_file() else None


def _as_list(value, n: int, name: str, once_for_all: bool = False) -> list:
    """A per-photo option: one value per photo, or none (or, ``once_for_all``, one value for every photo)."""
    if value is None:
        return [None] * n
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    if once_for_all and len(values) == 1:
        return values * n
    if len(values) != n:
        raise PrepareError(f"{name}: given {len(values)} times for {n} photos; give it once per photo, in order")
    return values


def prepare(
    photos: str | Path | list,
    out: str | Path,
    mask_path: str | Path | list | None = None,
    params_path: str | Path | None = None,
    focal: float | list | None = None,
    motion: str = "walk_in_place",
    steps: int | None = None,
    force: bool = False,
    max_megapixels: float = MAX_MEGAPIXELS,
) -> dict:
    """Build a subject from one or more photos of one person, written as a whole (a non-empty ``out`` only with
    ``force``); returns the fit report (also ``fit_report.json``). ``steps`` overrides the body fit's ``FIT_STEPS``.

    With several photos, ``mask_path`` and ``focal`` are given once per photo (or not at all). The first
    photo's fit fixes the body's shape; every other photo is fitted with that shape held, in its own pose,
    and its camera is placed so that its body stands where the first photo's does (:func:`camera_from_placements`).
    A photo whose own shape fit differs from the first's by more than ``MAX_SHAPE_DIFFERENCE_CM`` is refused."""
    from .importers import motion_with_input_frame

    t0 = time.perf_counter()
    paths = [Path(p) for p in (photos if isinstance(photos, (list, tuple)) else [photos])]
    out = Path(out)
    masks = [None if m is None else Path(m) for m in _as_list(mask_path, len(paths), "--mask")]
    focals = _as_list(focal, len(paths), "--focal", once_for_all=True)
    for f in focals:
        if f is not None and not (np.isfinite(f) and f > 0):
            raise PrepareError(f"--focal must be a positive number of pixels, got {f}")
    params = read_params(Path(params_path)) if params_path is not None else {}
    if params and len(paths) > 1:
        raise PrepareError("--params describes one photo; it cannot be used with several")
    with folder_in_place(out, force) as tmp:  # fails here, before the body fit, if out cannot be written
        shots = [
            read_photo(p, m, f, params, params_path, max_megapixels)
            for p, m, f in zip(paths, masks, focals, strict=True)
        ]
        joints3d = params.get("pred_joints")
        shots[0].sources["joints3d"] = f"{params_path} pred_joints" if joints3d is not None else "none"
        fits = [fit_body(shots[0], joints3d, steps)]
        shape = fits[0]["phenotype"]
        differences = [0.0]
        for shot in shots[1:]:
            own = fit_body(shot, None, steps)
            difference = shape_difference_cm(fits[0]["body"], own["body"])
            if difference > MAX_SHAPE_DIFFERENCE_CM:
                raise PrepareError(
                    f"{shot.path}: the body fitted to it differs from {shots[0].path}'s by {difference:.1f} cm "
                    f"(mean vertex distance at rest; at most {MAX_SHAPE_DIFFERENCE_CM} cm for one person): all photos "
                    "must show the same person in the same clothes"
                )
            differences.append(difference)
            fits.append(fit_body(shot, None, steps, phenotype=shape))
        body = fits[0]["body"]
        spec = {"model": "anny", "phenotype": {k: round(v, 4) for k, v in shape.items()}}
        first = fits[0]
        motion_obj = motion_with_input_frame(
            body, first["pose"], first["global_orient"], first["transl"], motion, np.array([0.0, -1.0, 0.0])
        )
        n = len(shots)
        if n > 1:  # frames 1..n-1: the other photos' poses, where the first photo's body stands
            extra = np.stack([f["pose"] for f in fits[1:]])
            motion_obj = Motion(
                np.concatenate([motion_obj.pose[:1], extra, motion_obj.pose[1:]]),
                np.concatenate([np.repeat(motion_obj.global_orient[:1], n, 0), motion_obj.global_orient[1:]]),
                np.concatenate([np.repeat(motion_obj.transl[:1], n, 0), motion_obj.transl[1:]]),
                None,
                motion_obj.fps,
                motion_obj.name,
            )
        cameras, views, inputs = {}, {}, []
        for k, (shot, fit) in enumerate(zip(shots, fits, strict=True)):
            h, w = shot.mask.shape
            name = "input" if k == 0 else f"input{k}"
            R, T = (np.eye(3), np.zeros(3)) if k == 0 else camera_from_placements(first, fit)
            cameras[name] = Camera(shot.K, R, T, w, h, name)
            views[(name, k)] = (shot.rgb * shot.mask[..., None], shot.mask)
            inputs.append((name, k))
        photo_sources = {"photo": str(shots[0].path), **shots[0].sources}
        if n > 1:
            photo_sources["photos"] = [str(s.path) for s in shots]
        write_subject(tmp, spec, cameras, motion_obj, "input", 0, views, {"prepare": photo_sources}, inputs)
        # Report and overlay.
        from ..data.mesh_render import MeshRenderer

        renderer = MeshRenderer(body.faces)
        per_photo, tiles = [], []
        for k, (shot, fit) in enumerate(zip(shots, fits, strict=True)):
            camera = cameras[inputs[k][0]]
            posed = body.pose(*motion_obj.frame(k))
            render = renderer.render(posed.vertices, [camera], ("mask",))["mask"][0] > 0
            iou = float((render & shot.mask).sum() / max((render | shot.mask).sum(), 1))
            h, w = shot.mask.shape
            row = {
                "photo": str(shot.path),
                "camera": inputs[k][0],
                "image_size": [w, h],
                "focal_px": float(shot.K[0, 0]),
                "sources": shot.sources,
                "silhouette_iou": iou,
                "shape_difference_cm": differences[k],
                **fit["report"],
            }
            if "keypoint_error_px" in row:
                row["keypoint_error_percent_of_height"] = 100.0 * row["keypoint_error_px"]["median"] / h
            per_photo.append(row)
            tiles.append(overlay_image(shot.rgb, shot.mask, render, shot.landmarks))
        report = {"subject": str(out), **per_photo[0], "seconds": time.perf_counter() - t0}
        if n > 1:
            report["photos"] = per_photo
        write_json(tmp / "fit_report.json", report)
        height = max(t.shape[0] for t in tiles)
        write_image(
            tmp / "overlay.png",
            np.concatenate([np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0))) for t in tiles], 1),
        )
    return report


def overlay_image(rgb: np.ndarray, mask: np.ndarray, render: np.ndarray, landmarks) -> np.ndarray:
    """The photo with the fitted body (tinted), the mask outline (green) and keypoints (detected: yellow), at
    most about 512 pixels across."""
    img = rgb.copy()
    img[render] = 0.55 * img[render] + 0.45 * np.array([0.9, 0.2, 0.2])
    edge = mask & ~ndimage.binary_erosion(mask, iterations=2)
    img[edge] = (0.1, 0.9, 0.2)
    if landmarks is not None:
        for x, y, vis in landmarks:
            if vis > 0.5:
                yi, xi = int(y), int(x)
                img[max(0, yi - 3) : yi + 4, max(0, xi - 3) : xi + 4] = (1.0, 0.9, 0.1)
    step = max(1, max(img.shape[:2]) // 512)
    return img[::step, ::step]
