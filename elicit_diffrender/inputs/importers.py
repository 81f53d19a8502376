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

from ..core.cameras import Camera
from ..core.checks import inside, numeric, read_image, read_mask
from ..core.errors import ElicitError
from ..core.io import folder_in_place
from ..core.safe_load import load_npy, load_npz
from ..data.motions import Motion, builtin_motion, read_zju_params
from ..data.subject import write_subject


class SourceImportError(ElicitError):
    """A source folder that cannot be imported."""


def _need(path: Path, what: str) -> Path:
    if not path.exists():
        raise SourceImportError(f"{path}: {what} not found")
    return path


def _load_npz(path: Path) -> dict:
    return load_npz(_need(path, "parameter file"), SourceImportError)


def _field(params: dict, key: str, shape: tuple, path: Path) -> np.ndarray:
    """A numeric field of ``size(shape)`` numbers (any layout, e.g. CLIFF's (1, 72) pose), reshaped."""
    if key not in params:
        raise SourceImportError(f"{path}: missing field '{key}'")
    arr = numeric(params[key], f"{path} field '{key}'", error=SourceImportError)
    if arr.size != int(np.prod(shape)):
        raise SourceImportError(f"{path}: field '{key}' must have shape {shape}, got {arr.shape}")
    return arr.reshape(shape)


def smpl_joints(params: dict, path: Path, error: type[ElicitError] = SourceImportError) -> np.ndarray:
    """CLIFF's ``pred_joints``: camera-space SMPL joints, (N >= 24, 3); the first 24 are returned."""
    joints = numeric(params["pred_joints"], f"{path} field 'pred_joints'", error=error)
    if joints.size % 3 or joints.size < 72:
        raise error(f"{path}: field 'pred_joints' must hold at least 24 3D joints, got {joints.shape}")
    return joints.reshape(-1, 3)[:24]


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
    from ..body.smpl_model import resolve_model_file

    try:
        resolve_model_file("smpl", "neutral", model_path)
        return True
    except ElicitError:
        return False


def import_elicit_wild(
    folder: str | Path,
    out: str | Path,
    motion: str = "walk_in_place",
    smpl_path: str | None = None,
    force: bool = False,
) -> Path:
    """Import ELICIT's ``gt_image.png`` + ``gt_mask.png`` + ``gt_params.npz`` as a subject, written as a whole
    (a non-empty ``out`` only with ``force``)."""
    with folder_in_place(out, force) as tmp:
        _import_elicit_wild(Path(folder), tmp, motion, smpl_path)
    return Path(out)


def _import_elicit_wild(folder: Path, out: Path, motion: str, smpl_path: str | None) -> None:
    if not folder.is_dir():
        raise SourceImportError(f"{folder}: folder not found")
    rgb, _ = read_image(folder / "gt_image.png", "image", error=SourceImportError)
    h, w = rgb.shape[:2]
    mask = read_mask(folder / "gt_mask.png", "mask", (h, w), error=SourceImportError)
    if not mask.any():
        raise SourceImportError(f"{folder / 'gt_mask.png'}: the mask is empty")
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
        from ..body.smpl_model import SmplBody

        spec = {"model": "smpl", "betas": betas.tolist(), "gender": "neutral"}
        if smpl_path:
            spec["model_path"] = str(smpl_path)
        body = SmplBody(betas, "neutral", "smpl", smpl_path)
        in_pose, in_orient, in_transl = pose, np.zeros(3), transl
        info["body_fit"] = "CLIFF SMPL parameters"
    elif "pred_joints" in params:
        from ..body.fitting import fit_anny_to_smpl_joints

        fit = fit_anny_to_smpl_joints(smpl_joints(params, params_path))
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


