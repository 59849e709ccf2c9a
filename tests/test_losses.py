"""Image losses: vectorised SSIM against the per-pixel float64 reference, L1, PSNR."""

import math

import numpy as np
import pytest
import torch

from gvae_core.losses import gaussian_window, l1_loss, photometric_loss, psnr, ssim, ssim_map, ssim_reference


@pytest.mark.parametrize("shape,window", [((9, 13, 3), 11), ((16, 7, 1), 5), ((12, 12, 2), 11)])
def test_ssim_matches_reference(shape, window):
    rng = np.random.default_rng(0)
    a = rng.random(shape)
    b = np.clip(a + rng.normal(0, 0.2, shape), 0, 1)
    got = ssim(torch.from_numpy(a), torch.from_numpy(b), window_size=window).item()
    want = ssim_reference(a, b, window_size=window)
    assert got == pytest.approx(want, abs=1e-10)
    # float32, batched input gives the same within float32 rounding
    batch = torch.from_numpy(np.stack([a, b])).float()
    got32 = ssim(batch, torch.from_numpy(np.stack([b, a])).float(), window_size=window).item()
    assert got32 == pytest.approx(want, abs=1e-5)


def test_ssim_properties_and_gradient():
    rng = np.random.default_rng(1)
    x = torch.from_numpy(rng.random((20, 24, 3))).float()
    assert ssim(x, x).item() == pytest.approx(1.0, abs=1e-6)
    y = x.clone().requires_grad_(True)
    noisy = (x + 0.3 * torch.from_numpy(rng.standard_normal((20, 24, 3))).float()).clamp(0, 1)
    assert ssim(noisy, x).item() < 0.9
    loss = photometric_loss(y, noisy)
    loss.backward()
    assert torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    # constant images (zero variance) stay finite
    flat = torch.zeros(8, 8, 3)
    assert torch.isfinite(ssim_map(flat, flat)).all()
    with pytest.raises(ValueError):
        ssim(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))


def test_photometric_loss_is_the_reference_mix():
    rng = np.random.default_rng(2)
    a = torch.from_numpy(rng.random((10, 10, 3))).double()
    b = torch.from_numpy(rng.random((10, 10, 3))).double()
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1 - ssim(a, b))
    assert photometric_loss(a, b).item() == pytest.approx(want.item(), rel=1e-12)
    assert l1_loss(a, b).item() == pytest.approx(np.abs(a.numpy() - b.numpy()).mean())


def test_window_and_psnr():
    g = gaussian_window(11, 1.5, torch.float64)
    assert g.sum().item() == pytest.approx(1.0) and g.argmax().item() == 5
    assert torch.allclose(g, g.flip(0))
    a = np.zeros((4, 4, 3))
    assert psnr(a, a) == math.inf
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert psnr(torch.zeros(2, 2), torch.full((2, 2), 0.01)) == pytest.approx(40.0)
