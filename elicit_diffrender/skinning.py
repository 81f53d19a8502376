"""Skinning in torch terms: rotations, inverse LBS (observation -> canonical), forward LBS, bone merging.

``inverse_lbs`` and ``forward_lbs`` run the Warp kernels in ``elicit_diffrender.kernels.skinning``
on torch memory and are differentiable with respect to points, bone transforms and weights.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import warp as wp

from .device import launch_parts, load_kernel, split_launch, to_warp, warp_device, warp_grid_frame, warp_scalar
from .kernels.skinning import forward_lbs_kernels, inverse_lbs_kernels

MAX_BONES = 128


def axis_angle_to_matrix(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula (..., 3) -> (..., 3, 3), exact and with finite gradients at every angle.

    Small angles use the Taylor series of sin(t)/t and (1 - cos t)/t^2, so there is no 0/0.
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


class _InverseLBS(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, rot, trans, weights, box, eps):
        dtype, device = points.dtype, points.device
        k = inverse_lbs_kernels(warp_scalar(dtype), weights.shape[0])
        n = points.shape[0]
        out_x = torch.empty_like(points)
        out_fg = torch.empty(n, dtype=dtype, device=device)
        args = [
            to_warp(points, dtype=k.vec3),
            to_warp(rot, dtype=k.mat33),
            to_warp(trans, dtype=k.vec3),
            to_warp(weights),
            *warp_grid_frame(box, weights.shape[1:], k.vec3),
            eps,
        ]
        outs = [to_warp(out_x, dtype=k.vec3), to_warp(out_fg)]
        wdev = warp_device(device)

        def run(b: int, e: int, part: int) -> None:
            wp.launch(k.fwd, dim=e - b, device=wdev, inputs=[b, *args, *outs])

        if n:
            load_kernel(k.fwd, device)
            split_launch(n, launch_parts(n, device), run)
        ctx.save_for_backward(points, rot, trans, weights, out_x, out_fg)
        ctx.box, ctx.eps = box, eps
        return out_x, out_fg

    @staticmethod
    def backward(ctx, g_x, g_fg):
        points, rot, trans, weights, out_x, out_fg = ctx.saved_tensors
        dtype, device = points.dtype, points.device
        k = inverse_lbs_kernels(warp_scalar(dtype), weights.shape[0])
        n = points.shape[0]
        need_points = ctx.needs_input_grad[0]
        need_bones = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        need_weights = ctx.needs_input_grad[3]
        g_x = torch.zeros_like(points) if g_x is None else g_x.contiguous()
        g_fg = torch.zeros(n, dtype=dtype, device=device) if g_fg is None else g_fg.contiguous()
        grad_points = torch.zeros_like(points) if need_points else torch.zeros((0, 3), dtype=dtype, device=device)
        parts = launch_parts(n, device)
        tiny4 = torch.zeros((1, 1, 1, 1), dtype=dtype, device=device)
        # Per-thread buffers for everything several points add into.
        bufs = [
            (torch.zeros_like(weights) if need_weights else tiny4, torch.zeros_like(rot), torch.zeros_like(trans))
            for _ in range(parts)
        ]
        args = [
            to_warp(points, dtype=k.vec3),
            to_warp(rot, dtype=k.mat33),
            to_warp(trans, dtype=k.vec3),
            to_warp(weights),
            *warp_grid_frame(ctx.box, weights.shape[1:], k.vec3),
            ctx.eps,
            to_warp(out_x, dtype=k.vec3),
            to_warp(out_fg),
            to_warp(g_x, dtype=k.vec3),
            to_warp(g_fg),
            int(need_points),
            int(need_weights),
            int(need_bones),
            to_warp(grad_points, dtype=k.vec3),
        ]
        wdev = warp_device(device)

        def run(b: int, e: int, part: int) -> None:
            gw, gr, gt = bufs[part]
            wp.launch(
                k.bwd,
                dim=e - b,
                device=wdev,
                inputs=[b, *args, to_warp(gw), to_warp(gr, dtype=k.mat33), to_warp(gt, dtype=k.vec3)],
            )

        if n:
            load_kernel(k.bwd, device)
            split_launch(n, parts, run)
        gw, gr, gt = bufs[0]
        for w2, r2, t2 in bufs[1:]:
            gw += w2
            gr += r2
            gt += t2
        return (
            grad_points if need_points else None,
            gr if need_bones else None,
            gt if need_bones else None,
            gw if need_weights else None,
            None,
            None,
        )


def inverse_lbs(
    points: torch.Tensor,
    obs_to_canonical: torch.Tensor,
    weights: torch.Tensor,
    box: torch.Tensor,
    eps: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp observation-space points to canonical space (HumanNeRF's inverse LBS).

    Args:
        points: (P, 3) observation-space points.
        obs_to_canonical: (B, 4, 4) per-bone transforms ``G_canonical,b @ inverse(G_observed,b)``.
        weights: (B, X, Y, Z) motion weights, node-aligned over ``box`` in canonical space.
        box: (2, 3) min and max corners of the weight volume.
        eps: floor of the weight sum in the normalisation.

    Returns:
        ``x_c`` (P, 3) canonical points and ``fg`` (P,) the summed bone weights (foreground likelihood).
    """
    n_bones = weights.shape[0]
    if not 1 <= n_bones <= MAX_BONES:
        raise ValueError(f"weights must have 1..{MAX_BONES} bone channels, got {n_bones}")
    if obs_to_canonical.shape != (n_bones, 4, 4):
        raise ValueError(f"obs_to_canonical must be ({n_bones}, 4, 4), got {tuple(obs_to_canonical.shape)}")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (P, 3), got {tuple(points.shape)}")
    if min(weights.shape[1:]) < 2:
        raise ValueError(f"weight volume needs at least 2 nodes per axis, got {tuple(weights.shape[1:])}")
    rot = obs_to_canonical[:, :3, :3].contiguous()
    trans = obs_to_canonical[:, :3, 3].contiguous()
    return _InverseLBS.apply(points.contiguous(), rot, trans, weights.contiguous(), box.detach().cpu(), float(eps))


