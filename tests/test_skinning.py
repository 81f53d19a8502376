"""Skinning warp: agreement with the torch reference, adjoints, and hard cases."""

import math

import pytest
import torch
from devices import on_device

from elicit_diffrender.core.geometry import axis_angle_to_matrix, matrix_to_axis_angle, merge_bones, rigid_inverse
from elicit_diffrender.model.skinning import forward_lbs as _forward_lbs
from elicit_diffrender.model.skinning import inverse_lbs as _inverse_lbs
from elicit_diffrender.model.torch_reference import forward_lbs_reference, inverse_lbs_reference

forward_lbs, inverse_lbs = on_device(_forward_lbs), on_device(_inverse_lbs)  # kernels on ELICIT_DEVICE

WBOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=torch.float64)


def random_transforms(n_bones: int, seed: int = 0, dtype=torch.float64, angle: float = 0.6):
    gen = torch.Generator().manual_seed(seed)
    mats = torch.eye(4, dtype=dtype).repeat(n_bones, 1, 1)
    mats[:, :3, :3] = axis_angle_to_matrix(angle * torch.randn(n_bones, 3, generator=gen, dtype=dtype))
    mats[:, :3, 3] = 0.2 * torch.randn(n_bones, 3, generator=gen, dtype=dtype)
    return mats


