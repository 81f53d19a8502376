"""Total variation of grid blocks: the Warp kernel against the torch reference."""

import pytest
import torch
from devices import on_device

from elicit_diffrender.model.torch_reference import total_variation_reference
from elicit_diffrender.model.total_variation import total_variation as _total_variation

total_variation = on_device(_total_variation)  # the kernel on ELICIT_DEVICE


@pytest.mark.parametrize("shape", [(5, 7, 4), (2, 2, 2), (40, 40, 40)])
def test_total_variation_matches_reference(shape):
    gen = torch.Generator().manual_seed(3)
    density = (3 * torch.randn(shape, generator=gen, dtype=torch.float64)).requires_grad_()
    color = torch.randn(*shape, 3, generator=gen, dtype=torch.float64).requires_grad_()
    upstream = 0.7  # an arbitrary incoming gradient
    got, want = total_variation(density, color), total_variation_reference(density, color)
    torch.testing.assert_close(got, want, atol=1e-12, rtol=1e-10)
    assert float(want.detach()) > 1.0
    grads = torch.autograd.grad(upstream * got, (density, color))
    for a, b in zip(grads, torch.autograd.grad(upstream * want, (density, color)), strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


def test_total_variation_float32_and_bad_blocks():
    gen = torch.Generator().manual_seed(4)
    density, color = torch.randn(40, 33, 20, generator=gen), torch.randn(40, 33, 20, 3, generator=gen)
    torch.testing.assert_close(total_variation(density, color), total_variation_reference(density, color))
    with pytest.raises(ValueError, match="at least 2 nodes"):
        total_variation(density[:1], color[:1])
    with pytest.raises(ValueError, match="must match"):
        total_variation(density, color[..., :2])
