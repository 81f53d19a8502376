"""Straightforward pure-torch versions of the Warp kernels' math.

They are the references the tests compare against and the baselines the kernel benchmark times;
nothing in the pipeline calls them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .volume import RaySamples


def trilinear(grid: torch.Tensor, box: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Node-aligned trilinear look-up of a (C, X, Y, Z) grid at (P, 3) points; zero outside the box."""
    lo, hi = box[0].to(points), box[1].to(points)
    norm = 2 * (points - lo) / (hi - lo) - 1
    # grid_sample's last coordinate indexes the first spatial dim, so reverse (x, y, z).
    coords = norm.flip(-1).reshape(1, 1, 1, -1, 3)
    out = F.grid_sample(grid[None], coords, mode="bilinear", padding_mode="zeros", align_corners=True)
    inside = ((norm >= -1) & (norm <= 1)).all(-1)
    return out.reshape(grid.shape[0], -1) * inside


def composite_reference(
    samples: RaySamples,
    density: torch.Tensor,
    color: torch.Tensor | None,
    box: torch.Tensor,
    positions: torch.Tensor | None = None,
    fg: torch.Tensor | None = None,
    activation: str = "softplus",
) -> dict[str, torch.Tensor]:
    """Same outputs as :func:`elicit_diffrender.model.volume.composite` without early stopping."""
    pos = samples.positions if positions is None else positions
    raw = trilinear(density[None], box, pos)[0]
    sigma = torch.relu(raw) if activation == "relu" else F.softplus(raw)
    alpha = 1 - torch.exp(-sigma * samples.deltas)
    if fg is not None:
        alpha = alpha * fg
    counts = (samples.offsets[1:] - samples.offsets[:-1]).long()
    n_rays, width = counts.shape[0], int(counts.max().item()) if counts.numel() else 0
    ray = samples.ray_ids.long()
    slot = torch.arange(pos.shape[0], device=pos.device) - samples.offsets[:-1].long()[ray]
    dense_alpha = torch.zeros(n_rays, width + 1, dtype=pos.dtype, device=pos.device)
    dense_alpha = dense_alpha.index_put((ray, slot), alpha)
    trans = torch.cumprod(torch.cat([torch.ones_like(dense_alpha[:, :1]), 1 - dense_alpha[:, :-1]], 1), 1)
    weights = (trans * dense_alpha)[ray, slot]
    out = {"alpha": torch.zeros(n_rays, dtype=pos.dtype, device=pos.device).index_add(0, ray, weights)}
    if color is not None:
        rgb = torch.sigmoid(trilinear(color.permute(3, 0, 1, 2), box, pos).T)
        out["rgb"] = torch.zeros(n_rays, 3, dtype=pos.dtype, device=pos.device).index_add(
            0, ray, weights[:, None] * rgb
        )
    out["depth"] = torch.zeros(n_rays, dtype=pos.dtype, device=pos.device).index_add(0, ray, weights * samples.t_mid)
    return out


def inverse_lbs_reference(
    points: torch.Tensor,
    obs_to_canonical: torch.Tensor,
    weights: torch.Tensor,
    box: torch.Tensor,
    eps: float = 1e-4,
    sharpness: float = 1.0,
    gate: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Same outputs as :func:`elicit_diffrender.model.skinning.inverse_lbs`."""
    y = torch.einsum("bij,pj->bpi", obs_to_canonical[:, :3, :3], points) + obs_to_canonical[:, None, :3, 3]
    lo, hi = box[0].to(points), box[1].to(points)
    norm = 2 * (y - lo) / (hi - lo) - 1
    coords = norm.flip(-1)[:, None, None]  # (B, 1, 1, P, 3)
    w = F.grid_sample(weights[:, None], coords, mode="bilinear", padding_mode="zeros", align_corners=True)
    w = w.reshape(weights.shape[0], -1) * ((norm >= -1) & (norm <= 1)).all(-1)
    fg = w.sum(0)
    top, arg = w.detach().max(0)  # x_c does not depend on a common scale of the weights
    # A point outside every bone's weights has top = 0; divide by 1 there, or the unused branch's 0 / 0 makes
    # the gradient NaN.
    u = torch.where(top > 0, w / torch.where(top > 0, top, torch.ones_like(top)), torch.zeros_like(w)) ** sharpness
    if gate > 0:  # only candidates near the dominant bone's are blended
        y_top = y.detach()[arg, torch.arange(y.shape[1])]
        u = torch.where((y.detach() - y_top).square().sum(-1) <= gate**2, u, torch.zeros_like(u))
    x_c = (u[..., None] * y).sum(0) / u.sum(0).clamp(min=eps)[:, None]
    return x_c, fg


def forward_lbs_reference(
    verts: torch.Tensor, bone_idx: torch.Tensor, bone_w: torch.Tensor, canonical_to_posed: torch.Tensor
) -> torch.Tensor:
    """Same output as :func:`elicit_diffrender.model.skinning.forward_lbs`."""
    mats = canonical_to_posed[bone_idx.long()]  # (V, K, 4, 4)
    posed = torch.einsum("vkij,vj->vki", mats[..., :3, :3], verts) + mats[..., :3, 3]
    return (bone_w[..., None] * posed).sum(1)


def total_variation_reference(density: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
    """Same output as :func:`elicit_diffrender.model.total_variation.total_variation`."""
    loss = torch.zeros((), dtype=density.dtype, device=density.device)
    for grid in (density, color):
        for axis in range(3):
            loss = loss + torch.diff(grid, dim=axis).pow(2).mean()
    return loss
