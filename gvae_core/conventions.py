"""The conventions of raw 3DGS parameters (DESIGN.md), defined once for the whole project.

Parameters are stored raw, as the reference 3DGS PLY stores them, and activated on use with the
functions here: log-scales through `exp`, opacity logits through the sigmoid, the SH DC term
through `SH_C0 * dc + 0.5`. Each function takes numpy arrays or torch tensors and returns the
same kind; torch is never imported here. (The float64 reference renderer keeps its own copies on
purpose: it is the check on the fast path.)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Number of SH "rest" coefficients per channel for SH degree 0..3.
SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}
#: The SH degree that has K rest coefficients per channel.
SH_DEGREE_OF_REST = {k: d for d, k in SH_REST_COUNTS.items()}

# Real spherical harmonics constants of the reference 3DGS code, band by band.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

#: Log-scales are clamped to this range before `exp`. exp(-30) ~ 1e-13 is far below the
#: resolution of any float32 position, so smaller Gaussians are points anyway; exp(20) ~ 5e8 scene
#: units is larger than any scene, and its square (a covariance entry) times a pixel-scale
#: Jacobian stays finite in float32.
LOG_SCALE_RANGE = (-30.0, 20.0)
#: Opacity logits are clamped to this range before the sigmoid: sigmoid(-50) ~ 2e-22 is still a
#: positive float32 (the rasteriser takes its log), exp(50) does not overflow float32.
OPACITY_LOGIT_RANGE = (-50.0, 50.0)


def is_torch(x: Any) -> bool:
    """True for a torch tensor, without importing torch."""
    return type(x).__module__.startswith("torch")


def clip(x, lo: float, hi: float):
    """np.clip or Tensor.clamp, whichever `x` needs."""
    return x.clamp(lo, hi) if is_torch(x) else np.clip(x, lo, hi)


def activate_scales(log_scales):
    """Standard deviations: exp of the clamped log-scales."""
    x = clip(log_scales, *LOG_SCALE_RANGE)
    return x.exp() if is_torch(x) else np.exp(x)


def activate_opacities(logits):
    """Opacities in [0, 1]: the sigmoid of the clamped logits."""
    x = clip(logits, *OPACITY_LOGIT_RANGE)
    return x.sigmoid() if is_torch(x) else 1.0 / (1.0 + np.exp(-x))


def opacity_logit(p: float) -> float:
    """The raw opacity (logit) of an opacity p in (0, 1)."""
    return math.log(p / (1.0 - p))


def dc_to_rgb(sh_dc):
    """The view-independent colour of the SH DC term: SH_C0 * dc + 0.5, clamped at 0."""
    c = sh_dc * SH_C0 + 0.5
    return c.clamp(min=0.0) if is_torch(c) else np.maximum(c, 0.0)


def rgb_to_dc(rgb):
    """The SH DC term whose colour is `rgb` (the inverse of `dc_to_rgb` above 0)."""
    return (rgb - 0.5) / SH_C0