def random_weights(n_bones: int, res=(6, 5, 7), seed: int = 1, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    return torch.softmax(2 * torch.randn(n_bones + 1, *res, generator=gen, dtype=dtype), 0)[:-1].contiguous()


@pytest.mark.parametrize("n_bones", [3, 24, 104])
def test_inverse_lbs_matches_reference(n_bones):
    gen = torch.Generator().manual_seed(2)
    pts = 0.6 * torch.randn(500, 3, generator=gen, dtype=torch.float64)
    mats, weights = random_transforms(n_bones), random_weights(n_bones)
    x_c, fg = inverse_lbs(pts, mats, weights, WBOX)
    rx, rfg = inverse_lbs_reference(pts, mats, weights, WBOX)
    torch.testing.assert_close(x_c, rx, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(fg, rfg, atol=1e-12, rtol=1e-10)
    assert fg.max() > 0.3


def test_inverse_lbs_gradients_match_finite_differences():
    gen = torch.Generator().manual_seed(3)
    pts = (0.4 * torch.randn(12, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    mats = random_transforms(3, seed=4).requires_grad_()
    weights = random_weights(3, res=(4, 4, 4), seed=5).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p, m, w: inverse_lbs(p, m, w, WBOX), (pts, mats, weights), eps=1e-6, atol=1e-6, rtol=1e-5
    )


def test_inverse_lbs_gradients_match_reference_autograd():
    gen = torch.Generator().manual_seed(6)
    pts = (0.5 * torch.randn(2000, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    mats = random_transforms(24, seed=7).requires_grad_()
    weights = random_weights(24, res=(8, 8, 8), seed=8).requires_grad_()
    wx, wfg = (
        torch.randn(2000, 3, generator=gen, dtype=torch.float64),
        torch.randn(2000, generator=gen, dtype=torch.float64),
    )
    ours = inverse_lbs(pts, mats, weights, WBOX)
    ref = inverse_lbs_reference(pts, mats, weights, WBOX)
    g1 = torch.autograd.grad((ours[0] * wx).sum() + (ours[1] * wfg).sum(), (pts, mats, weights))
    g2 = torch.autograd.grad((ref[0] * wx).sum() + (ref[1] * wfg).sum(), (pts, mats, weights))
    for a, b in zip(g1, g2, strict=True):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-8)


def test_bone_gradients_summed_over_copies_match_the_reference(monkeypatch):
    """On a GPU the backward pass adds each point's bone gradients into one of several copies (fewer atomics
    on one address) and sums them after; forced here on any device, with a count that does not divide P."""
    import elicit_diffrender.model.skinning as skinning

    monkeypatch.setattr(skinning, "bone_grad_copies", lambda device: 7)
    gen = torch.Generator().manual_seed(21)
    pts = 0.5 * torch.randn(1000, 3, generator=gen, dtype=torch.float64)
    mats = random_transforms(24, seed=22).requires_grad_()
    weights = random_weights(24, res=(8, 8, 8), seed=23).requires_grad_()
    ours = torch.autograd.grad(sum(t.sum() for t in inverse_lbs(pts, mats, weights, WBOX, sharpness=4)), mats)[0]
    ref = torch.autograd.grad(sum(t.sum() for t in inverse_lbs_reference(pts, mats, weights, WBOX, sharpness=4)), mats)
    torch.testing.assert_close(ours, ref[0], atol=1e-10, rtol=1e-8)
    assert ours[:, :3].abs().max() > 1.0  # the points reach the bones: the gradient is not trivially zero


def test_reference_gradients_stay_finite_in_float32_where_no_bone_reaches():
    """Points outside every bone's weights (top weight 0) once made the float32 reference's gradients NaN:
    its guard against dividing by 0 was 1e-300, which is 0 in float32."""
    gen = torch.Generator().manual_seed(9)
    pts = 1.5 * torch.randn(500, 3, generator=gen)
    mats = random_transforms(24, seed=10, dtype=torch.float32).requires_grad_()
    weights = random_weights(24, res=(8, 8, 8), seed=11, dtype=torch.float32).requires_grad_()
    box = WBOX.float()
    grads = []
    for warp in (inverse_lbs, inverse_lbs_reference):
        x_c, fg = warp(pts, mats, weights, box)
        grads.append(torch.autograd.grad(x_c.sum() + fg.sum(), (mats, weights)))
    assert (fg == 0).any() and (fg > 0).any()
    for ours, ref in zip(*grads, strict=True):
        assert torch.isfinite(ref).all()
        torch.testing.assert_close(ours, ref, atol=1e-4 * float(ref.abs().max()), rtol=1e-3)


def test_only_requested_gradients_are_computed():
    pts = torch.randn(50, 3, dtype=torch.float64, requires_grad=True)
    mats = random_transforms(4)
    weights = random_weights(4)
    x_c, _ = inverse_lbs(pts, mats, weights, WBOX)
    x_c.sum().backward()
    assert pts.grad is not None and torch.isfinite(pts.grad).all()


def test_points_outside_every_influence_are_finite():
    pts = torch.tensor([[5.0, 5.0, 5.0], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    mats = random_transforms(3, angle=0.0).requires_grad_()
    weights = torch.zeros(3, 4, 4, 4, dtype=torch.float64)
    weights[:, 2:, 2:, 2:] = 1e-9  # a tiny influence far from the origin
    weights.requires_grad_()
    x_c, fg = inverse_lbs(pts, mats, weights, WBOX)
    assert torch.isfinite(x_c).all() and torch.isfinite(fg).all()
    assert fg[0] == 0 and fg[1] < 1e-8
    (x_c.sum() + fg.sum()).backward()
    for t in (pts.grad, mats.grad, weights.grad):
        assert torch.isfinite(t).all()


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, math.pi - 1e-7, math.pi])
def test_single_bone_is_the_exact_rigid_motion(angle):
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    mat = torch.eye(4, dtype=torch.float64)[None].clone()
    mat[0, :3, :3] = axis_angle_to_matrix(axis * angle)
    mat[0, :3, 3] = torch.tensor([0.1, -0.05, 0.02], dtype=torch.float64)
    pts = 0.3 * torch.randn(100, 3, dtype=torch.float64)
    weights = torch.ones(1, 5, 5, 5, dtype=torch.float64)
    x_c, fg = inverse_lbs(pts, mat, weights, WBOX * 3)
    torch.testing.assert_close(x_c, pts @ mat[0, :3, :3].T + mat[0, :3, 3], atol=1e-13, rtol=0)
    torch.testing.assert_close(fg, torch.ones(100, dtype=torch.float64))


def test_axis_angle_tiny_angles_and_gradients():
    for angle in (0.0, 1e-12, 1e-8, 1e-4, 1e-3, 0.5, 3.0, math.pi):
        aa = torch.tensor([angle, 0.0, 0.0], dtype=torch.float64)
        expected = torch.tensor(
            [[1, 0, 0], [0, math.cos(angle), -math.sin(angle)], [0, math.sin(angle), math.cos(angle)]],
            dtype=torch.float64,
        )
        torch.testing.assert_close(axis_angle_to_matrix(aa), expected, atol=1e-15, rtol=0)
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(zero).sum().backward()
    assert torch.isfinite(zero.grad).all()
    assert torch.autograd.gradcheck(
        axis_angle_to_matrix, (torch.tensor([1e-5, 2e-5, -1e-5], dtype=torch.float64, requires_grad=True),)
    )
    assert torch.autograd.gradcheck(
        axis_angle_to_matrix, (torch.tensor([0.3, 1.0, -2.0], dtype=torch.float64, requires_grad=True),)
    )
    rot32 = axis_angle_to_matrix(torch.tensor([1e-7, 0, 0], dtype=torch.float32))
    assert torch.isfinite(rot32).all()


@pytest.mark.parametrize("angle", [1e-9, 1e-3, 1.0, math.pi - 1e-3, math.pi - 1e-6])
def test_matrix_to_axis_angle_round_trip(angle):
    axis = torch.nn.functional.normalize(torch.tensor([0.2, 0.9, -0.4], dtype=torch.float64), dim=0)
    aa = axis * angle
    back = matrix_to_axis_angle(axis_angle_to_matrix(aa))
    torch.testing.assert_close(axis_angle_to_matrix(back), axis_angle_to_matrix(aa), atol=1e-9, rtol=0)


def test_float32_agrees_with_float64():
    pts = 0.5 * torch.randn(3000, 3, dtype=torch.float64)
    mats, weights = random_transforms(24), random_weights(24, res=(16, 16, 16))
    x64, fg64 = inverse_lbs(pts, mats, weights, WBOX)
    x32, fg32 = inverse_lbs(pts.float(), mats.float(), weights.float(), WBOX.float())
    torch.testing.assert_close(x32.double(), x64, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(fg32.double(), fg64, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("scale", [1e-2, 1e2])
def test_scaled_scene_warps_the_same(scale):
    pts = 0.5 * torch.randn(400, 3, dtype=torch.float64)
    mats, weights = random_transforms(5), random_weights(5)
    x_c, fg = inverse_lbs(pts, mats, weights, WBOX)
    mats_s = mats.clone()
    mats_s[:, :3, 3] *= scale
    xs, fgs = inverse_lbs(pts * scale, mats_s, weights, WBOX * scale)
    torch.testing.assert_close(xs, x_c * scale, atol=1e-12 * scale, rtol=1e-9)
    torch.testing.assert_close(fgs, fg, atol=1e-12, rtol=1e-9)


def test_forward_lbs_matches_reference_and_gradients():
    gen = torch.Generator().manual_seed(9)
    verts = torch.randn(300, 3, generator=gen, dtype=torch.float64).requires_grad_()
    idx = torch.randint(0, 7, (300, 4), generator=gen)
    w = torch.rand(300, 4, generator=gen, dtype=torch.float64)
    w[:, 3] = 0
    w = (w / w.sum(1, keepdim=True)).requires_grad_()
    mats = random_transforms(7, seed=10).requires_grad_()
    torch.testing.assert_close(forward_lbs(verts, idx, w, mats), forward_lbs_reference(verts, idx, w, mats))
    assert torch.autograd.gradcheck(
        lambda v, ww, m: forward_lbs(v, idx[:20], ww, m),
        (verts[:20].detach().requires_grad_(), w[:20].detach().requires_grad_(), mats),
    )


def test_forward_then_inverse_round_trip():
    """A rigidly posed point warps back to where it started when the volume holds its bone's weight."""
    mats = random_transforms(2, seed=12)
    verts = 0.2 * torch.randn(50, 3, dtype=torch.float64)
    idx = torch.zeros(50, 1, dtype=torch.long)
    posed = forward_lbs(verts, idx, torch.ones(50, 1, dtype=torch.float64), mats)
    weights = torch.zeros(2, 5, 5, 5, dtype=torch.float64)
    weights[0] = 1.0
    back, fg = inverse_lbs(posed, rigid_inverse(mats), weights, WBOX)
    torch.testing.assert_close(back, verts, atol=1e-12, rtol=0)


def test_merge_bones():
    parents = [-1, 0, 1, 2, 1, 4, 0]
    mapping = merge_bones(parents, keep=[0, 1, 4])
    assert mapping.tolist() == [0, 1, 1, 1, 2, 2, 0]
    with pytest.raises(ValueError, match="root"):
        merge_bones(parents, keep=[1])


def test_bone_count_limits():
    with pytest.raises(ValueError, match="1..128"):
        inverse_lbs(torch.zeros(1, 3), torch.eye(4).repeat(129, 1, 1), torch.zeros(129, 2, 2, 2), WBOX.float())


@pytest.mark.parametrize(("sharpness", "gate"), [(2, 0.0), (6, 0.0), (1, 0.3), (4, 0.3)])
def test_sharpened_warp_matches_reference_values_and_gradients(sharpness, gate):
    gen = torch.Generator().manual_seed(13)
    pts = (0.5 * torch.randn(800, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    mats = random_transforms(24, seed=14).requires_grad_()
    weights = random_weights(24, res=(8, 8, 8), seed=15).requires_grad_()
    ours = inverse_lbs(pts, mats, weights, WBOX, sharpness=sharpness, gate=gate)
    ref = inverse_lbs_reference(pts, mats, weights, WBOX, sharpness=sharpness, gate=gate)
    if gate:  # the gate leaves out some candidates of most points, so it is tested, not idle
        y = torch.einsum("bij,pj->bpi", mats[:, :3, :3], pts) + mats[:, None, :3, 3]
        spread = (y - ref[0][None]).norm(dim=-1).max(0).values
        assert (spread > gate).float().mean() > 0.5
    torch.testing.assert_close(ours[0], ref[0], atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(ours[1], ref[1], atol=1e-12, rtol=1e-10)
    wx = torch.randn(800, 3, generator=gen, dtype=torch.float64)
    wfg = torch.randn(800, generator=gen, dtype=torch.float64)
    g1 = torch.autograd.grad((ours[0] * wx).sum() + (ours[1] * wfg).sum(), (pts, mats, weights))
    g2 = torch.autograd.grad((ref[0] * wx).sum() + (ref[1] * wfg).sum(), (pts, mats, weights))
    for a, b in zip(g1, g2, strict=True):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-8)
    small = (pts[:10].detach().requires_grad_(), mats.detach()[:3].requires_grad_())
    w3 = random_weights(3, res=(4, 4, 4), seed=16).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p, m, w: inverse_lbs(p, m, w, WBOX, sharpness=sharpness, gate=gate),
        (*small, w3),
        eps=1e-6,
        atol=1e-6,
        rtol=1e-5,
    )


def test_sharpening_lets_the_dominant_bone_decide():
    """Two bones whose candidates land far apart: HumanNeRF's blend puts the point between them (a ghost where
    neither bone has anything); a sharpened blend keeps it at the dominant bone's candidate."""
    mats = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    mats[1, :3, 3] = torch.tensor([0.8, 0.0, 0.0], dtype=torch.float64)  # bone 1 moves points 0.8 along x
    weights = torch.zeros(2, 9, 9, 9, dtype=torch.float64)
    weights[0] = 0.9  # bone 0 dominates near the origin
    weights[1] = 0.25
    pt = torch.tensor([[-0.4, 0.0, 0.0]], dtype=torch.float64)  # candidates at x = -0.4 (bone 0) and 0.4 (bone 1)
    plain, fg = inverse_lbs(pt, mats, weights, WBOX)
    sharp, fg_sharp = inverse_lbs(pt, mats, weights, WBOX, sharpness=8)
    assert abs(float(plain[0, 0]) - (-0.4 * 0.9 + 0.4 * 0.25) / 1.15) < 1e-12  # between the two
    assert abs(float(sharp[0, 0]) + 0.4) < 1e-4
    torch.testing.assert_close(fg, fg_sharp)
    with pytest.raises(ValueError, match="sharpness"):
        inverse_lbs(pt, mats, weights, WBOX, sharpness=0)
    with pytest.raises(ValueError, match="sharpness"):
        inverse_lbs(pt, mats, weights, WBOX, sharpness=2.5)


def test_gate_keeps_two_claiming_bones_apart():
    """A hand beside the hip: two bones claim the point with equal weight but their candidates lie 0.8 apart.
    Any blend puts it in the room between them, whatever the sharpness; the gate keeps the dominant candidate
    and blends only candidates near it. fg still counts every bone."""
    mats = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    mats[1, :3, 3] = torch.tensor([0.8, 0.0, 0.0], dtype=torch.float64)  # far from bone 0's candidate
    mats[2, :3, 3] = torch.tensor([0.0, 0.05, 0.0], dtype=torch.float64)  # near it
    weights = torch.zeros(3, 9, 9, 9, dtype=torch.float64)
    weights[0], weights[1], weights[2] = 0.5, 0.45, 0.5 * 0.5 ** (1 / 4)
    pt = torch.tensor([[-0.4, 0.0, 0.0]], dtype=torch.float64)
    blended, fg = inverse_lbs(pt, mats, weights, WBOX, sharpness=4)
    gated, fg_gated = inverse_lbs(pt, mats, weights, WBOX, sharpness=4, gate=0.1)
    assert float(blended[0, 0]) > -0.2  # pulled well into the room by bone 1
    # bone 1 is left out; bones 0 and 2 blend with u = 1 and 0.5
    torch.testing.assert_close(gated[0], torch.tensor([-0.4, 0.05 / 3, 0.0], dtype=torch.float64))
    torch.testing.assert_close(fg, fg_gated)
    with pytest.raises(ValueError, match="gate"):
        inverse_lbs(pt, mats, weights, WBOX, gate=-0.1)
