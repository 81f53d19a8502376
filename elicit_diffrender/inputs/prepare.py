"""``elicit prepare``: from one photo to an ``elicit-subject/1`` folder (mask, camera, Anny body fit).

* Mask: ``--mask``, else the image's alpha channel, else MediaPipe's pose segmentation.
* Camera: focal from ``--focal``, else ``--params`` (CLIFF's ``focal_l``), else EXIF
  (``FocalLengthIn35mmFilm``), else CLIFF's default ``f = sqrt(W^2 + H^2)``; principal point at the
  image centre; identity extrinsics (the subject lives in camera space).
* Body: Anny fitted to MediaPipe's 33 landmarks and the silhouette; with ``pred_joints`` in
  ``--params`` (camera-space SMPL joints) those are fitted too.
* Output: the subject (motion: the input pose, then a built-in motion placed where the person
  stands), ``overlay.png`` and ``fit_report.json`` (keypoint error, silhouette IoU, time).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..body.fitting import FIT_STEPS, SilhouetteFactory, fit_anny_to_image
from ..core.cameras import Camera
from ..core.checks import MAX_MEGAPIXELS, numeric, read_image, read_mask
from ..core.errors import ElicitError
from ..core.io import folder_in_place, write_image, write_json
from ..core.safe_load import load_npz
from ..data.subject import write_subject
from .mediapipe_bridge import MediaPipeUnavailable, PoseDetection, detect_pose

RENDER_SIZE = 160  # longer image side of the body fit's differentiable silhouette, pixels


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
            if vis < 0.3 or not (0 <= x < w and 0 <= y < h):
                raise PrepareError(
                    f"{photo}: the person's {part} is outside the image or hidden; a full-body photo is needed"
                )


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


def prepare(
    photo: str | Path,
    out: str | Path,
    mask_path: str | Path | None = None,
    params_path: str | Path | None = None,
    focal: float | None = None,
    motion: str = "walk_in_place",
    steps: int | None = None,
    force: bool = False,
    max_megapixels: float = MAX_MEGAPIXELS,
) -> dict:
    """Build a subject from one photo, written as a whole (a non-empty ``out`` only with ``force``);
    returns the fit report (also ``fit_report.json``). ``steps`` overrides the body fit's ``FIT_STEPS``."""
    from .importers import motion_with_input_frame

    t0 = time.perf_counter()
    photo, out = Path(photo), Path(out)
    rgb, alpha = read_image(photo, "photo", max_megapixels=max_megapixels, error=PrepareError)
    h, w = rgb.shape[:2]
    if focal is not None and not (np.isfinite(focal) and focal > 0):
        raise PrepareError(f"--focal must be a positive number of pixels, got {focal}")
    params = read_params(Path(params_path)) if params_path is not None else {}
    with folder_in_place(out, force) as tmp:  # fails here, before the body fit, if out cannot be written
        mask, detection, mask_source, missing = person_mask(
            photo, rgb, alpha, None if mask_path is None else Path(mask_path)
        )
        sources = {"mask": mask_source}
        check_single_person(mask, photo)
        landmarks = detection.landmarks if detection is not None else None
        check_not_cut_off(mask, landmarks, photo)
        # Camera.
        if focal is not None:
            sources["focal"] = "--focal"
        elif "focal_l" in params:
            focal, sources["focal"] = params["focal_l"], f"{params_path} focal_l"
        elif (f := exif_focal(photo, w, h)) is not None:
            focal, sources["focal"] = f, "EXIF FocalLengthIn35mmFilm"
        else:
            focal, sources["focal"] = float(np.hypot(w, h)), "default sqrt(W^2 + H^2) (CLIFF's)"
        K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
        camera = Camera(K, np.eye(3), np.zeros(3), w, h, "input")
        # Body.
        joints3d = params.get("pred_joints")
        if landmarks is None and joints3d is None:
            if detection is None:
                raise PrepareError(f"{photo}: keypoints are needed for the body fit and {missing}")
            raise PrepareError(f"{photo}: no person found by MediaPipe")
        sources["keypoints"] = "MediaPipe pose (33 landmarks)" if landmarks is not None else "none"
        has_world = detection is not None and detection.world is not None
        sources["body_directions"] = "MediaPipe metric landmarks" if has_world else "keypoints and silhouette only"
        sources["joints3d"] = f"{params_path} pred_joints" if joints3d is not None else "none"
        fit = fit_anny_to_image(
            K,
            mask,
            landmarks,
            joints3d,
            FIT_STEPS if steps is None else steps,
            mitsuba_silhouette(camera, RENDER_SIZE),
            world_landmarks=detection.world if detection is not None else None,
        )
        body = fit["body"]
        spec = {"model": "anny", "phenotype": {k: round(v, 4) for k, v in fit["phenotype"].items()}}
        motion_obj = motion_with_input_frame(
            body, fit["pose"], fit["global_orient"], fit["transl"], motion, np.array([0.0, -1.0, 0.0])
        )
        write_subject(
            tmp,
            spec,
            {"input": camera},
            motion_obj,
            "input",
            0,
            {("input", 0): (rgb * mask[..., None], mask)},
            {"prepare": {"photo": str(photo), **sources}},
        )
        # Report and overlay.
        from ..data.mesh_render import MeshRenderer

        posed = body.pose(*motion_obj.frame(0))
        render = MeshRenderer(body.faces).render(posed.vertices, [camera], ("mask",))["mask"][0] > 0
        iou = float((render & mask).sum() / max((render | mask).sum(), 1))
        report = {
            "photo": str(photo),
            "subject": str(out),
            "image_size": [w, h],
            "focal_px": focal,
            "sources": sources,
            "silhouette_iou": iou,
            **fit["report"],
            "seconds": time.perf_counter() - t0,
        }
        if "keypoint_error_px" in report:
            report["keypoint_error_percent_of_height"] = 100.0 * report["keypoint_error_px"]["median"] / h
        write_json(tmp / "fit_report.json", report)
        write_overlay(tmp / "overlay.png", rgb, mask, render, landmarks, camera, posed, body)
    return report


def write_overlay(
    path: Path, rgb: np.ndarray, mask: np.ndarray, render: np.ndarray, landmarks, camera, posed, body
) -> Path:
    """The photo with the fitted body (tinted), the mask outline (green) and keypoints (detected: yellow)."""
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
    return write_image(path, img[::step, ::step])
