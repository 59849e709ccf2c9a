"""Slow, obviously correct float64 reference renderer (numpy): every pixel looks at every
Gaussian, in depth order, with the rules of "Rendering semantics" in DESIGN.md. No tiles, no
footprints, no batching tricks: the fast renderer must agree with it to float32 precision."""

from __future__ import annotations

import numpy as np

from ..antialias import DILATION_KEY, FILTER_KEY
from ..camera import Camera
from ..cloud import GaussianCloud

NEAR = 0.01
DILATION = 0.3  # "classic": added to the 2D covariance, opacity unchanged
MIP_2D = 0.1  # "mip": added to the 2D covariance, opacity times sqrt(det ratio)
FILTER_MAX = float(np.exp(20.0))  # 3D filter std clamp (non-finite -> 0)
FOV_CLAMP = 1.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
LOG_SCALE_RANGE = (-30.0, 20.0)
OPACITY_LOGIT_RANGE = (-50.0, 50.0)

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def _np64(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def sh_color(dc: np.ndarray, rest: np.ndarray, d: np.ndarray, degree: int) -> np.ndarray:
    """RGB (N,3) of SH coefficients dc (N,3), rest (N,K,3) seen along unit directions d (N,3)."""
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    c = C0 * dc
    if degree >= 1:
        c = c - C1 * y * rest[:, 0] + C1 * z * rest[:, 1] - C1 * x * rest[:, 2]
    if degree >= 2:
        c = (c + C2[0] * x * y * rest[:, 3] + C2[1] * y * z * rest[:, 4]
             + C2[2] * (2 * z * z - x * x - y * y) * rest[:, 5]
             + C2[3] * x * z * rest[:, 6] + C2[4] * (x * x - y * y) * rest[:, 7])
    if degree >= 3:
        c = (c + C3[0] * y * (3 * x * x - y * y) * rest[:, 8] + C3[1] * x * y * z * rest[:, 9]
             + C3[2] * y * (4 * z * z - x * x - y * y) * rest[:, 10]
             + C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y) * rest[:, 11]
             + C3[4] * x * (4 * z * z - x * x - y * y) * rest[:, 12]
             + C3[5] * z * (x * x - y * y) * rest[:, 13] + C3[6] * x * (x * x - 3 * y * y) * rest[:, 14])
    return np.maximum(c + 0.5, 0.0)


def _sizes(cloud: GaussianCloud, key: str) -> np.ndarray:
    f = _np64(cloud.extra[key]).reshape(-1)
    return np.clip(np.where(np.isfinite(f), f, 0.0), 0.0, FILTER_MAX)


def _modes(cloud: GaussianCloud, antialias: str):
    """(Mip 3D filter std-devs or None, 2D Mip filter on, world dilation std-devs or None)."""
    if antialias not in ("auto", "classic", "mip", "matched"):
        raise ValueError(f"unknown antialias mode {antialias!r}")
    has_filter, has_dilation = FILTER_KEY in cloud.extra, DILATION_KEY in cloud.extra
    if antialias == "auto":
        antialias = "mip" if has_filter else "matched" if has_dilation else "classic"
    if antialias == "mip":
        return (_sizes(cloud, FILTER_KEY) if has_filter else None), True, None
    if antialias == "matched" and has_dilation:
        return None, False, _sizes(cloud, DILATION_KEY)
    return None, False, None


