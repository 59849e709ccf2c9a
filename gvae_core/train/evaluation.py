"""How well a cloud draws views: PSNR and SSIM of its renders against their images, the one
measure training, compaction and refine report (`evaluate_views`), and the three figures a
trained stage is logged with (`stage_scores`)."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..cloud import GaussianCloud
from ..datasets import Views
from ..losses import psnr, ssim
from ..rendering import RenderSettings, render

__all__ = ["evaluate_views", "evaluate_psnr", "training_targets", "stage_scores", "rounded"]


def training_targets(views: Views, background) -> torch.Tensor:
    """The views' photos composited on `background`, as the trainer's (N, H, W, 3) float tensor."""
    return torch.from_numpy(np.ascontiguousarray(views.composite(background)))


def evaluate_views(cloud: GaussianCloud, views: Views | None, background, sh_degree: int,
                   max_views: int | None = None, settings: RenderSettings | None = None, *,
                   with_ssim: bool = True) -> tuple[float, float]:
    """Mean PSNR and SSIM (NaN without `with_ssim`) over (up to `max_views` evenly spaced) views,
    images composited on background; NaN, NaN without views."""
    if views is None or len(views) == 0:
        return float("nan"), float("nan")
    n = len(views)
    pick = range(n) if max_views is None or max_views >= n else np.linspace(0, n - 1, max_views).round().astype(int)
    targets = torch.from_numpy(views.composite(background))
    psnrs, ssims = [], []
    with torch.no_grad():
        for i in pick:
            out = render(cloud, views.cameras[i], background=background, sh_degree=sh_degree, settings=settings)
            image = out.image.clamp(0, 1).cpu()
            psnrs.append(min(psnr(image, targets[i]), 100.0))
            if with_ssim:
                ssims.append(float(ssim(image, targets[i])))
    return float(np.mean(psnrs)), float(np.mean(ssims)) if ssims else float("nan")


def evaluate_psnr(cloud: GaussianCloud, views: Views | None, background, sh_degree: int,
                  max_views: int | None = None, settings: RenderSettings | None = None) -> float:
    """Mean PSNR over (up to `max_views` evenly spaced) views, images composited on background."""
    return evaluate_views(cloud, views, background, sh_degree, max_views, settings, with_ssim=False)[0]


def stage_scores(cloud: GaussianCloud, config, degree: int, settings: RenderSettings, train: Views,
                 validation: Views | None, test: Views | None) -> dict[str, float | None]:
    """A trained stage's figures, rounded as its log keeps them (None where there are no such
    views): PSNR on `config.train_eval_views` training views, on the validation photos, and PSNR
    and SSIM on (`config.test_eval_views` of) the held-out ones."""
    bg = config.background
    train_psnr = evaluate_psnr(cloud, train, bg, degree, config.train_eval_views, settings)
    val_psnr = evaluate_psnr(cloud, validation, bg, degree, None, settings)
    test_psnr, test_ssim = evaluate_views(cloud, test, bg, degree, config.test_eval_views, settings)
    return {"train_psnr": round(train_psnr, 4), "validation_psnr": rounded(val_psnr, 4),
            "test_psnr": rounded(test_psnr, 4), "test_ssim": rounded(test_ssim, 5)}


def rounded(x: float | None, digits: int) -> float | None:
    """`x` rounded, None for None or NaN (JSON has no NaN)."""
    return None if x is None or math.isnan(x) else round(float(x), digits)
