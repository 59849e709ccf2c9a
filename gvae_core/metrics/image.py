"""Image quality of a cloud's renders against ground-truth views: PSNR and SSIM (full-reference)
and NIQE (no-reference, `gvae_core.metrics.niqe`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from ..losses import psnr, ssim
from ..rendering import RenderSettings, render
from .niqe import niqe


@dataclass
class ImageScores:
    """Means over the views: PSNR (dB), SSIM, and NIQE (lower is better; NaN where the images
    are too small for it)."""

    psnr: float
    ssim: float
    niqe: float
    n_views: int
    height: int

    def as_dict(self) -> dict:
        return asdict(self)


def background_of(cloud, background=None) -> tuple[float, float, float]:
    """The background to draw `cloud` over: `background` when given, else the one it was trained
    over (`GaussianCloud.background`), else white (the benchmark scenes')."""
    if background is not None:
        return tuple(float(v) for v in background)
    return cloud.background or (1.0, 1.0, 1.0)


def render_views(cloud, views, background=None, sh_degree: int | None = None,
                 antialias: str | None = None, device=None) -> np.ndarray:
    """(N,H,W,3) float32 renders of `cloud` from every camera of `views` over `background`
    (`background_of`), clamped to [0,1]. `antialias`: a `gvae_core.rendering.ANTIALIAS_MODES`
    mode (default: RenderSettings'); `device`: the torch device to render on (default: the
    cloud's, the CPU for numpy)."""
    background = background_of(cloud, background)
    c = cloud.to_torch(device=device) if device is not None or not cloud.is_torch else cloud
    settings = RenderSettings() if antialias is None else RenderSettings(antialias=antialias)
    with torch.no_grad():
        return np.stack([render(c, cam, background=background, sh_degree=sh_degree, settings=settings)
                         .image.clamp(0, 1).cpu().numpy() for cam in views.cameras])


def image_scores(cloud, views, background=None, *, no_reference: bool = True,
                 images: np.ndarray | None = None, antialias: str | None = None, device=None) -> ImageScores:
    """PSNR and SSIM of the renders against `views` composited on `background` (`background_of`:
    by default the one the cloud was trained over), and the mean NIQE of the renders (skipped, NaN,
    when `no_reference` is False or the images are under 193 px). `images`: renders made already
    (skips rendering); `antialias`, `device`: as for `render_views`."""
    background = background_of(cloud, background)
    pred = (render_views(cloud, views, background, antialias=antialias, device=device) if images is None
            else np.asarray(images, np.float32))
    target = views.composite(background)
    p = [min(psnr(a, b), 100.0) for a, b in zip(pred, target)]
    s = [float(ssim(torch.from_numpy(a), torch.from_numpy(b))) for a, b in zip(pred, target)]
    nr = float("nan")
    if no_reference and min(pred.shape[1:3]) > 192:
        nr = float(np.mean([niqe(a) for a in pred]))
    return ImageScores(float(np.mean(p)), float(np.mean(s)), nr, len(pred), int(pred.shape[1]))
