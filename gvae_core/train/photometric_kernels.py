"""Compiled kernels of the training loss (Numba, the renderer's `rendering.kernels.kernel`: no GIL,
cached on disk), driven in threads by `train.photometric`.

The loss is `losses.photometric_loss`: (1 - λ)·L1 + λ·(1 - SSIM), SSIM with the 11-tap Gaussian
window and zero padding; these kernels give its value and its gradient with respect to the
rendered image in four passes over rows of a channels-last image flattened to (H, W·C): the
window's horizontal then vertical sums of x, y, x², y², xy; per pixel the SSIM and its derivatives
with respect to the three local statistics that depend on x (μx, E[x²], E[xy]); the same window
(symmetric, so its own transpose) over those three; the gradient. Each pass's inner loop runs
along a row with no branches, so the compiler vectorises it. Imported on first use (it imports
Numba).
"""

from __future__ import annotations

import numpy as np

from ..losses import SSIM_C1, SSIM_C2
from ..rendering.kernels import inline, kernel

f32 = np.float32
_C1, _C2 = f32(SSIM_C1), f32(SSIM_C2)
_ONE, _TWO, _ZERO = f32(1.0), f32(2.0), f32(0.0)


@inline
def _column_sums(planes, window, i, sums):
    """sums[k] = the window's vertical sums at row i of planes[k] (K, H, W·C), zero outside it."""
    h, half = planes.shape[1], len(window) // 2
    for k in range(sums.shape[0]):
        dst = sums[k]
        dst[:] = _ZERO
        for t in range(-half, half + 1):
            if 0 <= i + t < h:
                w, src = window[t + half], planes[k, i + t]
                for j in range(dst.shape[0]):
                    dst[j] += w * src[j]


@kernel
def blur_rows(planes, window, channels, r0, r1, out):
    """Rows r0..r1-1 of the window's horizontal sums of x, y, x², y², xy (planes: x and y, (2, H,
    W·C)) into out[0..4], zero outside the image. Each row is copied into a zero-padded buffer and
    summed into buffers of this kernel's own (the loops vectorise where they would not on views
    that might overlap)."""
    wc = planes.shape[2]
    half = len(window) // 2
    pad = half * channels
    px = np.zeros(wc + 2 * pad, np.float32)
    py = np.zeros(wc + 2 * pad, np.float32)
    a0 = np.empty(wc, np.float32)
    a1 = np.empty(wc, np.float32)
    a2 = np.empty(wc, np.float32)
    a3 = np.empty(wc, np.float32)
    a4 = np.empty(wc, np.float32)
    for i in range(r0, r1):
        px[pad:pad + wc] = planes[0, i]
        py[pad:pad + wc] = planes[1, i]
        a0[:] = _ZERO
        a1[:] = _ZERO
        a2[:] = _ZERO
        a3[:] = _ZERO
        a4[:] = _ZERO
        for t in range(2 * half + 1):
            w = window[t]
            shift = t * channels
            for j in range(wc):
                a, b = px[j + shift], py[j + shift]
                a0[j] += w * a
                a1[j] += w * b
                a2[j] += w * a * a
                a3[j] += w * b * b
                a4[j] += w * a * b
        out[0, i] = a0
        out[1, i] = a1
        out[2, i] = a2
        out[3, i] = a3
        out[4, i] = a4


@kernel
def blur_derivatives(derivs, window, channels, r0, r1, out):
    """Rows r0..r1-1 of the window's horizontal sums of derivs[0..2] into out[0..2] (as blur_rows)."""
    wc = derivs.shape[2]
    half = len(window) // 2
    pad = half * channels
    p0 = np.zeros(wc + 2 * pad, np.float32)
    p1 = np.zeros(wc + 2 * pad, np.float32)
    p2 = np.zeros(wc + 2 * pad, np.float32)
    a0 = np.empty(wc, np.float32)
    a1 = np.empty(wc, np.float32)
    a2 = np.empty(wc, np.float32)
    for i in range(r0, r1):
        p0[pad:pad + wc] = derivs[0, i]
        p1[pad:pad + wc] = derivs[1, i]
        p2[pad:pad + wc] = derivs[2, i]
        a0[:] = _ZERO
        a1[:] = _ZERO
        a2[:] = _ZERO
        for t in range(2 * half + 1):
            w = window[t]
            shift = t * channels
            for j in range(wc):
                a0[j] += w * p0[j + shift]
                a1[j] += w * p1[j + shift]
                a2[j] += w * p2[j + shift]
        out[0, i] = a0
        out[1, i] = a1
        out[2, i] = a2


@kernel
def ssim_rows(hsums, window, r0, r1, derivs, row_sums):
    """Rows r0..r1-1: the vertical window sums of `hsums` (blur_rows' five), the SSIM of each
    value (summed into row_sums[i]) and its derivatives with respect to μx, E[x²] and E[xy] into
    derivs[0..2]."""
    wc = hsums.shape[2]
    sums = np.empty((5, wc), np.float32)
    for i in range(r0, r1):
        _column_sums(hsums, window, i, sums)
        mx, my, exx, eyy, exy = sums[0], sums[1], sums[2], sums[3], sums[4]
        d0, d1, d2 = derivs[0, i], derivs[1, i], derivs[2, i]
        total = 0.0
        for j in range(wc):
            ux, uy = mx[j], my[j]
            a1 = _TWO * ux * uy + _C1
            a2 = _TWO * (exy[j] - ux * uy) + _C2
            b1 = ux * ux + uy * uy + _C1
            b2 = (exx[j] - ux * ux) + (eyy[j] - uy * uy) + _C2
            inv = _ONE / (b1 * b2)
            s = a1 * a2 * inv
            total += s
            d0[j] = _TWO * uy * (a2 - a1) * inv + _TWO * ux * s * (_ONE / b2 - _ONE / b1)
            d1[j] = -s / b2
            d2[j] = _TWO * a1 * inv
        row_sums[i] = total


@kernel
def gradient_rows(planes, hsums, window, l1_weight, ssim_weight, r0, r1, grad, row_sums):
    """Rows r0..r1-1 of d loss / d x: l1_weight·sign(x - y) - ssim_weight·(B0 + 2x·B1 + y·B2),
    B the vertical window sums of `hsums` (the horizontal ones of ssim_rows' derivatives); the
    rows' |x - y| summed into row_sums[i]."""
    wc = hsums.shape[2]
    sums = np.empty((3, wc), np.float32)
    for i in range(r0, r1):
        _column_sums(hsums, window, i, sums)
        b0, b1, b2 = sums[0], sums[1], sums[2]
        x, y, g = planes[0, i], planes[1, i], grad[i]
        total = 0.0
        for j in range(wc):
            d = x[j] - y[j]
            sign = f32(d > _ZERO) - f32(d < _ZERO)
            total += abs(d)
            g[j] = l1_weight * sign - ssim_weight * (b0[j] + _TWO * x[j] * b1[j] + y[j] * b2[j])
        row_sums[i] = total


KERNELS = ("blur_rows", "blur_derivatives", "ssim_rows", "gradient_rows")
