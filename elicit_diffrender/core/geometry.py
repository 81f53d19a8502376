"""Rotations, rigid transforms and skeleton reduction in plain torch (no Warp): what ``body/`` builds on."""

from __future__ import annotations

from collections.abc import Sequence

import torch


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula (..., 3) -> (..., 3, 3), exact and with finite gradients at every angle.

    ``R = I + a K + b K^2`` with ``K`` the cross-product matrix of ``aa``, ``a = sin(t)/t`` and
    ``b = (1 - cos t)/t^2`` for ``t = |aa|``; below ``t^2 = 1e-6`` both come from their Taylor series,
    so there is no 0/0.
    """
    theta2 = (aa * aa).sum(-1, keepdim=True)
    small = theta2 < 1e-6
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, (1 - torch.cos(theta)) / safe2)
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_axis_angle(rot: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`axis_angle_to_matrix` (no gradient guarantees near 180 degrees)."""
    cos = ((rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    theta = torch.acos(cos)
    vee = torch.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]], -1
    )
    sin = torch.sin(theta)
    small = sin.abs() < 1e-4
    scale = torch.where(small, 0.5 + theta * theta / 12, theta / (2 * torch.where(small, torch.ones_like(sin), sin)))
    aa = vee * scale[..., None]
    # Near 180 degrees vee vanishes: read the axis from (R + R^T)/2 = cos I + (1 - cos) a a^T instead.
    near_pi = (cos < -0.999) & small
    if near_pi.any():
        r, c = rot[near_pi], cos[near_pi][..., None, None]
        eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
        outer = ((r + r.transpose(-1, -2)) / 2 - c * eye) / (1 - c)
        col = outer.diagonal(dim1=-2, dim2=-1).argmax(-1)
        axis = outer[torch.arange(outer.shape[0]), :, col]
        axis = axis / axis.norm(dim=-1, keepdim=True)
        sign = torch.sign((axis * vee[near_pi]).sum(-1))
        sign = torch.where(sign == 0, torch.ones_like(sign), sign)
        aa[near_pi] = axis * theta[near_pi][..., None] * sign[..., None]
    return aa


def rigid_inverse(mat: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid (or similarity-free affine) 4x4 transforms, (..., 4, 4)."""
    rot_inv = torch.linalg.inv(mat[..., :3, :3])
    out = torch.zeros_like(mat)
    out[..., :3, :3] = rot_inv
    out[..., :3, 3] = -(rot_inv @ mat[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1
    return out


def merge_bones(parents: Sequence[int], keep: Sequence[int]) -> torch.Tensor:
    """Map every bone of a rig onto its nearest kept ancestor (itself if kept).

    Returns a (B,) long tensor of indices into ``keep``. The root must be kept.
    """
    slot = {b: i for i, b in enumerate(keep)}
    out = []
    for b in range(len(parents)):
        a = b
        while a not in slot:
            a = parents[a]
            if a < 0:
                raise ValueError(f"bone {b} has no kept ancestor; keep the root bone")
        out.append(slot[a])
    return torch.tensor(out, dtype=torch.long)