class _ForwardLBS(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, bone_idx, bone_w, rot, trans):
        k = forward_lbs_kernels(warp_scalar(verts.dtype))
        out = torch.empty_like(verts)
        if verts.shape[0]:
            wp.launch(
                k.fwd,
                dim=verts.shape[0],
                device=warp_device(verts.device),
                inputs=[
                    to_warp(verts, dtype=k.vec3),
                    to_warp(bone_idx),
                    to_warp(bone_w),
                    to_warp(rot, dtype=k.mat33),
                    to_warp(trans, dtype=k.vec3),
                    to_warp(out, dtype=k.vec3),
                ],
            )
        ctx.save_for_backward(verts, bone_idx, bone_w, rot, trans)
        return out

    @staticmethod
    def backward(ctx, g_out):
        verts, bone_idx, bone_w, rot, trans = ctx.saved_tensors
        k = forward_lbs_kernels(warp_scalar(verts.dtype))
        need_verts, _, need_w, need_r, need_t = ctx.needs_input_grad
        need_bones = need_r or need_t
        g_v = torch.zeros_like(verts)
        g_r = torch.zeros_like(rot)
        g_t = torch.zeros_like(trans)
        g_w = torch.zeros_like(bone_w) if need_w else torch.zeros((0, 0), dtype=verts.dtype, device=verts.device)
        if verts.shape[0]:
            wp.launch(
                k.bwd,
                dim=verts.shape[0],
                device=warp_device(verts.device),
                inputs=[
                    to_warp(verts, dtype=k.vec3),
                    to_warp(bone_idx),
                    to_warp(bone_w),
                    to_warp(rot, dtype=k.mat33),
                    to_warp(trans, dtype=k.vec3),
                    to_warp(g_out.contiguous(), dtype=k.vec3),
                    int(need_verts),
                    int(need_bones),
                    int(need_w),
                    to_warp(g_v, dtype=k.vec3),
                    to_warp(g_r, dtype=k.mat33),
                    to_warp(g_t, dtype=k.vec3),
                    to_warp(g_w),
                ],
            )
        return (
            g_v if need_verts else None,
            None,
            g_w if need_w else None,
            g_r if need_bones else None,
            g_t if need_bones else None,
        )


def forward_lbs(
    verts: torch.Tensor, bone_idx: torch.Tensor, bone_w: torch.Tensor, canonical_to_posed: torch.Tensor
) -> torch.Tensor:
    """Pose vertices: ``v' = sum_k w_k (R_b v + t_b)`` over each vertex's K influences.

    Args:
        verts: (V, 3) canonical vertices.
        bone_idx: (V, K) int bone indices; bone_w: (V, K) weights (zero entries are skipped).
        canonical_to_posed: (B, 4, 4) per-bone transforms ``G_observed,b @ inverse(G_canonical,b)``.
    """
    if bone_idx.shape != bone_w.shape or bone_idx.shape[0] != verts.shape[0]:
        raise ValueError(
            f"bone_idx {tuple(bone_idx.shape)} and bone_w {tuple(bone_w.shape)} must be (V, K), V = {verts.shape[0]}"
        )
    rot = canonical_to_posed[:, :3, :3].contiguous()
    trans = canonical_to_posed[:, :3, 3].contiguous()
    return _ForwardLBS.apply(verts.contiguous(), bone_idx.to(torch.int32).contiguous(), bone_w.contiguous(), rot, trans)


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


def merge_weights(weights: torch.Tensor, mapping: torch.Tensor, n_reduced: int) -> torch.Tensor:
    """Sum dense (V, B) skinning weights into (V, n_reduced) through a :func:`merge_bones` map."""
    out = torch.zeros(weights.shape[0], n_reduced, dtype=weights.dtype, device=weights.device)
    return out.index_add_(1, mapping.to(weights.device), weights)
