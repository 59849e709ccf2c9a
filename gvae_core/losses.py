"""Image losses and quality measures: L1, SSIM (Gaussian window, as in the reference 3DGS), PSNR.

Images are channels-last, (H,W,C) or (B,H,W,C) torch tensors in [0,1]. `ssim` is vectorised
(one separable grouped convolution for all five local statistics); `ssim_reference` is the slow
float64 per-pixel version it is tested against.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference."""
    return (pred - target).abs().mean()


def psnr(pred, target, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of the mean squared error over all values (numpy or
    torch); identical images give +inf."""
    a = pred.detach().cpu().double().numpy() if torch.is_tensor(pred) else np.asarray(pred, np.float64)
    b = target.detach().cpu().double().numpy() if torch.is_tensor(target) else np.asarray(target, np.float64)
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(max_value ** 2 / mse)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32) -> torch.Tensor:
    """Normalised 1D Gaussian of `size` taps (the 2D window is its outer product)."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return (g / g.sum()).to(dtype)


def _as_batch(img: torch.Tensor) -> torch.Tensor:
    if img.ndim == 3:
        img = img[None]
    if img.ndim != 4:
        raise ValueError(f"expected an (H,W,C) or (B,H,W,C) image, got shape {tuple(img.shape)}")
    return img.permute(0, 3, 1, 2)  # B,C,H,W


def ssim_map(pred: torch.Tensor, target: torch.Tensor, window_size: int = 11,
             sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel SSIM (B,C,H,W) with a Gaussian window and zero padding (the reference 3DGS
    definition: constants (0.01)^2 and (0.03)^2 for a data range of 1)."""
    if pred.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    x, y = _as_batch(pred), _as_batch(target)
    b, c, h, w = x.shape
    stack = torch.cat([x, y, x * x, y * y, x * y], 1)  # B,5C,H,W
    g = gaussian_window(window_size, sigma, x.dtype).to(x.device)
    pad = window_size // 2
    stack = F.conv2d(stack, g.view(1, 1, -1, 1).expand(5 * c, 1, -1, 1), padding=(pad, 0), groups=5 * c)
    stack = F.conv2d(stack, g.view(1, 1, 1, -1).expand(5 * c, 1, 1, -1), padding=(0, pad), groups=5 * c)
    mu_x, mu_y, e_xx, e_yy, e_xy = stack.split(c, 1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov = e_xy - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return num / den


def ssim(pred: torch.Tensor, target: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM over pixels, channels and batch (differentiable)."""
    return ssim_map(pred, target, window_size, sigma).mean()


def photometric_loss(pred: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """The reference 3DGS loss: (1 - λ)·L1 + λ·(1 - SSIM)."""
    return (1.0 - lambda_dssim) * l1_loss(pred, target) + lambda_dssim * (1.0 - ssim(pred, target))


def ssim_reference(pred, target, window_size: int = 11, sigma: float = 1.5) -> float:
    """Slow float64 SSIM of two (H,W,C) images: an explicit window sum at every pixel, zero
    outside the image. For tests of `ssim`."""
    x = np.asarray(pred, np.float64)
    y = np.asarray(target, np.float64)
    h, w, c = x.shape
    r = window_size // 2
    t = np.arange(window_size) - (window_size - 1) / 2.0
    g1 = np.exp(-t ** 2 / (2 * sigma ** 2))
    g1 /= g1.sum()
    win = np.outer(g1, g1)
    total = 0.0
    for ch in range(c):
        for i in range(h):
            for j in range(w):
                mx = my = sxx = syy = sxy = 0.0
                for di in range(-r, r + 1):
                    for dj in range(-r, r + 1):
                        ii, jj = i + di, j + dj
                        if 0 <= ii < h and 0 <= jj < w:
                            wt = win[di + r, dj + r]
                            a, b = x[ii, jj, ch], y[ii, jj, ch]
                            mx += wt * a
                            my += wt * b
                            sxx += wt * a * a
                            syy += wt * b * b
                            sxy += wt * a * b
                vx, vy, cxy = sxx - mx * mx, syy - my * my, sxy - mx * my
                total += ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / (
                    (mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    return total / (h * w * c)
