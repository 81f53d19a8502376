"""Importers into ``elicit-subject/1``: ELICIT's in-the-wild layout (CLIFF fits) and ZJU-MoCap.

ELICIT in the wild: ``gt_image.png`` (RGBA), ``gt_mask.png`` and ``gt_params.npz`` with CLIFF's
``pose`` (1, 72), ``shape`` (1, 10), ``global_t`` (1, 3) and ``focal_l`` (a scalar or (1,)); the
camera is ``K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]]`` with identity extrinsics. With SMPL model
files the body is SMPL with those parameters; without them it is Anny fitted to ``pred_joints``
(camera-space SMPL joints, present in some files).

ZJU-MoCap: ``annots.npy`` (cameras with T in millimetres, per-frame image lists), images under the
camera folders, masks under ``mask_cihp/`` or ``mask/``, and EasyMocap ``new_params/<frame>.npy``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import Camera
from .errors import ElicitError
from .motions import Motion, builtin_motion, read_zju_params
from .subject import SubjectError, read_png, write_subject


class SourceImportError(ElicitError):
    """A source folder that cannot be imported."""


def _need(path: Path, what: str) -> Path:
    if not path.exists():
        raise SourceImportError(f"{path}: {what} not found")
    return path


def _load_npz(path: Path) -> dict:
    try:
        with np.load(_need(path, "parameter file"), allow_pickle=True) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise SourceImportError(f"{path}: not a readable .npz file ({exc})") from exc


def _field(params: dict, key: str, shape: tuple, path: Path) -> np.ndarray:
    if key not in params:
        raise SourceImportError(f"{path}: missing field '{key}'")
    arr = np.asarray(params[key], dtype=np.float64)
    if arr.size != int(np.prod(shape)):
        raise SourceImportError(f"{path}: field '{key}' must have shape {shape}, got {arr.shape}")
    arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise SourceImportError(f"{path}: field '{key}' contains NaN or infinite values")
    return arr


def upright_frame(root_rotation: np.ndarray, up: np.ndarray) -> np.ndarray:
    """A rotation whose y axis is ``up`` and whose z axis is the body's facing, levelled."""
    y = up / np.linalg.norm(up)
    z = root_rotation[:, 2] - (root_rotation[:, 2] @ y) * y
    z /= np.linalg.norm(z)
    return np.stack([np.cross(y, z), y, z], axis=1)


def motion_with_input_frame(
    body, input_pose: np.ndarray, input_orient: np.ndarray, input_transl: np.ndarray, motion_name: str, up: np.ndarray
) -> Motion:
    """Frame 0 is the input pose; the built-in motion follows, placed upright where the person stands."""
    posed = body.pose(input_pose, input_orient, input_transl)
    pelvis = body.joint_index(body.semantic["pelvis"])
    frame = posed.bone_transforms[pelvis]
    rest_pelvis = body.pose(body.zero_pose()).bone_transforms[pelvis, :3, 3]
    rot = upright_frame(frame[:3, :3], up)
    target = builtin_motion(motion_name, body).placed(rot, frame[:3, 3] - rot @ rest_pelvis)
    return Motion(
        np.concatenate([input_pose[None], target.pose]),
        np.concatenate([np.asarray(input_orient).reshape(1, 3), target.global_orient]),
        np.concatenate([np.asarray(input_transl).reshape(1, 3), target.transl]),
        None,
        30.0,
        f"input+{motion_name}",
    )


def smpl_available(model_path: str | None) -> bool:
    from .body.smpl_model import resolve_model_file

    try:
        resolve_model_file("smpl", "neutral", model_path)
        return True
    except ElicitError:
        return False


