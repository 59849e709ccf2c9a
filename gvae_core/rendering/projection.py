"""Projection stage: raw Gaussian parameters + camera -> per-Gaussian screen-space quantities.

Positions are taken relative to the camera centre in float64 before anything is rounded to the
working precision, so scenes far from the origin render like the same scene at the origin.
Everything else is written out per component on (N,) vectors (no tiny batched matrix
products), in the working dtype (float32 by default; float64 for gradient checks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .. import quaternions
from ..antialias import CLASSIC_DILATION
from ..camera import Camera
from ..conventions import LOG_SCALE_RANGE, NEAR_PLANE as NEAR, activate_opacities, activate_scales, clip, dc_to_rgb
from .sh import sh_to_rgb

#: Added to the diagonal of every 2D covariance (anti-aliasing dilation of the reference 3DGS,
#: the `classic` mode), in the pixels of the image being rendered; the opacity is not changed.
DILATION = CLASSIC_DILATION
#: The 2D Mip filter (Mip-Splatting; the `mip` mode): a screen-space Gaussian of this variance
#: (px², about a one-pixel box filter) in place of DILATION, the opacity times
#: sqrt(det Σ2D / det(Σ2D + MIP_2D_VARIANCE I)) so that the Gaussian's integral is kept.
MIP_2D_VARIANCE = 0.1
#: The 3D sizes (filter or dilation, standard deviations in world units) are clamped to this range
#: on use: the lower end is far below any clamped scale (so 0 changes nothing, exactly), the upper
#: end is the largest scale (non-finite sizes count as 0).
FILTER_3D_RANGE = (math.exp(2.0 * LOG_SCALE_RANGE[0]), math.exp(LOG_SCALE_RANGE[1]))
#: Below this, sqrt(det Σ2D / det(Σ2D + s I)) is taken at this value (it leaves the Gaussian far
#: under 1/255 anyway); keeps the square root's derivative finite for degenerate footprints.
MIP_2D_RATIO_FLOOR = 1e-12
#: The projected centre is clamped to the image widened by (FOV_CLAMP - 1) half-sizes on each side,
#: for the Jacobian only (1.3 x the half field of view for a centred principal point).
FOV_CLAMP = 1.3
#: Contributions with alpha below this are skipped; no Gaussian with opacity below it is drawn.
ALPHA_MIN = 1.0 / 255.0
#: Entries of the projected axes J W R S are clamped to this many pixels, so that the 2D
#: covariance and its determinant stay finite in float32; a Gaussian a hundred million
#: pixels wide is flat over any image anyway.
MAX_AXIS_PX = 1e8
#: Relative safety margin on the opacity-aware footprint so float32 rounding never clips it.
FOOTPRINT_MARGIN = 1e-3


def fov_limits(camera: Camera) -> tuple[float, float, float, float]:
    """(lo_x, hi_x, lo_y, hi_y): the range of x/z and y/z the Jacobian's centre is clamped to, the
    image widened by (FOV_CLAMP - 1) half-sizes on each side (gsplat's rule; for a centred principal
    point +-FOV_CLAMP half fields of view; a crop of a camera keeps its pixels' clamp)."""
    mx, my = (FOV_CLAMP - 1.0) * 0.5 * camera.width, (FOV_CLAMP - 1.0) * 0.5 * camera.height
    return (-(camera.cx + mx) / camera.fx, (camera.width - camera.cx + mx) / camera.fx,
            -(camera.cy + my) / camera.fy, (camera.height - camera.cy + my) / camera.fy)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (N rows, culled ones included with zeros).

    means2d (N,2) pixel coordinates (x = column, y = row; pixel centres at +0.5);
    conics (N,3) (a, b, c) of the inverse 2D covariance: alpha = o * exp(-a dx²/2 - b dx dy - c dy²/2);
    opacities (N,), colors (N,3), depths (N,) camera z: differentiable, in the working dtype;
    radii (N,) int32 = ceil of the footprint's larger half-width, visible (N,) bool, footprint
    (N,4) float64 = (k, Σxx, Σxy, Σyy): the footprint is the ellipse dᵀ Σ⁻¹ d <= k², where
    alpha can reach 1/255; these three are outside the autograd graph.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    visible: torch.Tensor
    footprint: torch.Tensor


def project(means, log_scales, quats, opacity_logits, sh_dc, sh_rest, camera: Camera, sh_degree: int,
            dtype: torch.dtype = torch.float32, *, filter_3d=None, mip_2d: bool = False,
            dilation_3d=None) -> Projected:
    """Project N Gaussians (raw parameters, torch) through `camera` following DESIGN.md.

    `filter_3d` (N,) (None: off): standard deviation of Mip-Splatting's isotropic world-space 3D
    filter: the covariance becomes Σ + f² I and the opacity is multiplied by
    sqrt(det Σ / det(Σ + f² I)). `mip_2d`: the 2D Mip filter (MIP_2D_VARIANCE, opacity
    compensated) in place of the classic DILATION. `dilation_3d` (N,) (None: off; not with
    the other two): the classic dilation in world units, standard deviation g: covariance
    Σ + g² I and 2D dilation max(0, DILATION - g² fx fy / z²), opacity unchanged."""
    if dilation_3d is not None and (filter_3d is not None or mip_2d):
        raise ValueError("project: dilation_3d does not go with the Mip filters")
    dev = means.device
    rel64, z, in_front, iz, u, v = _camera_space(means, camera, dtype)
    zero = torch.zeros((), dtype=dtype, device=dev)
    # Rotation to camera space as one quaternion: q_cam = q_camera ⊗ q_gaussian.
    q_camera = torch.as_tensor(quaternions.from_rotmat(camera.rotation), dtype=dtype, device=dev)
    q = quaternions.multiply(q_camera, quaternions.normalize(quats.to(dtype))).unbind(-1)
    opac = activate_opacities(opacity_logits.to(dtype))
    scales, opac, f = _effective_scales(log_scales, opac, dtype, filter_3d, dilation_3d)
    a, b = _projected_axes(q, scales, camera, iz, u, v)
    d = MIP_2D_VARIANCE if mip_2d else DILATION
    if dilation_3d is not None:  # what the 3D dilation leaves of the classic one at this depth
        d = (DILATION - f * f * (camera.fx * camera.fy) * (iz * iz)).clamp(min=0.0)
    sxx, sxy, syy, cc, inv_det = _covariance_2d(a, b, d)
    conics = torch.stack([syy * inv_det, -sxy * inv_det, sxx * inv_det], -1)
    if mip_2d:
        opac = opac * torch.sqrt((cc * inv_det).clamp(min=MIP_2D_RATIO_FLOOR))
    mx = camera.fx * u + camera.cx
    my = camera.fy * v + camera.cy
    visible, radii, footprint = _footprint(opac, sxx, sxy, syy, mx, my, in_front, camera)
    colors = _colors(rel64, sh_dc, sh_rest, sh_degree, dtype)

    vis = visible[:, None]
    means2d = torch.where(vis, torch.stack([mx, my], -1), zero)
    conics = torch.where(vis, conics, zero)
    opac = torch.where(visible, opac, zero)
    colors = torch.where(vis, colors, zero)
    depths = torch.where(visible, z, zero)
    return Projected(means2d, conics, opac, colors, depths, radii, visible, footprint)


def _camera_space(means, camera: Camera, dtype):
    """(offset from the camera in float64, camera depth z, in front of the near plane, 1/z, x/z,
    y/z): the offset is taken before any rounding to `dtype`; behind the plane 1/z is 1, x/z 0."""
    dev = means.device
    f64 = torch.float64
    center = torch.as_tensor(camera.center, dtype=f64, device=dev)
    rot = torch.as_tensor(camera.rotation, dtype=f64, device=dev)
    rel64 = means.to(f64) - center  # world offset from the camera, before any rounding
    x, y, z = (rel64 @ rot.T).to(dtype).unbind(-1)  # camera coordinates
    in_front = torch.isfinite(z) & (z > NEAR)
    one = torch.ones((), dtype=dtype, device=dev)
    zero = torch.zeros((), dtype=dtype, device=dev)
    iz = 1.0 / torch.where(in_front, z, one)
    u = torch.where(in_front, x, zero) * iz
    v = torch.where(in_front, y, zero) * iz
    return rel64, z, in_front, iz, u, v


def _effective_scales(log_scales, opac, dtype, filter_3d, dilation_3d):
    """(the three std-devs (N,) each, the opacity, the 3D size f or None): the scales activated,
    or with a 3D size R diag(s²) Rᵀ + f² I = R diag(s² + f²) Rᵀ taken in the log domain (no
    overflow, no underflow, exact identity for f = 0); the 3D filter's opacity compensation
    Π s / sqrt(s² + f²)."""
    size = filter_3d if filter_3d is not None else dilation_3d
    if size is None:
        return activate_scales(log_scales.to(dtype)).unbind(-1), opac, None
    log_s = clip(log_scales.to(dtype), *LOG_SCALE_RANGE)
    f = size.to(dtype)
    f = torch.where(torch.isfinite(f), f, torch.zeros_like(f)).clamp(*FILTER_3D_RANGE)
    log_eff = 0.5 * torch.logaddexp(2.0 * log_s, 2.0 * torch.log(f)[:, None])
    scales = log_eff.exp().unbind(-1)
    if filter_3d is not None:
        opac = opac * (log_s - log_eff).sum(-1).exp()
    return scales, opac, f


def _projected_axes(q, scales, camera: Camera, iz, u, v):
    """Rows a, b of J R diag(s): the Gaussian's axes in camera space (columns of R diag(s), R from
    the camera-space quaternion `q`) through the perspective Jacobian, whose rows are (j00, 0, j02)
    and (0, j11, j12) with the centre clamped (`fov_limits`) for it only; entries clamped to
    MAX_AXIS_PX."""
    fx, fy = camera.fx, camera.fy
    lo_x, hi_x, lo_y, hi_y = fov_limits(camera)
    j00, j11 = fx * iz, fy * iz
    j02 = -fx * u.clamp(lo_x, hi_x) * iz
    j12 = -fy * v.clamp(lo_y, hi_y) * iz
    w, qx, qy, qz = q
    s0, s1, s2 = scales
    m00, m01, m02 = (1 - 2 * (qy * qy + qz * qz)) * s0, 2 * (qx * qy - w * qz) * s1, 2 * (qx * qz + w * qy) * s2
    m10, m11, m12 = 2 * (qx * qy + w * qz) * s0, (1 - 2 * (qx * qx + qz * qz)) * s1, 2 * (qy * qz - w * qx) * s2
    m20, m21, m22 = 2 * (qx * qz - w * qy) * s0, 2 * (qy * qz + w * qx) * s1, (1 - 2 * (qx * qx + qy * qy)) * s2
    lim = MAX_AXIS_PX
    a = ((j00 * m00 + j02 * m20).clamp(-lim, lim), (j00 * m01 + j02 * m21).clamp(-lim, lim),
         (j00 * m02 + j02 * m22).clamp(-lim, lim))
    b = ((j11 * m10 + j12 * m20).clamp(-lim, lim), (j11 * m11 + j12 * m21).clamp(-lim, lim),
         (j11 * m12 + j12 * m22).clamp(-lim, lim))
    return a, b


def _covariance_2d(a, b, d):
    """(Σxx, Σxy, Σyy, det(t tᵀ), 1 / det) of Σ2D = t tᵀ + d I with rows t1 = a, t2 = b: det =
    |a x b|² + d (|a|² + |b|²) + d² is a sum of non-negative terms, >= d², no cancellation even
    for needles."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    aa = a0 * a0 + a1 * a1 + a2 * a2
    bb = b0 * b0 + b1 * b1 + b2 * b2
    sxy = a0 * b0 + a1 * b1 + a2 * b2
    c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    cc = c0 * c0 + c1 * c1 + c2 * c2  # det(t tᵀ)
    det = cc + d * (aa + bb) + d ** 2
    sxx, syy = aa + d, bb + d
    return sxx, sxy, syy, cc, 1.0 / det


def _footprint(opac, sxx, sxy, syy, mx, my, in_front, camera: Camera):
    """(visible, radii, footprint) of `Projected`, outside the autograd graph: alpha >= 1/255 <=>
    Mahalanobis² <= 2 ln(255 o), the opacity-aware footprint, in float64."""
    f64 = torch.float64
    with torch.no_grad():
        o64 = opac.detach().to(f64)
        k = torch.sqrt((2.0 * torch.log(o64 * 255.0)).clamp(min=0.0)) * (1.0 + FOOTPRINT_MARGIN) + 1e-4
        sxx64, syy64 = sxx.detach().to(f64), syy.detach().to(f64)
        ex, ey = k * torch.sqrt(sxx64), k * torch.sqrt(syy64)
        mxd, myd = mx.detach().to(f64), my.detach().to(f64)
        visible = (in_front & (opac.detach() >= ALPHA_MIN)
                   & (mxd + ex >= 0.5) & (mxd - ex <= camera.width - 0.5)
                   & (myd + ey >= 0.5) & (myd - ey <= camera.height - 0.5))
        big = float(4 * max(camera.width, camera.height))
        radii = torch.where(visible, torch.ceil(torch.maximum(ex, ey).clamp(max=big)), torch.zeros_like(ex))
        radii = radii.to(torch.int32)
        footprint = torch.stack([k, sxx64, sxy.detach().to(f64), syy64], -1)
    return visible, radii, footprint


def _colors(rel64, sh_dc, sh_rest, sh_degree: int, dtype):
    """Colour from SH along normalise(mean − camera centre) (DC only without higher bands)."""
    if sh_rest.shape[1] and sh_degree > 0:
        n2 = (rel64 * rel64).sum(-1, keepdim=True)
        ok = n2 > 1e-300
        dirs = (torch.where(ok, rel64, torch.zeros_like(rel64))
                / torch.sqrt(torch.where(ok, n2, torch.ones_like(n2)))).to(dtype)
        return sh_to_rgb(sh_dc.to(dtype), sh_rest.to(dtype), dirs, sh_degree)
    return dc_to_rgb(sh_dc.to(dtype))
