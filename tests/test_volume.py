"""Ray marcher: agreement with the torch reference, hand-written adjoint, and hard cases."""

import math
import os
import time

import pytest
import torch
from devices import on_device
from elicit_diffrender.kernels.raymarch import ORDER_MIN_RAYS

from elicit_diffrender.core.device import split_launch, to_warp
from elicit_diffrender.model.skinning import lookup_baked_warp
from elicit_diffrender.model.torch_reference import composite_reference
from elicit_diffrender.model.volume import BakedWarp, RaySamples, coherent_ray_order
from elicit_diffrender.model.volume import composite as _composite
from elicit_diffrender.model.volume import sample_rays as _sample_rays

composite, sample_rays = on_device(_composite), on_device(_sample_rays)  # kernels on ELICIT_DEVICE

BOX = torch.tensor([[-1.0, -1.2, -0.8], [1.0, 1.1, 0.9]])


def camera_rays(n: int, dtype=torch.float64, seed: int = 0, scale: float = 1.0):
    gen = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.1, -0.2, -3.0], dtype=dtype) * scale + 0.05 * scale * torch.randn(
        n, 3, generator=gen, dtype=dtype
    )
    target = (torch.rand(n, 3, generator=gen, dtype=dtype) - 0.5) * 1.6 * scale
    dirs = torch.nn.functional.normalize(target - origins, dim=1)
    return origins, dirs


def random_grid(shape=(6, 7, 5), dtype=torch.float64, seed: int = 1):
    gen = torch.Generator().manual_seed(seed)
    density = (torch.randn(shape, generator=gen, dtype=dtype) * 2 + 1).requires_grad_()
    color = torch.randn((*shape, 3), generator=gen, dtype=dtype).requires_grad_()
    return density, color


@pytest.mark.parametrize("activation", ["relu", "softplus"])
def test_matches_reference_float64(activation):
    o, d = camera_rays(40)
    density, color = random_grid()
    samples = sample_rays(o, d, BOX.double(), 24, jitter=True, seed=3)
    fg = torch.rand(samples.n_samples, dtype=torch.float64)
    ours = composite(
        samples, density, color, BOX, fg=fg, outputs=("rgb", "alpha", "depth"), activation=activation, t_thresh=0.0
    )
    ref = composite_reference(samples, density, color, BOX, fg=fg, activation=activation)
    for key in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(ours[key], ref[key], atol=1e-12, rtol=1e-10)
    assert ours["alpha"].max() > 0.2  # the case is not trivially empty


