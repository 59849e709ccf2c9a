"""The compiled training loss (`train.photometric`) against the torch code it replaces
(`losses.photometric_loss` and its autograd): the same value and the same gradient with respect
to the render, on images of odd sizes (windows that cross every edge), flat and saturated images
included, for any weight of the SSIM term; the torch code where the compiled one does not apply."""

import pytest
import torch

from gvae_core.losses import photometric_loss as torch_loss
from gvae_core.rendering.compiled import numba_missing
from gvae_core.train.photometric import photometric_loss

pytestmark = pytest.mark.skipif(numba_missing() is not None, reason=f"compiled kernels: {numba_missing()}")


def _both(pred, target, lam):
    out = []
    for fn in (torch_loss, photometric_loss):
        x = pred.clone().requires_grad_()
        loss = fn(x, target, lam)
        loss.backward()
        out.append((loss.item(), x.grad))
    return out


@pytest.mark.parametrize("shape, lam", [((7, 5, 3), 0.2), ((37, 53, 3), 0.2), ((64, 48, 1), 0.9),
                                        ((23, 31, 3), 0.0), ((19, 12, 4), 1.0)])
def test_compiled_loss_and_gradient_are_the_torch_ones(shape, lam):
    g = torch.Generator().manual_seed(sum(shape))
    target = torch.rand(shape, generator=g)
    pred = (target + 0.15 * torch.randn(shape, generator=g)).clamp(0, 1)
    (want, want_grad), (got, got_grad) = _both(pred, target, lam)
    assert got == pytest.approx(want, rel=1e-5, abs=1e-7)
    assert torch.allclose(got_grad, want_grad, rtol=1e-4, atol=1e-4 * float(want_grad.abs().max()))


def test_flat_and_saturated_images_give_finite_gradients_that_agree():
    flat = torch.full((20, 30, 3), 0.5)
    (want, want_grad), (got, got_grad) = _both(torch.ones(20, 30, 3), flat, 0.2)
    assert got == pytest.approx(want, rel=1e-5) and torch.isfinite(got_grad).all()
    assert torch.allclose(got_grad, want_grad, atol=1e-4 * float(want_grad.abs().max()))
    _, (loss, grad) = _both(flat, flat, 0.2)  # a perfect render: zero loss, zero gradient
    assert loss == pytest.approx(0.0, abs=1e-6) and float(grad.abs().max()) < 1e-6


def test_the_torch_code_runs_where_the_compiled_loss_does_not_apply():
    a, b = torch.rand(2, 9, 9, 3, dtype=torch.float64)
    x = a.clone().requires_grad_()
    photometric_loss(x, b).backward()  # float64: the torch code, the same gradient as its autograd
    y = a.clone().requires_grad_()
    torch_loss(y, b).backward()
    assert torch.equal(x.grad, y.grad)
    batch = torch.rand(2, 9, 9, 3)
    assert photometric_loss(batch, batch.flip(0)).item() == pytest.approx(torch_loss(batch, batch.flip(0)).item())
