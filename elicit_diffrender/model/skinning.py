"""Skinning in torch terms: inverse LBS (observation -> canonical) and forward LBS, on Warp kernels.

``inverse_lbs`` and ``forward_lbs`` run the Warp kernels in ``elicit_diffrender.kernels.skinning``
on torch memory and are differentiable with respect to points, bone transforms and weights.
"""

from __future__ import annotations

import torch

from ..core.device import grid_frame, host_tensor, launch, launch_parts, partial_sums, to_warp, warp_scalar
from ..kernels.skinning import (
    baked_warp_lookup,
    forward_lbs_backward,
    forward_lbs_forward,
    inverse_lbs_backward,
    inverse_lbs_forward,
    skinning_types,
)

MAX_BONES = 128
MAX_SHARPNESS = 16
# Copies of the bone gradients a CUDA backward pass sums into (point i into copy i % BONE_GRAD_COPIES), so that
# its atomic adds do not all wait on the same few addresses; CPU pieces each have their own buffer instead.
BONE_GRAD_COPIES = 256


def bone_grad_copies(device: torch.device) -> int:
    """How many copies of the bone gradients an inverse-LBS backward pass on ``device`` sums into."""
    return BONE_GRAD_COPIES if device.type == "cuda" else 1


def _warp_arguments(
    rot: torch.Tensor, trans: torch.Tensor, weights: torch.Tensor, box: torch.Tensor, eps: float, gate: float
):
    """The struct both inverse-LBS passes read: bone transforms, the weight volume and where it lies."""
    st = skinning_types(warp_scalar(weights.dtype))
    warp = st.Warp()
    warp.rot = to_warp(rot, dtype=st.mat33)
    warp.trans = to_warp(trans, dtype=st.vec3)
    warp.weights = to_warp(weights)
    warp.frame = grid_frame(st.grid, box, weights.shape[1:])
    warp.eps = eps
    warp.gate = gate
    return st, warp


class _InverseLBS(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points, rot, trans, weights, box, eps, sharpness, gate):
        st, warp = _warp_arguments(rot, trans, weights, box, eps, gate)
        out_x = torch.empty_like(points)
        out_fg = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
        out_norm = torch.empty(points.shape[0], 2, dtype=points.dtype, device=points.device)  # (max w, sum u)
        out_top = torch.empty(points.shape[0], dtype=torch.int32, device=points.device)  # argmax_b w_b
        kernel = inverse_lbs_forward(warp_scalar(points.dtype), weights.shape[0], sharpness)
        args = [to_warp(points, dtype=st.vec3), warp, to_warp(out_x, dtype=st.vec3), to_warp(out_fg)]
        launch(kernel, points.shape[0], points.device, [*args, to_warp(out_norm, dtype=st.vec2), to_warp(out_top)])
        ctx.save_for_backward(points, rot, trans, weights, out_x, out_norm, out_top)
        ctx.box, ctx.eps, ctx.sharpness, ctx.gate = box, eps, sharpness, gate
        return out_x, out_fg

    @staticmethod
    def backward(ctx, g_x, g_fg):
        points, rot, trans, weights, out_x, out_norm, out_top = ctx.saved_tensors
        dtype, device = points.dtype, points.device
        n = points.shape[0]
        need_points = ctx.needs_input_grad[0]
        need_bones = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        need_weights = ctx.needs_input_grad[3]
        g_x = torch.zeros_like(points) if g_x is None else g_x.contiguous()
        g_fg = torch.zeros(n, dtype=dtype, device=device) if g_fg is None else g_fg.contiguous()
        grad_points = torch.zeros_like(points) if need_points else torch.zeros((0, 3), dtype=dtype, device=device)
        parts = launch_parts(n, device)
        copies = bone_grad_copies(device) if need_bones else 1
        tiny4 = torch.zeros((1, 1, 1, 1), dtype=dtype, device=device)
        # Per-thread buffers for everything several points add into.
        weight_sums = partial_sums("weights", weights, parts) if need_weights else [tiny4] * parts
        bufs = [
            (gw, rot.new_zeros((copies * rot.shape[0], 3, 3)), trans.new_zeros((copies * trans.shape[0], 3)))
            for gw in weight_sums
        ]
        st, warp = _warp_arguments(rot, trans, weights, ctx.box, ctx.eps, ctx.gate)
        common = [
            to_warp(points, dtype=st.vec3),
            warp,
            to_warp(out_x, dtype=st.vec3),
            to_warp(out_norm, dtype=st.vec2),
            to_warp(out_top),
            to_warp(g_x, dtype=st.vec3),
            to_warp(g_fg),
            to_warp(grad_points, dtype=st.vec3),
        ]

        def per_part(part: int) -> list:
            gw, gr, gt = bufs[part]
            return [*common, to_warp(gw), to_warp(gr, dtype=st.mat33), to_warp(gt, dtype=st.vec3), copies]

        kernel = inverse_lbs_backward(
            warp_scalar(dtype), weights.shape[0], need_points, need_weights, need_bones, ctx.sharpness
        )
        launch(kernel, n, device, per_part, parts)
        gw, gr, gt = bufs[0]
        for w2, r2, t2 in bufs[1:]:
            gw += w2
            gr += r2
            gt += t2
        if copies > 1:
            gr, gt = gr.view(copies, -1, 3, 3).sum(0), gt.view(copies, -1, 3).sum(0)
        return (
            grad_points if need_points else None,
            gr if need_bones else None,
            gt if need_bones else None,
            gw if need_weights else None,
            None,
            None,
            None,
            None,
        )


