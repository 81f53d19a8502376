"""Losses on hand-made cases: values and the direction of their gradients."""

import torch

from elicit_diffrender.model.losses import (
    Perceptual,
    edge_distance,
    edge_loss,
    opacity_entropy,
    semantic_loss,
    silhouette_loss,
    ssim,
)


def square_mask(n=32, lo=8, hi=24):
    m = torch.zeros(1, n, n)
    m[:, lo:hi, lo:hi] = 1
    return m


def test_soft_silhouette_only_punishes_missing_density_inside_the_body():
    mask = square_mask()
    assert silhouette_loss(mask.clone(), mask) == 0
    # Clothing outside the body costs nothing with the soft loss, but does with the hard one.
    wider = square_mask(lo=4, hi=28)
    assert silhouette_loss(wider, mask, soft=True) == 0
    assert silhouette_loss(wider, mask, soft=False) > 0
    alpha = torch.zeros(1, 32, 32, requires_grad=True)
    silhouette_loss(alpha, mask).backward()
    assert (alpha.grad[mask > 0] < 0).all()  # more density inside the body lowers the loss
    assert (alpha.grad[mask == 0] == 0).all()  # outside, nothing pulls


def test_edge_term_pulls_a_shrunken_silhouette_outwards():
    mask = square_mask()
    dist = torch.as_tensor(edge_distance(mask[0].numpy() > 0.5))[None]
    small = square_mask(lo=12, hi=20)
    assert edge_loss(mask.clone(), mask, dist) < 1e-6  # matching silhouettes: nothing left inside
    assert edge_loss(small, mask, dist) > edge_loss(square_mask(lo=10, hi=22), mask, dist) > 0
    alpha = small.clone().requires_grad_()
    edge_loss(alpha, mask, dist).backward()
    ring = (torch.nn.functional.max_pool2d(small[None], 3, 1, 1)[0] - small) > 0  # just outside the render
    assert alpha.grad[ring].mean() < 0  # growing the render into the body lowers the loss


def test_opacity_entropy_pushes_half_transparent_pixels_to_empty_or_solid():
    solid_or_empty = torch.tensor([0.0, 1.0, 1.0, 0.0])
    assert opacity_entropy(solid_or_empty) < 2e-3
    assert abs(float(opacity_entropy(torch.full((4,), 0.5))) - float(torch.log(torch.tensor(2.0)))) < 1e-6
    alpha = torch.tensor([0.0, 0.2, 0.8, 1.0], requires_grad=True)  # the hard cases 0 and 1 included
    opacity_entropy(alpha).backward()
    assert torch.isfinite(alpha.grad).all()
    assert alpha.grad[1] > 0 and alpha.grad[2] < 0  # a gradient step moves 0.2 down and 0.8 up


def test_semantic_loss_value_and_gradient():
    ref = torch.nn.functional.normalize(torch.tensor([[1.0, 0.0, 0.0]]), dim=-1)
    emb = torch.nn.functional.normalize(torch.tensor([[0.6, 0.8, 0.0]]), dim=-1).requires_grad_()
    loss = semantic_loss(ref, emb)
    assert abs(float(loss.detach()) - 0.4) < 1e-6
    loss.backward()
    assert emb.grad[0, 0] < 0  # moving towards the reference lowers the loss
    assert semantic_loss(ref, ref) < 1e-7


def test_ssim_and_the_weights_free_perceptual_term():
    a = torch.rand(1, 3, 32, 32)
    assert abs(float(ssim(a, a)) - 1) < 1e-5
    per = Perceptual("ssim")
    assert per.name.startswith("ssim") and per.lpips is None
    b = (a + 0.3 * torch.randn_like(a)).clamp(0, 1).requires_grad_()
    loss = per(b, a)
    assert loss > 0.1
    loss.backward()
    step = b - 0.5 * b.grad / b.grad.abs().max()
    assert per(step.detach(), a) < loss  # following the gradient moves towards the target
