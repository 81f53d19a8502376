"""Losses of the ELICIT fit, on (N, 3, H, W) images and (N, H, W) masks in torch.

* reconstruction: MSE plus a perceptual term, LPIPS(VGG) when its weights are available, otherwise
  SSIM (weights-free, named as such wherever it is used);
* semantic: ``1 - cos(E(reference), E(render))`` for an image encoder ``E``;
* soft silhouette: ``mean((M - A)^2 * M)`` punishes only missing density inside the body mask, so
  clothing may extend past the body; the one-way edge term pulls the render's silhouette edge
  towards the mask's edge, weighted by the mask edge's distance transform (both as the reference code);
* opacity entropy: a binary-entropy prior on a render's accumulated opacity (not in the paper; a grid
  spreads half-transparent density where an MLP would not).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from ..core.host_reads import on_host


def mse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return F.mse_loss(a, b)


@functools.cache
def _gaussian_taps(size: int, sigma: float, device: str) -> torch.Tensor:
    """(size,) normalised 1-D Gaussian taps (the 2-D window is their outer product)."""
    x = torch.arange(size, dtype=torch.float32, device=device) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 7) -> torch.Tensor:
    """Mean structural similarity of (N, C, H, W) images in [0, 1] (Gaussian window, sigma 1.5, reflected
    borders). The five local means are one separable blur of the stacked images."""
    c = a.shape[1]
    taps = _gaussian_taps(window, 1.5, str(a.device))
    pad = window // 2
    stack = F.pad(torch.cat([a, b, a * a, b * b, a * b], 1), (pad, pad, pad, pad), mode="reflect")
    k = stack.shape[1]
    blurred = F.conv2d(stack, taps.view(1, 1, 1, -1).expand(k, 1, 1, window), groups=k)
    blurred = F.conv2d(blurred, taps.view(1, 1, -1, 1).expand(k, 1, window, 1), groups=k)
    mu_a, mu_b, aa, bb, ab = blurred.split(c, 1)
    var_a = aa - mu_a**2
    var_b = bb - mu_b**2
    cov = ab - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.mean()


def load_lpips(device: torch.device | str = "cpu"):
    """LPIPS(VGG) if the ``lpips`` package and its weights are on disk, else None; plus the reason."""
    try:
        import lpips  # optional: needs its VGG weights on disk

        model = lpips.LPIPS(net="vgg", verbose=False).eval().to(device)
    except Exception as exc:  # not installed, or the weights cannot be loaded offline
        return None, f"LPIPS(VGG) unavailable ({type(exc).__name__}: {str(exc)[:120]})"
    for p in model.parameters():
        p.requires_grad_(False)
    return model, ""


class Perceptual:
    """``1 - SSIM`` or LPIPS(VGG); ``name`` says which one is in use."""

    def __init__(self, kind: str = "auto", device: torch.device | str = "cpu") -> None:
        self.lpips, self.reason = (None, "requested by config") if kind == "ssim" else load_lpips(device)
        if kind == "lpips" and self.lpips is None:
            from ..core.errors import ElicitError

            raise ElicitError(f"perceptual=lpips but {self.reason}")
        self.name = "lpips-vgg" if self.lpips is not None else "ssim (weights-free)"

    def __call__(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        if self.lpips is not None:
            return self.lpips(a * 2 - 1, b * 2 - 1).mean()
        return 1.0 - ssim(a, b)


def semantic_loss(ref: torch.Tensor, render: torch.Tensor) -> torch.Tensor:
    """``1 - cos`` between (N, D) embeddings, averaged."""
    return (1.0 - F.cosine_similarity(ref, render, dim=-1)).mean()


def edge(x: torch.Tensor, size: int = 7) -> torch.Tensor:
    """``maxpool(x) - x``: the band just outside a silhouette (reference code's edge operator)."""
    return F.max_pool2d(x[:, None], size, 1, size // 2)[:, 0] - x


def edge_distance(mask: np.ndarray) -> np.ndarray:
    """sqrt of the distance transform to the mask's edge band (the one-way chamfer weights)."""
    m = torch.as_tensor(mask, dtype=torch.float32)
    with on_host():
        band = edge(m[None])[0].numpy() > 0
    return np.sqrt(ndimage.distance_transform_edt(~band)).astype(np.float32)


def silhouette_loss(alpha: torch.Tensor, mask: torch.Tensor, soft: bool = True) -> torch.Tensor:
    """``mean((M - A)^2 * M)`` (soft: only missing density inside the body) or plain MSE (hard)."""
    err = (mask - alpha) ** 2
    return (err * mask).mean() if soft else err.mean()


def edge_loss(alpha: torch.Tensor, mask: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """``sum(edge(A) * dist) / sum(edge(A))`` with edge(A) kept inside the mask (reference code)."""
    e = edge(alpha) * mask
    return (e * dist).sum() / e.sum().clamp(min=1e-6)


def opacity_entropy(alpha: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """Mean binary entropy of the accumulated opacity: pushes half-transparent pixels to 0 or 1."""
    a = alpha.clamp(eps, 1 - eps)
    return -(a * a.log() + (1 - a) * (1 - a).log()).mean()