def zju_annotations(annots, path: Path, frames: list[int]) -> tuple[list[tuple], list[list[str]]]:
    """ZJU-MoCap's ``annots.npy``: per camera (K, R, T in metres), and per frame the image path of each camera."""
    if not isinstance(annots, dict) or not isinstance(annots.get("cams"), dict) or "ims" not in annots:
        raise SourceImportError(f"{path}: not a ZJU-MoCap annots file (expected a dict with 'cams' and 'ims')")
    raw = annots["cams"]
    for key in ("K", "R", "T"):
        if not isinstance(raw.get(key), (list, tuple, np.ndarray)) or len(raw[key]) == 0:
            raise SourceImportError(f"{path}: field 'cams.{key}' must be a list with one entry per camera")
    n = len(raw["K"])
    if len(raw["R"]) != n or len(raw["T"]) != n:
        raise SourceImportError(f"{path}: fields 'cams.K', 'cams.R' and 'cams.T' must have the same length")
    cams = []
    for c in range(n):
        where = f"{path} camera {c}"
        K = numeric(raw["K"][c], f"{where} field 'K'", (3, 3), SourceImportError)
        R = numeric(raw["R"][c], f"{where} field 'R'", (3, 3), SourceImportError)
        T = numeric(raw["T"][c], f"{where} field 'T'", error=SourceImportError).ravel()
        if T.shape != (3,):
            raise SourceImportError(f"{where} field 'T': expected 3 numbers, got {T.shape}")
        cams.append((K, R, T / 1000.0))  # millimetres
    ims = annots["ims"]
    out = []
    for f in range(len(ims) if isinstance(ims, (list, tuple, np.ndarray)) else 0):
        entry = ims[f].get("ims") if isinstance(ims[f], dict) else None
        listed = isinstance(entry, (list, tuple, np.ndarray)) and len(entry) == n
        if not listed or not all(isinstance(p, str) for p in entry):
            raise SourceImportError(f"{path}: field 'ims[{f}].ims' must list {n} image paths, one per camera")
        out.append(list(entry))
    bad = [f for f in frames if not 0 <= f < len(out)]
    if bad:
        raise SourceImportError(f"{path}: frames {bad[:5]} are not in 'ims' (0..{len(out) - 1})")
    return cams, out


def import_zju(
    folder: str | Path,
    out: str | Path,
    frames: list[int],
    input_camera: int = 0,
    smpl_path: str | None = None,
    force: bool = False,
) -> Path:
    """Import ZJU-MoCap frames (all cameras) as a subject with an SMPL body (needs model files), written as a
    whole (a non-empty ``out`` only with ``force``)."""
    with folder_in_place(out, force) as tmp:
        _import_zju(Path(folder), tmp, frames, input_camera, smpl_path)
    return Path(out)


def _import_zju(folder: Path, out: Path, frames: list[int], input_camera: int, smpl_path: str | None) -> None:
    annots_path = _need(folder / "annots.npy", "annots.npy")
    cams, ims = zju_annotations(load_npy(annots_path, SourceImportError), annots_path, frames)
    if not 0 <= input_camera < len(cams):
        raise SourceImportError(f"{annots_path}: input camera {input_camera} out of range (0..{len(cams) - 1})")
    params_dir = folder / "new_params" if (folder / "new_params").is_dir() else folder / "params"
    first_path = _need(params_dir / f"{frames[0]}.npy", "SMPL parameters")
    first = load_npy(first_path, SourceImportError)
    shapes = first.get("shapes", np.zeros(10)) if isinstance(first, dict) else np.zeros(10)
    betas = numeric(shapes, f"{first_path} field 'shapes'", error=SourceImportError).ravel()[:10]
    from ..body.smpl_model import SmplBody

    body = SmplBody(betas, "neutral", "smpl", smpl_path)
    motion = read_zju_params(params_dir, body, frames)
    cameras, views = {}, {}
    mask_dir = folder / "mask_cihp" if (folder / "mask_cihp").is_dir() else folder / "mask"
    for c, (K, R, T) in enumerate(cams):
        name = f"cam{c:02d}"
        for f in frames:  # image paths are relative to the ZJU folder, and stay inside it (masks follow them)
            where = f"{annots_path} field 'ims[{f}].ims'"
            inside(folder, ims[f][c], where, SourceImportError)
            inside(mask_dir, Path(ims[f][c]).with_suffix(".png"), where, SourceImportError)
        first_img, _ = read_image(folder / ims[frames[0]][c], "image", error=SourceImportError)
        cameras[name] = Camera(K, R, T, first_img.shape[1], first_img.shape[0], name)
        for f in frames:
            rel = Path(ims[f][c])
            img, _ = read_image(folder / rel, "image", first_img.shape[:2], error=SourceImportError)
            m = read_mask(mask_dir / rel.with_suffix(".png"), "mask", img.shape[:2], error=SourceImportError)
            views[(name, f)] = (img * m[..., None], m)
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
