"""The 3DGS split rule and the units of densification's gradients, shared by the trainer
(`gvae_core.train.strategy`), the plain-split control, the synthetic lineages and refine's children."""

from __future__ import annotations

import math

import torch

from .conventions import activate_scales

__all__ = ["split_children", "g_scale"]


def split_children(means, log_scales, rotmats, normals, n_children: int = 2):
    """The 3DGS split of Gaussians into `n_children` each: a child's centre is drawn from the
    parent Gaussian, its log-scale is the parent's minus log(0.8 n_children) (scale / 1.6 for two).
    `normals`: standard-normal draws (..., 3), one per child, from the caller's generator (numpy or
    torch, like the other arrays); `rotmats` (..., 3, 3) the parents' rotations. Returns the
    children's (means, log-scales)."""
    offsets = (rotmats @ (normals * activate_scales(log_scales))[..., None])[..., 0]
    return means + offsets, log_scales - math.log(0.8 * n_children)


def g_scale(width: int, height: int, device=None) -> torch.Tensor:
    """Pixel-to-NDC factor of screen-space gradients: d(ndc)/d(pixel) = 2/size, so a gradient
    with respect to pixels times size/2 is the gradient with respect to NDC."""
    return torch.tensor([0.5 * width, 0.5 * height], device=device)
