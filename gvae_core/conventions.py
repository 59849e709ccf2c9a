"""The conventions of raw 3DGS parameters (DESIGN.md), defined once for the whole project.

Parameters are stored raw, as the reference 3DGS PLY stores them, and activated on use with the
functions here: log-scales through `exp`, opacity logits through the sigmoid (`activate_opacities`
clamped, `sigmoid` as it is), the SH DC term through `SH_C0 * dc + 0.5`. Each function takes numpy
arrays or torch tensors and returns the same kind; torch is never imported here. (The float64
reference renderer keeps its own copies on purpose: it is the check on the fast path; so do the
compiled kernels, which call no Python.)
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

#: Near plane: Gaussians whose camera depth is <= NEAR_PLANE are culled before any division (DESIGN.md).
NEAR_PLANE = 0.01
#: Log-scales are clamped to this range before `exp`. exp(-30) ~ 1e-13 is far below the
#: resolution of any float32 position, so smaller Gaussians are points anyway; exp(20) ~ 5e8 scene
#: units is larger than any scene, and its square (a covariance entry) times a pixel-scale
#: Jacobian stays finite in float32.
LOG_SCALE_RANGE = (-30.0, 20.0)
#: Opacity logits are clamped to this range before the sigmoid: sigmoid(-50) ~ 2e-22 is still a
#: positive float32 (the rasteriser takes its log), exp(50) does not overflow float32.
OPACITY_LOGIT_RANGE = (-50.0, 50.0)
#: Compositing (DESIGN.md, Rendering semantics): a Gaussian's alpha is capped at ALPHA_MAX and a
#: contribution below ALPHA_MIN is skipped, so no Gaussian with opacity below ALPHA_MIN is drawn.
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
#: Variance (px²) of Mip-Splatting's 2D filter, the screen-space part of the `mip` anti-aliasing
#: mode (gvae_core.antialias); the renderer's copy is gvae_core.rendering.projection's.
MIP_2D_VARIANCE = 0.1
#: The sRGB EOTF (display-referred value -> linear; DESIGN.md, Colour in Blender):
#: c / 12.92 below 0.04045, else ((c + 0.055) / 1.055) ** 2.4: (threshold, slope, offset, scale, gamma).
SRGB_EOTF = (0.04045, 12.92, 0.055, 1.055, 2.4)


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


def sigmoid(x):
    """The logistic 1 / (1 + exp(-x)) of opacity logits, unclamped: a logit of +inf is opacity 1 and
    -inf opacity 0 exactly (DESIGN.md, Numerical guards), a large finite one rounds to 0 or 1 without
    a warning. The project's one sigmoid (tests/test_layout.py): the formats and the add-on apply it
    to the raw logits, `activate_opacities` to the clamped ones. torch: `Tensor.sigmoid`. numpy:
    float32 stays float32, computed as Niantic's spz encoder does it (exp correctly rounded, via
    float64, then 1 / (1 + e) in float32: the formats' 8-bit codes match its); the rest in float64."""
    if is_torch(x):
        return x.sigmoid()
    dtype = np.float32 if np.asarray(x).dtype == np.float32 else np.float64
    with np.errstate(over="ignore"):
        e = np.exp(-np.asarray(x, np.float64)).astype(dtype, copy=False)
    return dtype(1.0) / (dtype(1.0) + e)


def activate_opacities(logits):
    """Opacities in [0, 1]: the sigmoid of the clamped logits."""
    return sigmoid(clip(logits, *OPACITY_LOGIT_RANGE))


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


def footprint_sigmas(opacity):
    """How many standard deviations from its centre a Gaussian of (activated) opacity o can still
    reach alpha ALPHA_MIN: sqrt(2 ln(o / ALPHA_MIN)), 0 for o <= ALPHA_MIN (numpy)."""
    return np.sqrt(2.0 * np.log(np.maximum(np.asarray(opacity, np.float64) / ALPHA_MIN, 1.0)))


def srgb_to_linear(c, dtype=np.float64):
    """The sRGB EOTF (numpy, in `dtype`), extended above 1 by its power law: what a Blender material
    emits for a display-referred colour c >= 0 so that the Standard view transform shows c."""
    thr, slope, off, scale, gamma = (np.dtype(dtype).type(v) for v in SRGB_EOTF)
    c = np.asarray(c, dtype)
    return np.where(c < thr, c / slope, ((np.maximum(c, dtype(0)) + off) / scale) ** gamma)


def linear_to_srgb(x):
    """The inverse of `srgb_to_linear` (numpy): the Standard view transform's encoding."""
    thr, slope, off, scale, gamma = SRGB_EOTF
    x = np.asarray(x, np.float64)
    return np.where(x < thr / slope, x * slope, scale * np.maximum(x, 0.0) ** (1.0 / gamma) - off)
