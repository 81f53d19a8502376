"""Functional volume rendering over an explicit grid (nerfacc-style): sample rays, then composite.

``sample_rays`` places stratified samples inside a box, optionally skipping cells an occupancy grid
marks empty (and warping them to canonical space by a pose's baked warp), and returns them packed per
ray. ``composite`` reads density and colour from a grid at any per-sample positions (for example samples
warped to canonical space) and alpha-composites them.
Both run Warp kernels on torch memory through DLPack; ``composite`` is differentiable with respect
to the grids, the positions and the foreground likelihood.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.device import grid_frame, host_box, host_tensor, launch, launch_parts, partial_sums, to_warp, warp_scalar
from ..kernels.raymarch import (
    ACT_RELU,
    ACT_SOFTPLUS,
    ORDER_CELLS,
    ORDER_MIN_RAYS,
    composite_backward,
    composite_forward,
    composite_structs,
    ray_order_keys,
    sampling_kernels,
)

ACTIVATIONS = {"relu": ACT_RELU, "softplus": ACT_SOFTPLUS}
OUTPUTS = ("rgb", "alpha", "depth")


@dataclass
class RaySamples:
    """Samples packed per ray: ray ``r`` owns ``offsets[r]:offsets[r+1]``."""

    offsets: torch.Tensor  # (R+1,) int32
    positions: torch.Tensor  # (P, 3)
    t_mid: torch.Tensor  # (P,) distance along the (unit) ray
    deltas: torch.Tensor  # (P,) segment length
    ray_ids: torch.Tensor  # (P,) int32
    # With a baked warp (:class:`BakedWarp`): each sample's foreground likelihood, and ``positions`` are canonical
    fg: torch.Tensor | None = None

    @property
    def n_rays(self) -> int:
        return self.offsets.shape[0] - 1

    @property
    def n_samples(self) -> int:
        return self.positions.shape[0]


@dataclass
class BakedWarp:
    """A pose's inverse warp baked into a look-up table, for :func:`sample_rays` to warp its samples with.

    ``table`` (X, Y, Z, 4) over ``box`` (2, 3), as :func:`elicit_diffrender.model.skinning.lookup_baked_warp` reads it.
    """

    table: torch.Tensor
    box: torch.Tensor


def sample_rays(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    box: torch.Tensor,
    n_samples: int,
    jitter: bool = False,
    seed: int = 0,
    occupancy: torch.Tensor | None = None,
    warp: BakedWarp | None = None,
) -> RaySamples:
    """Stratified samples between each ray's entry and exit of ``box`` (2, 3).

    ``dirs`` should be unit length so that ``t_mid`` and ``deltas`` are distances. With ``jitter``
    each sample moves randomly inside its bin (training); without, it sits at the bin centre.
    ``occupancy`` (uint8, any resolution, covering ``box``) drops samples in empty cells. With ``warp``
    the samples come out in canonical space with their foreground likelihood (``fg``); samples whose
    likelihood is 0 are dropped, since they would add nothing to a render.
    """
    if origins.shape != dirs.shape or origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins and dirs must both be (R, 3), got {tuple(origins.shape)} and {tuple(dirs.shape)}")
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    device, dtype = origins.device, origins.dtype
    baked = warp is not None
    k = sampling_kernels(warp_scalar(dtype), bool(jitter), occupancy is not None, baked)
    n_rays = origins.shape[0]
    if occupancy is None:
        occ_t = torch.zeros((1, 1, 1), dtype=torch.uint8, device=device)
    else:
        occ_t = occupancy.to(device=device, dtype=torch.uint8).contiguous()
    lo, hi = host_box(box)
    rays = [
        to_warp(origins.contiguous(), dtype=k.vec3),
        to_warp(dirs.contiguous(), dtype=k.vec3),
        k.vec3(*lo),
        k.vec3(*hi),
        n_samples,
        seed,
        to_warp(occ_t),
    ]
    baked_args = k.BakedWarp()
    if baked:
        baked_args.table = to_warp(warp.table.contiguous(), dtype=k.vec4)
        baked_args.frame = grid_frame(k.grid, warp.box, warp.table.shape[:3])
    n_kept = n_rays * n_samples if baked else 0
    counts = torch.empty(n_rays, dtype=torch.int32, device=device)
    kept_t = torch.empty(n_rays * n_samples, dtype=dtype, device=device)
    kept_x = torch.empty((n_kept, 3), dtype=dtype, device=device)
    kept_fg = torch.empty(n_kept, dtype=dtype, device=device)
    steps = torch.empty(n_rays, dtype=dtype, device=device)
    kept = [to_warp(kept_t), to_warp(kept_x, dtype=k.vec3), to_warp(kept_fg)]
    launch(k.count, n_rays, device, [*rays, baked_args, to_warp(counts), *kept, to_warp(steps)])
    offsets = torch.zeros(n_rays + 1, dtype=torch.int32, device=device)
    torch.cumsum(counts, 0, out=offsets[1:])
    total = int(offsets[-1].item())  # a step's one host sync: the sample count sizes the buffers below
    positions = torch.empty((total, 3), dtype=dtype, device=device)
    t_mid = torch.empty(total, dtype=dtype, device=device)
    deltas = torch.empty(total, dtype=dtype, device=device)
    ray_ids = torch.empty(total, dtype=torch.int32, device=device)
    fg = torch.empty(total if baked else 0, dtype=dtype, device=device)
    if total:
        outs = [to_warp(t) for t in (offsets, t_mid, deltas, ray_ids)]
        outs += [to_warp(positions, dtype=k.vec3), to_warp(fg)]
        launch(k.fill, n_rays, device, [*rays[:2], n_samples, *kept, to_warp(steps), *outs])
    return RaySamples(offsets, positions, t_mid, deltas, ray_ids, fg if baked else None)


def _empty(*shape: int, like: torch.Tensor) -> torch.Tensor:
    return torch.zeros(shape, dtype=like.dtype, device=like.device)


def coherent_ray_order(offsets: torch.Tensor, positions: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """(R,) int32: the rays ordered so that neighbours read the same part of a grid over ``box``, by the Morton
    code of the cell holding each ray's middle sample (``kernels.raymarch.ray_order_keys``), rays in the same
    cell in their given order, rays without samples last. Fewer than ``ORDER_MIN_RAYS`` rays keep their order."""
    n_rays = offsets.shape[0] - 1
    if n_rays < ORDER_MIN_RAYS:
        return torch.arange(n_rays, dtype=torch.int32, device=offsets.device)
    keys = torch.empty(n_rays, dtype=torch.int32, device=offsets.device)
    st = composite_structs(warp_scalar(positions.dtype))
    frame = grid_frame(st.grid, box, (ORDER_CELLS + 1,) * 3)
    args = [to_warp(offsets), to_warp(positions, dtype=st.vec3), frame, to_warp(keys)]
    launch(ray_order_keys(warp_scalar(positions.dtype)), n_rays, offsets.device, args)
    return torch.argsort(keys, stable=True).to(torch.int32)


def _ray_arguments(st, order, positions, fg, density, color, offsets, t_mid, deltas, box):
    """The two structs both compositing passes read: the packed samples and the radiance grid."""
    samples = st.RaySamples()
    samples.order = to_warp(order)
    samples.offsets = to_warp(offsets)
    samples.positions = to_warp(positions, dtype=st.vec3)
    samples.t_mid = to_warp(t_mid)
    samples.deltas = to_warp(deltas)
    samples.fg = to_warp(fg)
    grid = st.RadianceGrid()
    grid.density = to_warp(density)
    grid.color = to_warp(color, dtype=st.vec3)
    grid.frame = grid_frame(st.grid, box, density.shape)
    return samples, grid


def _saved(st, trans, raw, extinction, color, n_used):
    """The forward pass's per-sample record for the backward (see ``kernels.raymarch``'s ``Saved``)."""
    saved = st.Saved()
    saved.trans, saved.raw, saved.extinction = to_warp(trans), to_warp(raw), to_warp(extinction)
    saved.color, saved.n_used = to_warp(color, dtype=st.vec3), to_warp(n_used)
    return saved


def _ray_outputs(st, rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor):
    out = st.RayOutputs()
    out.rgb, out.alpha, out.depth = to_warp(rgb, dtype=st.vec3), to_warp(alpha), to_warp(depth)
    return out


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions, fg, density, color, offsets, t_mid, deltas, box, act, t_thresh, need_rgb, need_depth):
        device, dtype = positions.device, positions.dtype
        st = composite_structs(warp_scalar(dtype))
        n_rays = offsets.shape[0] - 1
        save = any(ctx.needs_input_grad[:4])
        has_fg = fg is not None
        rgb = _empty(n_rays if need_rgb else 0, 3, like=positions)
        acc = _empty(n_rays, like=positions)
        depth = _empty(n_rays if need_depth else 0, like=positions)
        fg_t = fg.contiguous() if has_fg else _empty(0, like=positions)
        color_t = color.contiguous() if need_rgb else _empty(1, 1, 1, 3, like=positions)
        n_saved = positions.shape[0] if save else 0
        trans, raw, extinction = (torch.empty(n_saved, dtype=dtype, device=device) for _ in range(3))
        saved_color = torch.empty(n_saved if need_rgb else 0, 3, dtype=dtype, device=device)
        n_used = torch.zeros(n_rays if save else 0, dtype=torch.int32, device=device)
        saved = _saved(st, trans, raw, extinction, saved_color, n_used)
        order = coherent_ray_order(offsets, positions, box)
        samples, grid = _ray_arguments(st, order, positions, fg_t, density, color_t, offsets, t_mid, deltas, box)
        kernel = composite_forward(warp_scalar(dtype), act, has_fg, need_rgb, need_depth, save)
        args = [samples, grid, t_thresh, _ray_outputs(st, rgb, acc, depth), saved]
        launch(kernel, n_rays, device, args)
        ctx.save_for_backward(
            order,
            positions,
            fg_t,
            density,
            color_t,
            offsets,
            t_mid,
            deltas,
            trans,
            raw,
            extinction,
            saved_color,
            n_used,
        )
        ctx.box, ctx.act, ctx.has_fg, ctx.need_rgb, ctx.need_depth = box, act, has_fg, need_rgb, need_depth
        ctx.mark_non_differentiable(*([] if need_rgb else [rgb]), *([] if need_depth else [depth]))
        return rgb, acc, depth

    @staticmethod
    def backward(ctx, g_rgb, g_acc, g_depth):
        order, positions, fg_t, density, color_t, offsets, t_mid, deltas, *kept = ctx.saved_tensors
        device, dtype = positions.device, positions.dtype
        st = composite_structs(warp_scalar(dtype))
        n_rays = offsets.shape[0] - 1
        need_pos = ctx.needs_input_grad[0]
        need_grid = ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
        g_rgb = g_rgb.contiguous() if ctx.need_rgb else _empty(0, 3, like=positions)
        g_depth = g_depth.contiguous() if ctx.need_depth else _empty(0, like=positions)
        grad_pos = torch.zeros_like(positions) if need_pos else _empty(0, 3, like=positions)
        grad_fg = torch.zeros_like(fg_t)
        n_parts = launch_parts(n_rays, device)
        if need_grid:  # one gradient buffer per thread, summed into the first afterwards
            density_sums = partial_sums("density", density, n_parts)
            grids = list(zip(density_sums, partial_sums("color", color_t, n_parts), strict=True))
        else:
            grids = [(_empty(1, 1, 1, like=positions), _empty(1, 1, 1, 3, like=positions))] * n_parts
        samples, grid = _ray_arguments(st, order, positions, fg_t, density, color_t, offsets, t_mid, deltas, ctx.box)
        saved = _saved(st, *kept)
        grad_out = _ray_outputs(st, g_rgb, g_acc.contiguous(), g_depth)

        def gradients(part: int):
            out = st.Gradients()
            out.density = to_warp(grids[part][0])
            out.color = to_warp(grids[part][1], dtype=st.vec3)
            out.positions = to_warp(grad_pos, dtype=st.vec3)
            out.fg = to_warp(grad_fg)
            return [samples, grid, saved, grad_out, out]

        kernel = composite_backward(
            warp_scalar(dtype), ctx.act, ctx.has_fg, ctx.need_rgb, ctx.need_depth, need_grid, need_pos
        )
        launch(kernel, n_rays, device, gradients, n_parts)
        grad_density = grad_color = None
        if need_grid:
            grad_density = grids[0][0]
            grad_color = grids[0][1]
            for gd, gc in grids[1:]:
                grad_density += gd
                grad_color += gc
            if not ctx.need_rgb:
                grad_color = None
        return (
            grad_pos if need_pos else None,
            grad_fg if ctx.has_fg else None,
            grad_density,
            grad_color,
            *[None] * 8,
        )


def composite(
    samples: RaySamples,
    density: torch.Tensor,
    color: torch.Tensor | None,
    box: torch.Tensor,
    positions: torch.Tensor | None = None,
    fg: torch.Tensor | None = None,
    outputs: tuple[str, ...] = ("rgb", "alpha"),
    activation: str = "softplus",
    t_thresh: float = 1e-4,
    density_scale: float = 1.0,
) -> dict[str, torch.Tensor]:
    """Alpha-composite grid samples along each ray.

    Args:
        samples: packed samples from :func:`sample_rays`.
        density: raw density grid (X, Y, Z), node-aligned over ``box``.
        color: raw colour grid (X, Y, Z, 3) (sigmoid-activated), or None for alpha/depth only.
        box: (2, 3) min and max corners of the grids.
        positions: where to read the grids per sample (default: the samples' own positions); pass
            canonical positions from the skinning warp here.
        fg: optional per-sample foreground likelihood multiplying each alpha (HumanNeRF).
        outputs: any of "rgb", "alpha", "depth"; only these are computed. "alpha" is always returned.
        activation: "relu" (HumanNeRF) or "softplus" for the density.
        t_thresh: stop a ray once its transmittance drops below this (0 disables early stopping).
        density_scale: multiplies every activated density (e.g. 1 / voxel size, so that raw values
            are optical depths per grid cell).

    Returns:
        {"rgb": (R, 3) premultiplied colour, "alpha": (R,), "depth": (R,) sum of weight * t}.
        Composite a background with ``rgb + (1 - alpha)[:, None] * bg``.
    """
    unknown = set(outputs) - set(OUTPUTS)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {OUTPUTS}")
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    need_rgb = "rgb" in outputs
    if need_rgb and color is None:
        raise ValueError("outputs include 'rgb' but no colour grid was given")
    if min(density.shape) < 2:
        raise ValueError(f"density grid needs at least 2 nodes per axis, got {tuple(density.shape)}")
    if need_rgb and color.shape != (*density.shape, 3):
        raise ValueError(f"colour grid must be {(*density.shape, 3)}, got {tuple(color.shape)}")
    pos = samples.positions if positions is None else positions
    if pos.shape != samples.positions.shape:
        raise ValueError(f"positions must be {tuple(samples.positions.shape)}, got {tuple(pos.shape)}")
    rgb, acc, depth = _Composite.apply(
        pos.contiguous(),
        fg,
        density.contiguous(),
        color if need_rgb else None,
        samples.offsets,
        samples.t_mid,
        samples.deltas if density_scale == 1.0 else samples.deltas * density_scale,
        host_tensor(box),
        ACTIVATIONS[activation],
        float(t_thresh),
        need_rgb,
        "depth" in outputs,
    )
    out = {"alpha": acc}
    if need_rgb:
        out["rgb"] = rgb
    if "depth" in outputs:
        out["depth"] = depth
    return out