def inverse_lbs(
    points: torch.Tensor,
    obs_to_canonical: torch.Tensor,
    weights: torch.Tensor,
    box: torch.Tensor,
    eps: float = 1e-4,
    sharpness: int = 1,
    gate: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp observation-space points to canonical space (HumanNeRF's inverse LBS, optionally sharpened and gated).

    Args:
        points: (P, 3) observation-space points.
        obs_to_canonical: (B, 4, 4) per-bone transforms ``G_canonical,b @ inverse(G_observed,b)``.
        weights: (B, X, Y, Z) motion weights, node-aligned over ``box`` in canonical space.
        box: (2, 3) min and max corners of the weight volume.
        eps: floor of the blend weights' sum in the normalisation.
        sharpness: the integer exponent ``k`` (1..16) of the blend: each bone's candidate ``y_b`` counts
            ``(w_b / max_b w_b)^k``; 1 is HumanNeRF's ``sum_b w_b y_b / sum_b w_b``, larger values let the
            dominant bone decide where candidates of distant bones would average into a ghost
            (``kernels/skinning.py``).
        gate: metres; only candidates within ``gate`` of the dominant bone's candidate are blended (0: all),
            so two bones that both claim a point (a hand beside the hip) do not average it into empty room.

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
    if int(sharpness) != sharpness or not 1 <= sharpness <= MAX_SHARPNESS:
        raise ValueError(f"sharpness must be an integer in 1..{MAX_SHARPNESS}, got {sharpness}")
    if not gate >= 0:
        raise ValueError(f"gate must be >= 0 metres, got {gate}")
    box = host_tensor(box)
    return _InverseLBS.apply(
        points.contiguous(), rot, trans, weights.contiguous(), box, float(eps), int(sharpness), float(gate)
    )


def lookup_baked_warp(
    points: torch.Tensor, table: torch.Tensor, box: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Canonical points (P, 3) and summed bone weights (P,) of observation-space ``points`` (P, 3) from a baked
    warp: ``table`` (X, Y, Z, 4) holds ``(fg * x_c, fg)`` at the nodes of a lattice over ``box`` (2, 3); not
    differentiable (the table is a constant of the fit)."""
    if table.ndim != 4 or table.shape[3] != 4 or min(table.shape[:3]) < 2:
        raise ValueError(f"table must be (X, Y, Z, 4) with at least 2 nodes per axis, got {tuple(table.shape)}")
    k = baked_warp_lookup(warp_scalar(points.dtype))
    st = skinning_types(warp_scalar(points.dtype))
    points = points.detach().contiguous()
    out_x = torch.empty_like(points)
    out_fg = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    frame = grid_frame(st.grid, box, table.shape[:3])
    args = [to_warp(points, dtype=st.vec3), to_warp(table.contiguous(), dtype=k.vec4), frame]
    launch(k.kernel, points.shape[0], points.device, [*args, to_warp(out_x, dtype=st.vec3), to_warp(out_fg)])
    return out_x, out_fg


class _ForwardLBS(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, bone_idx, bone_w, rot, trans):
        st = skinning_types(warp_scalar(verts.dtype))
        out = torch.empty_like(verts)
        args = [to_warp(verts, dtype=st.vec3), to_warp(bone_idx), to_warp(bone_w), to_warp(rot, dtype=st.mat33)]
        args += [to_warp(trans, dtype=st.vec3), to_warp(out, dtype=st.vec3)]
        launch(forward_lbs_forward(warp_scalar(verts.dtype)), verts.shape[0], verts.device, args)
        ctx.save_for_backward(verts, bone_idx, bone_w, rot, trans)
        return out

    @staticmethod
    def backward(ctx, g_out):
        verts, bone_idx, bone_w, rot, trans = ctx.saved_tensors
        st = skinning_types(warp_scalar(verts.dtype))
        need_verts, _, need_w, need_r, need_t = ctx.needs_input_grad
        need_bones = need_r or need_t
        g_v = torch.zeros_like(verts)
        g_r = torch.zeros_like(rot)
        g_t = torch.zeros_like(trans)
        g_w = torch.zeros_like(bone_w) if need_w else torch.zeros((0, 0), dtype=verts.dtype, device=verts.device)
        args = [to_warp(verts, dtype=st.vec3), to_warp(bone_idx), to_warp(bone_w), to_warp(rot, dtype=st.mat33)]
        args += [to_warp(trans, dtype=st.vec3), to_warp(g_out.contiguous(), dtype=st.vec3)]
        args += [to_warp(g_v, dtype=st.vec3), to_warp(g_r, dtype=st.mat33), to_warp(g_t, dtype=st.vec3), to_warp(g_w)]
        kernel = forward_lbs_backward(warp_scalar(verts.dtype), need_verts, need_bones, need_w)
        launch(kernel, verts.shape[0], verts.device, args, parts=1)  # bone gradients use atomics
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
