"""SMPL / SMPL-X through ``smplx``, for users who have the (licensed) model files.

Model files come from ``model_path`` or the ``ELICIT_SMPL_DIR`` environment variable: either a
file (``SMPL_NEUTRAL.pkl``, ``SMPLX_NEUTRAL.npz``, ...) or a folder holding ``SMPL_<GENDER>.pkl``.
SMPL is already in the world frame used here (+y up, facing +z). SMPL-X uses its 22 body joints.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from ..core.geometry import axis_angle_to_matrix, merge_bones
from ..core.safe_load import UnsafeFileError, load_npz, load_pickle
from .base import PART_NAMES, BodyModel, BodyModelError, PosedBody, apply_global, check_pose

SMPL_JOINTS = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle", "right_ankle",
    "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
]  # fmt: skip

SEMANTIC = {
    "pelvis": "pelvis", "spine_lower": "spine1", "spine_mid": "spine2", "spine_upper": "spine3", "neck": "neck",
    "head": "head", "l_collar": "left_collar", "l_shoulder": "left_shoulder", "l_elbow": "left_elbow",
    "l_wrist": "left_wrist", "r_collar": "right_collar", "r_shoulder": "right_shoulder", "r_elbow": "right_elbow",
    "r_wrist": "right_wrist", "l_hip": "left_hip", "l_knee": "left_knee", "l_ankle": "left_ankle",
    "r_hip": "right_hip", "r_knee": "right_knee", "r_ankle": "right_ankle",
}  # fmt: skip

PARTS = {
    "pelvis": "torso", "spine1": "torso", "spine2": "torso", "spine3": "torso", "neck": "head", "head": "head",
    "left_collar": "left_upper_arm", "left_shoulder": "left_upper_arm", "right_collar": "right_upper_arm",
    "right_shoulder": "right_upper_arm", "left_elbow": "left_forearm", "left_wrist": "left_forearm",
    "left_hand": "left_forearm", "right_elbow": "right_forearm", "right_wrist": "right_forearm",
    "right_hand": "right_forearm", "left_hip": "left_thigh", "right_hip": "right_thigh", "left_knee": "left_shin",
    "left_ankle": "left_shin", "left_foot": "left_shin", "right_knee": "right_shin", "right_ankle": "right_shin",
    "right_foot": "right_shin",
}  # fmt: skip


def resolve_model_file(model: str, gender: str, model_path: str | Path | None) -> Path:
    """The model file for ``model`` (smpl/smplx) and ``gender``, or a clear error."""
    root = model_path or os.environ.get("ELICIT_SMPL_DIR")
    if not root:
        raise BodyModelError(
            f"{model}: model files are not bundled (they are licensed). Download them from "
            f"https://{model}.is.tue.mpg.de and pass their path (body.model_path in subject.json, or "
            f"ELICIT_SMPL_DIR=/path/to/models)"
        )
    if not isinstance(root, (str, Path)):
        raise BodyModelError(f"{model}: model_path must be a path, got a {type(root).__name__}")
    root = Path(root).expanduser()
    if root.is_file():
        if root.suffix not in (".pkl", ".npz"):  # a path from a file's header must not open anything else
            raise BodyModelError(f"{model}: model_path {str(root)!r} is not a model file (.pkl or .npz) or a folder")
        return root
    stem = f"{model.upper()}_{gender.upper()}"
    for ext in (".pkl", ".npz"):
        for candidate in (root / f"{stem}{ext}", root / model / f"{stem}{ext}"):
            if candidate.is_file():
                return candidate
    raise BodyModelError(f"{model}: no {stem}.pkl or {stem}.npz under {root}")


def model_arrays(path: Path) -> dict[str, np.ndarray]:
    """An SMPL-family model file's contents as plain arrays, read without running code from it: ``.npz``
    with pickles disallowed, ``.pkl`` through the restricted unpickler (sparse matrices become dense)."""
    try:
        if path.suffix == ".npz":
            fields = load_npz(path)
            data = {k: fields[k] for k in fields}
        else:
            data = load_pickle(path)
    except UnsafeFileError as exc:
        reason = str(exc).removeprefix(f"{path}: ")
        raise BodyModelError(f"{path}: cannot load as an SMPL-family model file: {reason}") from None
    if not isinstance(data, dict):
        raise BodyModelError(f"{path}: not an SMPL-family model file (it holds a {type(data).__name__})")
    out = {}
    for key, value in data.items():
        value = value.toarray() if hasattr(value, "toarray") else value
        arr = np.asarray(value)
        if arr.dtype.kind == "O":
            raise BodyModelError(f"{path}: field {key!r} is not an array of numbers or strings")
        out[str(key)] = arr
    return out


class SmplBody(BodyModel):
    """SMPL (24 joints) or SMPL-X (22 body joints) with fixed betas."""

    def __init__(
        self, betas=None, gender: str = "neutral", model: str = "smpl", model_path: str | Path | None = None
    ) -> None:
        import smplx
        from smplx.utils import Struct

        if model not in ("smpl", "smplx"):
            raise BodyModelError(f"unknown SMPL family model {model!r}; use 'smpl' or 'smplx'")
        if gender not in ("neutral", "male", "female"):
            raise BodyModelError(f"{model}: gender must be neutral, male or female, got {gender!r}")
        path = resolve_model_file(model, gender, model_path)
        data = model_arrays(path)
        try:
            if model == "smpl":
                layer = smplx.SMPL(model_path=str(path), gender=gender, data_struct=Struct(**data))
            else:  # smplx reads SMPL-X files itself: hand it a copy holding nothing but plain arrays
                with tempfile.TemporaryDirectory() as tmp:
                    plain = Path(tmp) / f"SMPLX_{gender.upper()}.npz"
                    np.savez(plain, **data)
                    layer = smplx.SMPLX(model_path=str(plain), gender=gender, use_pca=False, ext="npz")
        except Exception as exc:  # smplx raises assorted errors for files that are not its models
            raise BodyModelError(f"{path}: cannot load as a {model.upper()} model file ({exc})") from exc
        self.name = model
        n_body = 24 if model == "smpl" else 22
        betas = np.zeros(layer.num_betas) if betas is None else np.asarray(betas, dtype=np.float64).ravel()
        if betas.size > layer.num_betas or not np.isfinite(betas).all():
            raise BodyModelError(f"{model}: betas must be at most {layer.num_betas} finite numbers, got {betas}")
        self.betas = np.pad(betas, (0, layer.num_betas - betas.size))
        self._layer = layer.double()
        self.joint_names = SMPL_JOINTS[:n_body]
        self.parents = layer.parents.cpu().numpy()[:n_body].astype(np.int64)
        self.faces = np.asarray(layer.faces, dtype=np.int64)
        all_parents = layer.parents.cpu().numpy().astype(np.int64)
        mapping = merge_bones(all_parents.tolist(), list(range(n_body))).numpy()  # hands, jaw, eyes -> body
        weights = np.zeros((layer.lbs_weights.shape[0], n_body))
        np.add.at(weights.T, mapping, layer.lbs_weights.detach().cpu().numpy().astype(np.float64).T)
        k = min(4, n_body)
        self.skin_idx = np.argsort(-weights, axis=1)[:, :k]
        w = np.take_along_axis(weights, self.skin_idx, 1)
        self.skin_w = w / np.maximum(w.sum(1, keepdims=True), 1e-12)
        self.semantic = dict(SEMANTIC)
        self.reduced_joints = list(self.joint_names)
        self.part_of_joint = {n: PART_NAMES.index(PARTS[n]) for n in self.joint_names}
        self.model_axes = np.eye(3)
        self._n_body = n_body
        self.rest_vertices = self.pose(self.zero_pose()).vertices

    def pose(
        self, pose: np.ndarray, global_orient: np.ndarray | None = None, transl: np.ndarray | None = None
    ) -> PosedBody:
        from smplx.lbs import batch_rigid_transform, lbs

        pose = check_pose(pose, self.n_joints, self.name)
        layer = self._layer
        full = torch.zeros(1, layer.lbs_weights.shape[1], 3, dtype=torch.float64)
        full[0, : self._n_body] = torch.as_tensor(pose)
        betas = torch.as_tensor(self.betas[None])
        with torch.no_grad():
            verts, _ = lbs(
                betas,
                full.reshape(1, -1),
                layer.v_template,
                layer.shapedirs,
                layer.posedirs,
                layer.J_regressor,
                layer.parents,
                layer.lbs_weights,
                pose2rot=True,
            )
            shaped = layer.v_template + torch.einsum("bl,mkl->bmk", betas, layer.shapedirs)
            joints = torch.einsum("bik,ji->bjk", shaped, layer.J_regressor)
            rots = axis_angle_to_matrix(full)
            _, rel = batch_rigid_transform(rots, joints, layer.parents)
        rest = np.tile(np.eye(4), (joints.shape[1], 1, 1))
        rest[:, :3, 3] = joints[0].numpy()
        frames = rel[0].numpy() @ rest  # G = A @ [I | J_rest]
        return apply_global(verts[0].numpy(), frames[: self._n_body], global_orient, transl)
