"""Hessian-guided sampling (DESIGN.md step 4): a per-Gaussian second-order importance score.

The score is built from the Gauss-Newton (Fisher) block H_i = J_i^T J_i of the rendered images
with respect to Gaussian i's position (in the scene-normalised frame) and log-scale (6x6),
summed over views. It needs no ground truth: with random +-1 pixel weights v, one ordinary
backward pass of sum_p v_p I_p gives g_i = J_i^T v for every Gaussian at once, and
E[g_i g_i^T] = J_i^T J_i. `probes` such passes per view average to the estimate.
Score: log det(I + H_i / lambda) with a ridge lambda relative to the mean block trace (finite,
>= 0, 0 for invisible Gaussians), or the trace of H_i.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from .camera import Camera
from .cloud import GaussianCloud
from .rendering import render

BLOCK = 6  # position (3) + log-scale (3)


def default_views(cloud: GaussianCloud, views: int = 4, resolution: int = 96,
                  fov_x: float = math.radians(50.0), normalization=None) -> list[Camera]:
    """`views` cameras spread over a sphere around the cloud (Fibonacci lattice), each looking at
    its robust centre from where a sphere of 1.4 half-extents just fits. `normalization`: the
    cloud's (centre, scale) when known (`GaussianCloud.normalization`)."""
    center, half = normalization or cloud.normalization()
    radius = 1.4 * half / math.sin(0.5 * fov_x)  # a sphere of radius 1.4 half-extents fills the view
    cams = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for k in range(max(int(views), 1)):
        z = 0.85 - 1.5 * (k + 0.5) / max(views, 1)  # mostly the upper hemisphere, like NeRF-Synthetic
        r = math.sqrt(max(1.0 - z * z, 0.0))
        d = np.array([r * math.cos(golden * k), r * math.sin(golden * k), z])
        cams.append(Camera.look_at(center + radius * d, center, (0.0, 0.0, 1.0), width=resolution,
                                   height=resolution, fov_x=fov_x))
    return cams


def _prepare(cloud: GaussianCloud):
    """A float32 torch copy whose means and log-scales are leaves that require grad."""
    c = cloud.detach().to_torch(dtype=torch.float32) if cloud.is_torch else cloud.to_torch(dtype=torch.float32)
    means = c.means.detach().clone().requires_grad_(True)
    scales = c.scales.detach().clone().requires_grad_(True)
    return c.replace(means=means, scales=scales), means, scales


def _gradient(output: torch.Tensor, means: torch.Tensor, scales: torch.Tensor, scale: float,
              retain: bool) -> torch.Tensor:
    """(N,6) float64 gradient of a scalar output: position (normalised frame), log-scale."""
    gm, gs = torch.autograd.grad(output, [means, scales], retain_graph=retain, allow_unused=True)
    gm = torch.zeros_like(means) if gm is None else gm
    gs = torch.zeros_like(scales) if gs is None else gs
    return torch.nan_to_num(torch.cat([gm * scale, gs], 1).double(), nan=0.0, posinf=0.0, neginf=0.0)


def _render_image(cloud: GaussianCloud, camera: Camera, settings=None) -> torch.Tensor:
    return render(cloud, camera, settings=settings).image


def hessian_blocks(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None, *, probes: int = 4,
                   views: int = 4, resolution: int = 96, seed: int = 0, render_settings=None,
                   normalization=None) -> torch.Tensor:
    """(N,6,6) Hutchinson-style estimate of sum over views of J_i^T J_i (position in the
    normalised frame, log-scale), from `probes` Rademacher-weighted backward passes per view.
    `render_settings`: a `gvae_core.rendering.RenderSettings` (speed/memory knobs only);
    `normalization`: the cloud's (centre, scale) when known (`GaussianCloud.normalization`)."""
    if probes < 1:
        raise ValueError(f"hessian: probes must be >= 1, got {probes}")
    n = len(cloud)
    blocks = torch.zeros((n, BLOCK, BLOCK), dtype=torch.float64)
    if n == 0:
        return blocks
    normalization = normalization or cloud.normalization()
    cams = list(cameras) if cameras is not None else default_views(cloud, views, resolution,
                                                                   normalization=normalization)
    scale = normalization[1]
    rc, means, scales = _prepare(cloud)
    gen = torch.Generator().manual_seed(int(seed))
    for cam in cams:
        image = _render_image(rc, cam, render_settings)
        if not image.requires_grad:
            continue
        for p in range(probes):
            v = torch.randint(0, 2, image.shape, generator=gen).to(image.dtype).mul_(2).sub_(1)
            g = _gradient((image * v).sum(), means, scales, scale, retain=p < probes - 1)
            blocks += g[:, :, None] * g[:, None, :]
    return blocks / probes


def hessian_blocks_reference(cloud: GaussianCloud, cameras: Sequence[Camera], render_settings=None) -> torch.Tensor:
    """Slow exact reference: J_i^T J_i accumulated pixel by pixel (one backward per pixel channel)."""
    n = len(cloud)
    blocks = torch.zeros((n, BLOCK, BLOCK), dtype=torch.float64)
    scale = cloud.normalization()[1]
    rc, means, scales = _prepare(cloud)
    for cam in cameras:
        image = _render_image(rc, cam, render_settings).reshape(-1)
        for p in range(image.numel()):
            if not image[p].requires_grad:
                continue
            g = _gradient(image[p], means, scales, scale, retain=True)
            blocks += g[:, :, None] * g[:, None, :]
    return blocks


def scores_from_blocks(blocks: torch.Tensor, score: str = "logdet", ridge: float = 1e-2) -> torch.Tensor:
    """(N,) float32 scores from (N,6,6) blocks: 'trace', or 'logdet' = log det(I + H/lambda) with
    lambda = ridge * mean(trace)/6 (so the score does not depend on the image scale)."""
    if score not in ("logdet", "trace"):
        raise ValueError(f"hessian: score must be 'logdet' or 'trace', got {score!r}")
    h = torch.nan_to_num(blocks.double(), nan=0.0, posinf=0.0, neginf=0.0)
    h = 0.5 * (h + h.transpose(1, 2))
    trace = torch.diagonal(h, dim1=1, dim2=2).sum(-1).clamp(min=0.0)
    if score == "trace" or len(h) == 0:
        return trace.float()
    lam = ridge * float(trace.mean()) / BLOCK
    if not math.isfinite(lam) or lam <= 0.0:
        return torch.zeros(len(h), dtype=torch.float32)
    eig = torch.linalg.eigvalsh(h / lam).clamp(min=0.0)
    return torch.log1p(eig).sum(-1).float()


def hessian_scores(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None, *, probes: int = 4,
                   views: int = 4, score: str = "logdet", seed: int = 0, resolution: int = 96,
                   ridge: float = 1e-2, render_settings=None, normalization=None) -> torch.Tensor:
    """(N,) finite, non-negative per-Gaussian scores: the Gauss-Newton block of the renders over
    `cameras` (or `views` cameras around the cloud at `resolution` px), estimated with `probes`
    random +-1 pixel weightings per view; see the module docstring."""
    if score not in ("logdet", "trace"):
        raise ValueError(f"hessian: score must be 'logdet' or 'trace', got {score!r}")
    blocks = hessian_blocks(cloud, cameras, probes=probes, views=views, resolution=resolution, seed=seed,
                            render_settings=render_settings, normalization=normalization)
    return scores_from_blocks(blocks, score, ridge)
