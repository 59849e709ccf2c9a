"""The training loss, compiled: `photometric_loss(pred, target, λ)` is `losses.photometric_loss`
((1 - λ)·L1 + λ·(1 - SSIM)) with its value and its gradient from `photometric_kernels` in one
pass, where the renderer's kernels run (a float32 (H, W, C) image on the CPU, Numba there) and the
target needs no gradient; elsewhere, and with `compiled=False`, the torch code, which is what the
tests hold it to.

Torch's autograd of the same loss keeps a dozen image-sized intermediates and runs grouped
convolutions forward and back; here the gradient is four passes over rows in threads and is kept
for the backward, which only scales it.
"""

from __future__ import annotations

import numpy as np
import torch

from ..losses import gaussian_window
from ..losses import photometric_loss as torch_photometric_loss
from ..parallel import run
from ..rendering.compiled import use_compiled

__all__ = ["photometric_loss", "loss_and_gradient"]

#: Rows per thread's task: a few tasks per thread even at 200 px.
_ROWS = 32


def _kernels():
    from . import photometric_kernels  # noqa: PLC0415 - imports Numba, on first use

    return photometric_kernels


def _in_rows(height: int, work) -> None:
    """work(a, b) for runs of `_ROWS` rows covering 0..height, in threads (`parallel.run`)."""
    run([lambda a=a: work(a, min(a + _ROWS, height)) for a in range(0, height, _ROWS)], "gvae-loss")


def loss_and_gradient(pred: np.ndarray, target: np.ndarray, lambda_dssim: float,
                      window_size: int = 11, sigma: float = 1.5) -> tuple[float, np.ndarray]:
    """The loss of two float32 (H, W, C) images (any strides) and its gradient with respect to `pred`."""
    k = _kernels()
    h, w, c = pred.shape
    planes = np.empty((2, h, w * c), np.float32)
    planes[0].reshape(h, w, c)[...] = pred  # (one copy each, into the rows the kernels read)
    planes[1].reshape(h, w, c)[...] = target
    window = gaussian_window(window_size, sigma).numpy().astype(np.float32)
    hsums = np.empty((5, h, w * c), np.float32)
    derivs = np.empty((3, h, w * c), np.float32)
    ssim_sums, l1_sums = np.zeros(h), np.zeros(h)
    _in_rows(h, lambda a, b: k.blur_rows(planes, window, c, a, b, hsums))
    _in_rows(h, lambda a, b: k.ssim_rows(hsums, window, a, b, derivs, ssim_sums))
    _in_rows(h, lambda a, b: k.blur_derivatives(derivs, window, c, a, b, hsums[:3]))
    n = h * w * c
    grad = np.empty((h, w * c), np.float32)
    _in_rows(h, lambda a, b: k.gradient_rows(planes, hsums[:3], window, np.float32((1.0 - lambda_dssim) / n),
                                             np.float32(lambda_dssim / n), a, b, grad, l1_sums))
    loss = (1.0 - lambda_dssim) * l1_sums.sum() / n + lambda_dssim * (1.0 - ssim_sums.sum() / n)
    return float(loss), grad.reshape(h, w, c)


class _PhotometricFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, target, lambda_dssim):
        loss, grad = loss_and_gradient(pred.detach().numpy(), target.detach().numpy(), float(lambda_dssim))
        ctx.save_for_backward(torch.from_numpy(grad))
        return pred.new_tensor(loss)

    @staticmethod
    def backward(ctx, grad_out):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None


def photometric_loss(pred: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2, *,
                     compiled: bool = True) -> torch.Tensor:
    """(1 - λ)·L1 + λ·(1 - SSIM) of an (H, W, C) render against its photo (module docstring)."""
    if (compiled and pred.ndim == 3 and pred.shape == target.shape and not target.requires_grad
            and pred.dtype == target.dtype and target.device == pred.device
            and use_compiled("auto", pred.device, pred.dtype)):
        return _PhotometricFunction.apply(pred, target, lambda_dssim)
    return torch_photometric_loss(pred, target, lambda_dssim)