def project_reference(cloud: GaussianCloud, camera: Camera, sh_degree: int | None = None,
                      antialias: str = "auto") -> dict:
    """Per-Gaussian float64 screen quantities: mean2d (N,2), conic (N,2,2) = inverse 2D
    covariance, opacity (N,), color (N,3), depth (N,), valid (N,) = in front of the near plane.
    `antialias`: "classic" (2D covariance + 0.3 I), "mip" (3D covariance + filter_3D² I and 2D
    covariance + 0.1 I, each with the opacity times sqrt(det before / det after)), "matched" (3D
    covariance + g² I with g = gvae_dilation_3D, 2D covariance + max(0, 0.3 - g² fx fy / z²) I,
    opacity as it is) or "auto" (mip with filter_3D, else matched with gvae_dilation_3D)."""
    filt, mip, dil = _modes(cloud, antialias)
    means = _np64(cloud.means)
    n = len(means)
    degree = cloud.sh_degree if sh_degree is None else min(sh_degree, cloud.sh_degree)
    rot, center = camera.rotation, camera.center
    rel = means - center
    p = rel @ rot.T
    valid = p[:, 2] > NEAR
    out = dict(mean2d=np.zeros((n, 2)), conic=np.zeros((n, 2, 2)), opacity=np.zeros(n),
               color=np.zeros((n, 3)), depth=p[:, 2].copy(), valid=valid)
    scales = np.exp(np.clip(_np64(cloud.scales), *LOG_SCALE_RANGE))
    quats = _np64(cloud.quats)
    opac = 1.0 / (1.0 + np.exp(-np.clip(_np64(cloud.opacities), *OPACITY_LOGIT_RANGE)))
    dc, rest = _np64(cloud.sh_dc), _np64(cloud.sh_rest)
    # the image widened by (FOV_CLAMP - 1) half-sizes on each side, as x/z and y/z
    mx, my = (FOV_CLAMP - 1) * camera.width / 2, (FOV_CLAMP - 1) * camera.height / 2
    lo_x, hi_x = -(camera.cx + mx) / camera.fx, (camera.width - camera.cx + mx) / camera.fx
    lo_y, hi_y = -(camera.cy + my) / camera.fy, (camera.height - camera.cy + my) / camera.fy
    # Written per Gaussian i as batched 3x3 / 2x3 matrix products (numpy, float64).
    i = np.flatnonzero(valid)
    x, y, z = p[i, 0], p[i, 1], p[i, 2]
    norm = np.linalg.norm(quats[i], axis=1, keepdims=True)
    q = np.where(norm > 1e-12, quats[i] / np.where(norm > 1e-12, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    w, qx, qy, qz = q.T
    r = np.stack([
        np.stack([1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)], -1),
        np.stack([2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)], -1),
        np.stack([2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)], -1)], 1)
    m = r * scales[i][:, None, :]  # R @ diag(s)
    cov3 = m @ m.transpose(0, 2, 1)
    weight = np.ones(len(i))
    if filt is not None:
        smoothed = cov3 + (filt[i] ** 2)[:, None, None] * np.eye(3)
        weight *= np.exp(0.5 * (np.linalg.slogdet(cov3)[1] - np.linalg.slogdet(smoothed)[1]))
        cov3 = smoothed
    if dil is not None:
        cov3 = cov3 + (dil[i] ** 2)[:, None, None] * np.eye(3)
    tx = np.clip(x / z, lo_x, hi_x) * z
    ty = np.clip(y / z, lo_y, hi_y) * z
    jac = np.zeros((len(i), 2, 3))
    jac[:, 0, 0] = camera.fx / z
    jac[:, 0, 2] = -camera.fx * tx / (z * z)
    jac[:, 1, 1] = camera.fy / z
    jac[:, 1, 2] = -camera.fy * ty / (z * z)
    t = jac @ rot
    cov2 = t @ cov3 @ t.transpose(0, 2, 1)
    if mip:
        det0 = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] * cov2[:, 1, 0]
        cov2 = cov2 + MIP_2D * np.eye(2)
        det1 = cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] * cov2[:, 1, 0]
        weight *= np.sqrt(np.maximum(det0, 0.0) / det1)
    elif dil is not None:
        left = np.maximum(DILATION - dil[i] ** 2 * camera.fx * camera.fy / (z * z), 0.0)  # of the 0.3 px²
        cov2 = cov2 + left[:, None, None] * np.eye(2)
    else:
        cov2 = cov2 + DILATION * np.eye(2)
    out["conic"][i] = np.linalg.inv(cov2)
    out["mean2d"][i] = np.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], 1)
    out["opacity"][i] = opac[i] * weight
    d = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-300)
    out["color"] = sh_color(dc, rest, d, degree)
    return out


def render_reference(cloud: GaussianCloud, camera: Camera, background=(0.0, 0.0, 0.0),
                     sh_degree: int | None = None, pixels: np.ndarray | None = None, antialias: str = "auto"):
    """Float64 image (H,W,3), alpha (H,W) and expected depth (H,W); or, with `pixels` (M,2) as
    (row, column) pairs, the (M,3), (M,), (M,) values at those pixels only. `antialias`: as for
    `project_reference`."""
    pr = project_reference(cloud, camera, sh_degree, antialias)
    bg = np.asarray(background, np.float64).reshape(3)
    idx = np.flatnonzero(pr["valid"])
    idx = idx[np.argsort(pr["depth"][idx], kind="stable")]  # front to back
    mean2d, conic, opac = pr["mean2d"][idx], pr["conic"][idx], pr["opacity"][idx]
    color, depth = pr["color"][idx], pr["depth"][idx]
    full = pixels is None
    if full:
        rows, cols = np.meshgrid(np.arange(camera.height), np.arange(camera.width), indexing="ij")
        pixels = np.stack([rows.ravel(), cols.ravel()], 1)
    pixels = np.asarray(pixels, np.int64).reshape(-1, 2)
    img = np.zeros((len(pixels), 3))
    alpha_out = np.zeros(len(pixels))
    depth_out = np.zeros(len(pixels))
    for k, (row, col) in enumerate(pixels):
        d = np.array([col + 0.5, row + 0.5]) - mean2d  # (n,2)
        power = -0.5 * np.einsum("ni,nij,nj->n", d, conic, d)
        alpha = np.minimum(ALPHA_MAX, opac * np.exp(power))
        c = np.zeros(3)
        dep = 0.0
        trans = 1.0
        for i in np.flatnonzero(alpha >= ALPHA_MIN):  # the others are skipped anyway
            test = trans * (1.0 - alpha[i])
            if test < T_MIN:
                break
            c += color[i] * alpha[i] * trans
            dep += depth[i] * alpha[i] * trans
            trans = test
        img[k] = c + trans * bg
        alpha_out[k] = 1.0 - trans
        depth_out[k] = dep / alpha_out[k] if alpha_out[k] > 1e-6 else 0.0
    if not full:
        return img, alpha_out, depth_out
    shape = (camera.height, camera.width)
    return img.reshape(shape + (3,)), alpha_out.reshape(shape), depth_out.reshape(shape)
