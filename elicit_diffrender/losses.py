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

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage


def mse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return F.mse_loss(a, b)


def _gaussian_window(size: int = 7, sigma: float = 1.5, device=None) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32, device=device) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None]


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 7) -> torch.Tensor:
    """Mean structural similarity of (N, C, H, W) images in [0, 1] (Gaussian window)."""
    c = a.shape[1]
    w = _gaussian_window(window, device=a.device).expand(c, 1, window, window)
    pad = window // 2

    def blur(x):
        return F.conv2d(F.pad(x, (pad, pad, pad, pad), mode="reflect"), w, groups=c)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
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
            from .errors import ElicitError

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
