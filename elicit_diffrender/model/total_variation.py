"""Total variation of a block of the canonical density and colour grids, on a Warp kernel.

``kernels/total_variation.py`` holds the maths; :func:`total_variation` is differentiable with respect to both
grids. The pure-torch version is :func:`elicit_diffrender.model.torch_reference.total_variation_reference`.
"""

from __future__ import annotations

import torch

from ..core.device import launch, launch_parts, to_warp, warp_scalar
from ..kernels.grid import grid_funcs
from ..kernels.total_variation import total_variation_kernels


def _inverse_pairs(shape: tuple[int, ...]) -> list[float]:
    """1 / (neighbour pairs along each axis) of a block."""
    nodes = shape[0] * shape[1] * shape[2]
    return [shape[a] / ((shape[a] - 1) * nodes) for a in range(3)]


class _TotalVariation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density, color):
        vec3 = grid_funcs(warp_scalar(density.dtype)).vec3
        fwd, _ = total_variation_kernels(warp_scalar(density.dtype))
        rows = density.shape[0] * density.shape[1]  # a thread per (x, y) row
        parts = launch_parts(rows, density.device)
        sums = torch.zeros(parts, dtype=density.dtype, device=density.device)
        args = [to_warp(density), to_warp(color, dtype=vec3), vec3(*_inverse_pairs(density.shape))]
        launch(fwd, rows, density.device, lambda part: [*args, to_warp(sums[part : part + 1])], parts)
        ctx.save_for_backward(density, color)
        return sums.sum()

    @staticmethod
    def backward(ctx, g_tv):
        density, color = ctx.saved_tensors
        vec3 = grid_funcs(warp_scalar(density.dtype)).vec3
        _, bwd = total_variation_kernels(warp_scalar(density.dtype))
        grad_density, grad_color = torch.empty_like(density), torch.empty_like(color)
        args = [to_warp(density), to_warp(color, dtype=vec3), vec3(*_inverse_pairs(density.shape))]
        args += [to_warp(g_tv.reshape(1).to(density.dtype).contiguous())]
        args += [to_warp(grad_density), to_warp(grad_color, dtype=vec3)]
        launch(bwd, density.shape[0] * density.shape[1], density.device, args)
        return grad_density, grad_color


def total_variation(density: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
    """Mean squared neighbour difference, summed over the 3 axes, of a block of the raw density (X, Y, Z) plus
    that of the colour logits (X, Y, Z, 3), averaged over its channels (``kernels/total_variation.py``)."""
    if density.ndim != 3 or color.shape != (*density.shape, 3):
        raise ValueError(f"density (X, Y, Z) and color (X, Y, Z, 3) must match, got {density.shape}, {color.shape}")
    if min(density.shape) < 2:
        raise ValueError(f"a block needs at least 2 nodes per axis, got {tuple(density.shape)}")
    return _TotalVariation.apply(density.contiguous(), color.contiguous())