def import_elicit_wild(
    folder: str | Path, out: str | Path, motion: str = "walk_in_place", smpl_path: str | None = None
) -> Path:
    """Import ELICIT's ``gt_image.png`` + ``gt_mask.png`` + ``gt_params.npz`` as a subject."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SourceImportError(f"{folder}: folder not found")
    img = read_png(_need(folder / "gt_image.png", "image"), None, "image")
    h, w = img.shape[:2]
    try:
        mask = read_png(_need(folder / "gt_mask.png", "mask"), (h, w), "mask")
    except SubjectError as exc:
        raise SourceImportError(str(exc)) from None
    mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
    params_path = folder / "gt_params.npz"
    params = _load_npz(params_path)
    focal = float(_field(params, "focal_l", (1,), params_path)[0])
    if focal <= 0:
        raise SourceImportError(f"{params_path}: field 'focal_l' must be positive, got {focal}")
    pose = _field(params, "pose", (24, 3), params_path)
    betas = _field(params, "shape", (10,), params_path)
    transl = _field(params, "global_t", (3,), params_path)
    K = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    camera = Camera(K, np.eye(3), np.zeros(3), w, h, "input")
    up = np.array([0.0, -1.0, 0.0])  # camera space: image up is -y
    info: dict = {"source": str(folder), "focal_l": focal}
    if smpl_available(smpl_path):
        from .body.smpl_model import SmplBody

        spec = {"model": "smpl", "betas": betas.tolist(), "gender": "neutral"}
        if smpl_path:
            spec["model_path"] = str(smpl_path)
        body = SmplBody(betas, "neutral", "smpl", smpl_path)
        in_pose, in_orient, in_transl = pose, np.zeros(3), transl
        info["body_fit"] = "CLIFF SMPL parameters"
    elif "pred_joints" in params:
        from .body.fitting import fit_anny_to_smpl_joints

        joints = _field(params, "pred_joints", (params["pred_joints"].size // 3, 3), params_path)
        fit = fit_anny_to_smpl_joints(joints[:24])
        body = fit["body"]
        spec = {"model": "anny", "phenotype": {k: round(v, 4) for k, v in fit["phenotype"].items()}}
        in_pose, in_orient, in_transl = fit["pose"], fit["global_orient"], fit["transl"]
        info["body_fit"] = "Anny fitted to CLIFF pred_joints"
        info["joint_error_mm"] = float(np.median(fit["joint_error_m"]) * 1000)
    else:
        raise SourceImportError(
            f"{params_path}: has SMPL parameters but no 'pred_joints', and no SMPL model files were found "
            f"(set ELICIT_SMPL_DIR or pass smpl_path); without either the body cannot be built"
        )
    motion_obj = motion_with_input_frame(body, in_pose, in_orient, in_transl, motion, up)
    rgb = img[..., :3].astype(np.float32) / 255.0
    rgb = rgb * mask[..., None]
    write_subject(
        out,
        spec,
        {"input": camera},
        motion_obj,
        "input",
        0,
        {("input", 0): (rgb, mask)},
        {"import": {"layout": "elicit-wild", **info}},
    )
    return Path(out)


def import_zju(
    folder: str | Path, out: str | Path, frames: list[int], input_camera: int = 0, smpl_path: str | None = None
) -> Path:
    """Import ZJU-MoCap frames (all cameras) as a subject with an SMPL body (needs model files)."""
    folder = Path(folder)
    annots_path = _need(folder / "annots.npy", "annots.npy")
    try:
        annots = np.load(annots_path, allow_pickle=True).item()
        cams_raw, ims = annots["cams"], annots["ims"]
    except (ValueError, KeyError, AttributeError) as exc:
        raise SourceImportError(f"{annots_path}: not a ZJU-MoCap annots file ({exc})") from exc
    n_cams = len(cams_raw["K"])
    if not 0 <= input_camera < n_cams:
        raise SourceImportError(f"{annots_path}: input camera {input_camera} out of range (0..{n_cams - 1})")
    params_dir = folder / "new_params" if (folder / "new_params").is_dir() else folder / "params"
    first = np.load(_need(params_dir / f"{frames[0]}.npy", "SMPL parameters"), allow_pickle=True).item()
    betas = np.asarray(first.get("shapes", np.zeros(10))).ravel()[:10]
    from .body.smpl_model import SmplBody

    body = SmplBody(betas, "neutral", "smpl", smpl_path)
    motion = read_zju_params(params_dir, body, frames)
    cameras, views = {}, {}
    mask_dir = folder / "mask_cihp" if (folder / "mask_cihp").is_dir() else folder / "mask"
    for c in range(n_cams):
        name = f"cam{c:02d}"
        first_img = read_png(_need(folder / ims[frames[0]]["ims"][c], "image"), None, "image")
        K = np.asarray(cams_raw["K"][c], dtype=np.float64)
        T = np.asarray(cams_raw["T"][c], dtype=np.float64).ravel() / 1000.0
        cameras[name] = Camera(K, np.asarray(cams_raw["R"][c]), T, first_img.shape[1], first_img.shape[0], name)
        for f in frames:
            rel = Path(ims[f]["ims"][c])
            img = read_png(_need(folder / rel, "image"), None, "image")
            m = read_png(_need(mask_dir / rel.with_suffix(".png"), "mask"), img.shape[:2], "mask")
            m = (m[..., 0] if m.ndim == 3 else m) > 0
            views[(name, f)] = (img[..., :3].astype(np.float32) / 255.0 * m[..., None], m)
    spec = {"model": "smpl", "betas": betas.tolist(), "gender": "neutral"}
    if smpl_path:
        spec["model_path"] = str(smpl_path)
    write_subject(
        out,
        spec,
        cameras,
        motion,
        f"cam{input_camera:02d}",
        frames[0],
        views,
        {"import": {"layout": "zju-mocap", "source": str(folder)}},
    )
    return Path(out)