def test_gradients_match_finite_differences():
    o, d = camera_rays(6, seed=4)
    density, color = random_grid((4, 5, 4), seed=5)
    samples = sample_rays(o, d, BOX.double(), 7, jitter=True, seed=1)
    positions = samples.positions.clone().requires_grad_()
    fg = (0.3 + 0.7 * torch.rand(samples.n_samples, dtype=torch.float64)).requires_grad_()

    def fn(dens, col, pos, fgv):
        out = composite(
            samples,
            dens,
            col,
            BOX,
            positions=pos,
            fg=fgv,
            outputs=("rgb", "alpha", "depth"),
            activation="softplus",
            t_thresh=0.0,
        )
        return out["rgb"], out["alpha"], out["depth"]

    assert torch.autograd.gradcheck(fn, (density, color, positions, fg), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradients_match_reference_autograd():
    o, d = camera_rays(64, seed=7)
    density, color = random_grid((8, 8, 8), seed=8)
    samples = sample_rays(o, d, BOX.double(), 32, jitter=True, seed=2)
    pos = samples.positions.clone().requires_grad_()
    fg = torch.rand(samples.n_samples, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(64, 5, dtype=torch.float64)

    def loss(out):
        return (
            (out["rgb"] * weights[:, :3]).sum()
            + (out["alpha"] * weights[:, 3]).sum()
            + (out["depth"] * weights[:, 4]).sum()
        )

    grads = torch.autograd.grad(
        loss(
            composite(
                samples, density, color, BOX, positions=pos, fg=fg, outputs=("rgb", "alpha", "depth"), t_thresh=0.0
            )
        ),
        (density, color, pos, fg),
    )
    ref = torch.autograd.grad(
        loss(composite_reference(samples, density, color, BOX, positions=pos, fg=fg)), (density, color, pos, fg)
    )
    for a, b in zip(grads, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-8)


def test_rays_are_composited_in_a_coherent_order_that_changes_no_result():
    n = ORDER_MIN_RAYS  # fewer rays keep their order
    o, d = camera_rays(n, seed=4)
    d[:7] = -d[:7]  # these point away from the box: no samples
    samples = sample_rays(o, d, BOX.double(), 16)
    order = coherent_ray_order(samples.offsets, samples.positions, BOX).cpu().long()
    assert sorted(order.tolist()) == list(range(n))
    empty = (samples.offsets[1:] == samples.offsets[:-1]).cpu()
    assert empty[:7].all() and int(empty.sum()) == 7
    assert set(order[-7:].tolist()) == set(range(7))  # rays without samples come last
    offsets = samples.offsets.cpu().long()
    middle = samples.positions.cpu()[((offsets[:-1] + offsets[1:]) // 2)[order[:-7]]]
    unsorted = samples.positions.cpu()[((offsets[:-1] + offsets[1:]) // 2)[7:]]
    step_sorted = (middle[1:] - middle[:-1]).norm(dim=1).mean()
    step_input = (unsorted[1:] - unsorted[:-1]).norm(dim=1).mean()
    assert step_sorted < 0.5 * step_input  # neighbours in the order read nearby cells
    few = coherent_ray_order(samples.offsets[:101], samples.positions, BOX).cpu()
    assert torch.equal(few, torch.arange(100, dtype=torch.int32))  # a small launch keeps its order

    # The order is internal: shuffling the input rays shuffles the outputs and leaves the gradients alone.
    density, color = random_grid((9, 8, 7), seed=5)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    results = []
    for oo, dd in ((o, d), (o[perm], d[perm])):
        out = composite(sample_rays(oo, dd, BOX.double(), 16), density, color, BOX, outputs=("rgb", "alpha", "depth"))
        grads = torch.autograd.grad(out["rgb"].sum() + out["alpha"].sum() + out["depth"].sum(), (density, color))
        results.append((out, grads))
    (first, grads_first), (shuffled, grads_shuffled) = results
    for key in ("rgb", "alpha", "depth"):
        torch.testing.assert_close(shuffled[key], first[key][perm.to(first[key].device)], atol=1e-12, rtol=1e-12)
    for a, b in zip(grads_shuffled, grads_first, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


def test_float32_agrees_with_float64():
    o, d = camera_rays(256)
    density, color = random_grid((16, 16, 16))
    s64 = sample_rays(o, d, BOX.double(), 48)
    s32 = sample_rays(o.float(), d.float(), BOX, 48)
    out64 = composite(s64, density, color, BOX, outputs=("rgb", "alpha", "depth"))
    d32, c32 = density.detach().float().requires_grad_(), color.detach().float().requires_grad_()
    out32 = composite(s32, d32, c32, BOX, outputs=("rgb", "alpha", "depth"))
    for key in out64:
        torch.testing.assert_close(out32[key].double(), out64[key].detach(), atol=2e-5, rtol=1e-4)
    out64["rgb"].sum().backward()
    out32["rgb"].sum().backward()
    torch.testing.assert_close(d32.grad.double(), density.grad, atol=1e-4, rtol=1e-3)


@pytest.mark.parametrize("scale", [1e-2, 1e2])
def test_scaled_scene_renders_the_same_image(scale):
    o, d = camera_rays(128)
    density, color = random_grid((10, 10, 10))
    base = composite(
        sample_rays(o, d, BOX.double(), 40),
        density.detach(),
        color.detach(),
        BOX,
        outputs=("rgb", "alpha", "depth"),
        activation="relu",
    )
    # Scaling lengths by s scales optical depth per metre by 1/s: relu density is linear in raw.
    o_s, d_s = camera_rays(128, scale=scale)
    dens_s = (density.detach() / scale).requires_grad_()
    scaled = composite(
        sample_rays(o_s, d_s, BOX.double() * scale, 40),
        dens_s,
        color.detach(),
        BOX.double() * scale,
        outputs=("rgb", "alpha", "depth"),
        activation="relu",
    )
    torch.testing.assert_close(scaled["rgb"], base["rgb"], atol=1e-9, rtol=1e-7)
    torch.testing.assert_close(scaled["depth"], base["depth"] * scale, atol=1e-9 * scale, rtol=1e-7)
    scaled["alpha"].sum().backward()
    assert torch.isfinite(dens_s.grad).all()


def test_huge_density_is_finite_and_opaque():
    o, d = camera_rays(64, dtype=torch.float32)
    density = torch.full((6, 6, 6), 1e8, requires_grad=True)
    color = torch.zeros((6, 6, 6, 3), requires_grad=True)
    samples = sample_rays(o, d, BOX, 32)
    pos = samples.positions.clone().requires_grad_()
    fg = torch.ones(samples.n_samples, requires_grad=True)
    out = composite(samples, density, color, BOX, positions=pos, fg=fg, outputs=("rgb", "alpha", "depth"), t_thresh=0.0)
    hit = samples.offsets[1:] > samples.offsets[:-1]
    assert hit.any()
    torch.testing.assert_close(out["alpha"][hit], torch.ones(int(hit.sum())))
    torch.testing.assert_close(out["rgb"][hit], torch.full((int(hit.sum()), 3), 0.5))
    (out["rgb"].sum() + out["alpha"].sum() + out["depth"].sum()).backward()
    for t in (density.grad, color.grad, pos.grad, fg.grad):
        assert torch.isfinite(t).all()


def test_transparent_and_opaque_limits():
    o, d = camera_rays(32)
    samples = sample_rays(o, d, BOX.double(), 16)
    empty = composite(
        samples,
        torch.full((5, 5, 5), -50.0, dtype=torch.float64),
        torch.zeros(5, 5, 5, 3, dtype=torch.float64),
        BOX,
        outputs=("rgb", "alpha", "depth"),
    )
    assert empty["alpha"].abs().max() < 1e-15 and empty["rgb"].abs().max() < 1e-15
    solid = composite(
        samples,
        torch.full((5, 5, 5), 1e4, dtype=torch.float64),
        torch.full((5, 5, 5, 3), 50.0, dtype=torch.float64),
        BOX,
        outputs=("rgb", "alpha"),
    )
    hit = samples.offsets[1:] > samples.offsets[:-1]
    torch.testing.assert_close(solid["alpha"][hit], torch.ones(int(hit.sum()), dtype=torch.float64))
    torch.testing.assert_close(solid["rgb"][hit], torch.ones(int(hit.sum()), 3, dtype=torch.float64))


def test_missing_and_grazing_rays():
    o = torch.tensor([[5.0, 5.0, -3.0], [1.0, 0.0, -3.0], [1.0, 1.1, -3.0], [0.0, 0.0, -3.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    samples = sample_rays(o, d, BOX.double(), 8)
    counts = (samples.offsets[1:] - samples.offsets[:-1]).tolist()
    assert counts[0] == 0 and counts[3] == 0  # misses: beside the box, and parallel to it outside
    assert counts[1] == 8 and counts[2] == 8  # grazing a face and an edge of the box
    density, color = random_grid((5, 5, 5))
    pos = samples.positions.clone().requires_grad_()
    out = composite(samples, density, color, BOX, positions=pos, outputs=("rgb", "alpha", "depth"))
    assert out["alpha"][0] == 0 and out["alpha"][3] == 0
    (out["rgb"].sum() + out["alpha"].sum()).backward()
    assert torch.isfinite(pos.grad).all() and torch.isfinite(density.grad).all()


def test_zero_length_segments_contribute_nothing():
    positions = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    samples = RaySamples(
        offsets=torch.tensor([0, 4], dtype=torch.int32),
        positions=positions.detach(),
        t_mid=torch.ones(4, dtype=torch.float64),
        deltas=torch.zeros(4, dtype=torch.float64),
        ray_ids=torch.zeros(4, dtype=torch.int32),
    )
    density = torch.full((4, 4, 4), 1e6, dtype=torch.float64, requires_grad=True)
    color = torch.zeros(4, 4, 4, 3, dtype=torch.float64, requires_grad=True)
    out = composite(samples, density, color, BOX, positions=positions, outputs=("rgb", "alpha", "depth"))
    assert out["alpha"].item() == 0.0 and out["rgb"].abs().sum().item() == 0.0
    out["alpha"].sum().backward()
    assert torch.isfinite(positions.grad).all() and torch.isfinite(density.grad).all()


def test_early_termination_matches_full_march():
    o, d = camera_rays(256)
    density, color = random_grid((12, 12, 12))
    density = (density.detach() + 3).requires_grad_()
    samples = sample_rays(o, d, BOX.double(), 64)
    full = composite(samples, density, color, BOX, outputs=("rgb", "alpha", "depth"), t_thresh=0.0)
    early = composite(samples, density, color, BOX, outputs=("rgb", "alpha", "depth"), t_thresh=1e-4)
    for key in full:
        torch.testing.assert_close(early[key], full[key], atol=2e-4 * (5 if key == "depth" else 1), rtol=0)
    g_full = torch.autograd.grad(full["rgb"].sum(), density)[0]
    g_early = torch.autograd.grad(early["rgb"].sum(), density)[0]
    assert (g_full - g_early).abs().max() < 1e-3 * g_full.abs().max()


def test_occupancy_skipping_keeps_the_image():
    o, d = camera_rays(200)
    density = torch.full((16, 16, 16), -30.0, dtype=torch.float64)
    density[5:11, 4:12, 6:10] = 3.0
    color = torch.randn(16, 16, 16, 3, dtype=torch.float64)
    occ = torch.zeros(8, 8, 8, dtype=torch.uint8)
    occ[2:6, 1:7, 2:6] = 1  # covers the dense block with a margin
    full = sample_rays(o, d, BOX.double(), 64)
    skip = sample_rays(o, d, BOX.double(), 64, occupancy=occ)
    assert skip.n_samples < 0.6 * full.n_samples
    a = composite(full, density, color, BOX, outputs=("rgb", "alpha"))
    b = composite(skip, density, color, BOX, outputs=("rgb", "alpha"))
    torch.testing.assert_close(a["rgb"], b["rgb"], atol=1e-9, rtol=0)


def test_baked_warp_sampling_matches_a_separate_look_up():
    """Sampling with a pose's baked warp gives the look-up of every plain sample, less those with fg = 0."""
    o, d = camera_rays(200)
    gen = torch.Generator().manual_seed(5)
    table = torch.rand(9, 10, 8, 4, generator=gen, dtype=torch.float64)
    table[..., 3] = torch.where(table[..., 3] > 0.4, table[..., 3], torch.zeros(()))  # empty room: fg = 0
    table_box = torch.tensor([[-0.9, -1.0, -0.7], [0.8, 1.0, 0.8]], dtype=torch.float64)  # misses part of BOX
    occ = (torch.rand(6, 6, 6, generator=gen) > 0.3).to(torch.uint8)
    plain = sample_rays(o, d, BOX.double(), 32, jitter=True, seed=3, occupancy=occ)
    warped = sample_rays(o, d, BOX.double(), 32, jitter=True, seed=3, occupancy=occ, warp=BakedWarp(table, table_box))
    x_c, fg = on_device(lookup_baked_warp)(plain.positions, table, table_box)
    kept = fg > 0
    assert 0.2 * plain.n_samples < warped.n_samples == int(kept.sum()) < 0.9 * plain.n_samples
    torch.testing.assert_close(warped.positions, x_c[kept], atol=1e-12, rtol=0)
    torch.testing.assert_close(warped.fg, fg[kept], atol=1e-12, rtol=0)
    torch.testing.assert_close(warped.t_mid, plain.t_mid[kept])
    assert torch.equal(warped.ray_ids, plain.ray_ids[kept]) and plain.fg is None
    counts = torch.bincount(plain.ray_ids[kept].long(), minlength=200)
    assert torch.equal(warped.offsets[1:] - warped.offsets[:-1], counts.to(torch.int32))


def test_silhouette_call_needs_no_colour():
    o, d = camera_rays(50)
    density, color = random_grid()
    samples = sample_rays(o, d, BOX.double(), 16)
    with_color = composite(samples, density, color, BOX, outputs=("rgb", "alpha"))
    alpha_only = composite(samples, density, None, BOX, outputs=("alpha",))
    assert set(alpha_only) == {"alpha"}
    torch.testing.assert_close(alpha_only["alpha"], with_color["alpha"])
    alpha_only["alpha"].sum().backward()
    assert color.grad is None and density.grad is not None


def test_jitter_is_seeded_and_stays_in_bins():
    o, d = camera_rays(16)
    a = sample_rays(o, d, BOX.double(), 10, jitter=True, seed=11)
    b = sample_rays(o, d, BOX.double(), 10, jitter=True, seed=11)
    c = sample_rays(o, d, BOX.double(), 10, jitter=False)
    torch.testing.assert_close(a.t_mid, b.t_mid)
    assert (a.t_mid - c.t_mid).abs().max() <= 0.5 * c.deltas.max() + 1e-12
    assert not torch.equal(a.t_mid, c.t_mid)


def test_dlpack_shares_memory():
    t = torch.randn(10, 3)
    assert to_warp(t).ptr == t.data_ptr()
    t64 = torch.randn(5, dtype=torch.float64, requires_grad=True)
    to_warp(t64)
    assert t64.grad is None  # never allocates .grad as a side effect


def test_bad_arguments_name_the_problem():
    o, d = camera_rays(4)
    with pytest.raises(ValueError, match="outputs"):
        composite(
            sample_rays(o, d, BOX.double(), 4),
            torch.zeros(3, 3, 3, dtype=torch.float64),
            None,
            BOX,
            outputs=("normals",),
        )
    with pytest.raises(ValueError, match="colour"):
        composite(sample_rays(o, d, BOX.double(), 4), torch.zeros(3, 3, 3, dtype=torch.float64), None, BOX)
    with pytest.raises(ValueError, match="n_samples"):
        sample_rays(o, d, BOX.double(), 0)
    assert math.isfinite(1.0)


def test_split_launch_runs_every_piece_and_raises_their_errors():
    """CPU launches run in pieces on a pool of threads: every piece once, an error re-raised in the caller, and a
    forked child (whose copy of the pool has no threads) starts its own."""
    seen = []
    split_launch(1000, 2, lambda b, e, p: seen.append((b, e, p)))
    assert sorted(seen) == [(0, 500, 0), (500, 1000, 1)]

    def fail_second(b, e, p):
        if p == 1:
            raise RuntimeError("piece 1 failed")

    with pytest.raises(RuntimeError, match="piece 1 failed"):
        split_launch(10, 2, fail_second)
    pid = os.fork()
    if pid == 0:  # the child: two pieces again, then report by exit code
        pieces = []
        split_launch(10, 2, lambda b, e, p: pieces.append(p))
        os._exit(0 if sorted(pieces) == [0, 1] else 3)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        time.sleep(0.05)
    else:
        os.kill(pid, 9)
        pytest.fail("split_launch hung in a forked child")
    assert os.waitstatus_to_exitcode(status) == 0
