"""Fit Anny (phenotype, pose, global placement) to 3D SMPL joint positions.

Used where a photo comes with an SMPL estimate (CLIFF's ``pred_joints``) but the licensed SMPL model
files are not available: Anny's joints are matched to the SMPL joints they correspond to, with a
Procrustes start on the torso (so the body cannot start mirrored) and priors that keep the pose
near rest and the phenotype near average.
"""

from __future__ import annotations

import numpy as np
import torch

from ..skinning import axis_angle_to_matrix, matrix_to_axis_angle
from .anny_model import ANNY_TO_WORLD, AnnyBody, anny_model

# SMPL joint index -> Anny joint, for the joints whose anatomy agrees between the two rigs.
SMPL_TO_ANNY = {
    0: "root", 1: "upperleg01.L", 2: "upperleg01.R", 4: "lowerleg01.L", 5: "lowerleg01.R", 7: "foot.L",
    8: "foot.R", 12: "neck01", 15: "head", 16: "upperarm01.L", 17: "upperarm01.R", 18: "lowerarm01.L",
    19: "lowerarm01.R", 20: "wrist.L", 21: "wrist.R",
}  # fmt: skip
TORSO = (0, 1, 2, 12, 16, 17)
FREE_JOINTS = (
    "spine04",
    "spine03",
    "spine01",
    "neck01",
    "head",
    "clavicle.L",
    "clavicle.R",
    "upperarm01.L",
    "upperarm01.R",
    "lowerarm01.L",
    "lowerarm01.R",
    "upperleg01.L",
    "upperleg01.R",
    "lowerleg01.L",
    "lowerleg01.R",
    "foot.L",
    "foot.R",
)


def procrustes(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising |R src + t - dst| (no scale, no reflection)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((dst - cd).T @ (src - cs))
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, 1.0, d]) @ vt
    return rot, cd - rot @ cs


def fit_anny_to_smpl_joints(target: np.ndarray, steps: int = 300) -> dict:
    """Fit Anny to (24+, 3) SMPL joints in any world frame; returns phenotype, pose and the fit error (m)."""
    target = np.asarray(target, dtype=np.float64)[:24]
    if target.shape != (24, 3) or not np.isfinite(target).all():
        raise ValueError(f"expected 24 finite SMPL joints (24, 3), got {target.shape}")
    model = anny_model()
    names = list(model.bone_labels)
    smpl_ids = list(SMPL_TO_ANNY)
    anny_ids = [names.index(SMPL_TO_ANNY[i]) for i in smpl_ids]
    free = [names.index(n) for n in FREE_JOINTS]
    labels = list(model.phenotype_labels)
    a4 = torch.eye(4, dtype=torch.float64)
    a4[:3, :3] = torch.as_tensor(ANNY_TO_WORLD)

    def joints(rotvecs: torch.Tensor, pheno_logits: torch.Tensor) -> torch.Tensor:
        params = torch.eye(4, dtype=torch.float64).repeat(1, len(names), 1, 1)
        full = torch.zeros(len(names), 3, dtype=torch.float64).index_copy(0, torch.tensor(free), rotvecs)
        params = params.clone()
        params[0, :, :3, :3] = axis_angle_to_matrix(full)
        pheno = {k: torch.sigmoid(pheno_logits[i])[None] for i, k in enumerate(labels)}
        out = model(pose_parameters=params, phenotype_kwargs=pheno)
        heads = (a4 @ out["bone_poses"][0])[:, :3, 3]
        return heads[anny_ids]

    # Start: rest pose, placed by Procrustes on the torso joints.
    rot0 = torch.zeros(len(free), 3, dtype=torch.float64)
    logits = torch.zeros(len(labels), dtype=torch.float64)
    with torch.no_grad():
        j0 = joints(rot0, logits).numpy()
    torso = [smpl_ids.index(i) for i in TORSO]
    r_init, t_init = procrustes(j0[torso], target[smpl_ids][torso])
    rotvecs = rot0.clone().requires_grad_()
    logits = logits.clone().requires_grad_()
    g_rot = matrix_to_axis_angle(torch.as_tensor(r_init)).clone().requires_grad_()
    g_t = torch.as_tensor(t_init).clone().requires_grad_()
    goal = torch.as_tensor(target[smpl_ids])
    opt = torch.optim.Adam([rotvecs, logits, g_rot, g_t], lr=0.03)
    for step in range(steps):
        opt.zero_grad()
        j = joints(rotvecs, logits) @ axis_angle_to_matrix(g_rot).T + g_t
        loss = ((j - goal) ** 2).sum(1).mean() + 1e-4 * (rotvecs**2).sum() + 1e-4 * (logits**2).sum()
        loss.backward()
        opt.step()
        if step == steps // 2:
            for group in opt.param_groups:
                group["lr"] = 0.01
    with torch.no_grad():
        j = joints(rotvecs, logits) @ axis_angle_to_matrix(g_rot).T + g_t
        err = (j - goal).norm(dim=1).numpy()
    phenotype = {k: float(torch.sigmoid(logits[i].detach())) for i, k in enumerate(labels)}
    pose = np.zeros((len(names), 3))
    pose[free] = rotvecs.detach().numpy()
    body = AnnyBody(phenotype)
    # The fitted joints are Anny's world frame moved by (g_rot, g_t): express that as global orient + transl.
    return {
        "phenotype": phenotype,
        "pose": pose,
        "global_orient": g_rot.detach().numpy(),
        "transl": g_t.detach().numpy(),
        "joint_error_m": err,
        "body": body,
    }
