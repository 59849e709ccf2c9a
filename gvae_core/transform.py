"""Moving a whole cloud by an affine map, SH included: the frame changes between file formats and the
node transforms of a glTF scene.

A map x -> A x + t moves each Gaussian's centre, turns its covariance R S² Rᵀ into A R S² Rᵀ Aᵀ and
its view-dependent colour f(d) into f(Q⁻¹ d), Q the rotation part of A (A = Q P, P symmetric
positive). When A is Q times a uniform scale k the quaternion becomes q_Q q and the log-scales
grow by ln k; otherwise each covariance is eigen-decomposed (scales from the eigenvalues, the
rotation from the eigenvectors). Each SH band l is rotated by a (2l+1)² matrix found by fitting the
basis of `conventions` at fixed directions (exact to float64 rounding; entries within 1e-12 of
-1, 0 or 1 are those values, so a change of axes that only flips signs gives exact sign flips).

`flip_axes` is the exact special case of a rotation by 180 degrees about an axis (two axes change
sign): positions, quaternions and SH coefficients only change sign, so it is its own inverse bit for
bit. It is the frame change between a 3DGS PLY (x right, y down, z forward) and glTF (x left, y up,
z forward).
"""

from __future__ import annotations

import math

import numpy as np

from . import quaternions
from .cloud import GaussianCloud
from .conventions import LOG_SCALE_RANGE, SH_C1, SH_C2, SH_C3, SH_REST_COUNTS

__all__ = ["sh_basis", "sh_rotation", "rotate_sh", "flip_axes", "affine"]

# Fixed directions at which the basis is fitted: a Fibonacci sphere, well spread, deterministic.
_FIT_POINTS = 64


def _fit_directions() -> np.ndarray:
    i = np.arange(_FIT_POINTS) + 0.5
    z = 1.0 - 2.0 * i / _FIT_POINTS
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(M, K) values of the K = (degree+1)² - 1 SH rest basis functions (bands 1..degree, the order
    of `sh_rest`) at the (M, 3) unit directions, float64 (numpy: the renderer's is torch)."""
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = []
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        cols += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * z * z - x * x - y * y), SH_C2[3] * x * z,
                 SH_C2[4] * (x * x - y * y)]
    if degree >= 3:
        cols += [SH_C3[0] * y * (3 * x * x - y * y), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * z * z - x * x - y * y),
                 SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), SH_C3[4] * x * (4 * z * z - x * x - y * y),
                 SH_C3[5] * z * (x * x - y * y), SH_C3[6] * x * (x * x - 3 * y * y)]
    return np.stack(cols, 1) if cols else np.zeros((len(d), 0))


def _orthogonal(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, np.float64).reshape(3, 3)
    if not np.allclose(q @ q.T, np.eye(3), atol=1e-9):
        raise ValueError(f"not an orthogonal matrix: {np.round(q, 6).tolist()}")
    return q


def sh_rotation(q, degree: int) -> np.ndarray:
    """The (K, K) block-diagonal matrix T with sh_rest' = T sh_rest (per colour channel) for a cloud
    turned by the orthogonal 3x3 matrix `q`: the colour seen along q d afterwards is the colour seen
    along d before. A mirror (det -1) is allowed."""
    q = _orthogonal(q)
    k = SH_REST_COUNTS[degree]
    dirs = _fit_directions()
    before, after = sh_basis(dirs, degree), sh_basis(dirs @ q, degree)  # after[i] = basis(qᵀ d_i)
    out = np.zeros((k, k))
    for band in range(1, degree + 1):
        lo, hi = band * band - 1, (band + 1) ** 2 - 1
        out[lo:hi, lo:hi] = np.linalg.lstsq(before[:, lo:hi], after[:, lo:hi], rcond=None)[0]
    snapped = np.rint(out)
    near = (np.abs(out - snapped) < 1e-12) & (np.abs(snapped) <= 1)
    return np.where(near, snapped, out)


def rotate_sh(sh_rest: np.ndarray, q) -> np.ndarray:
    """(N, K, 3) SH rest coefficients of a cloud turned by the orthogonal matrix `q`, float32."""
    sh = np.asarray(sh_rest)
    k = sh.shape[1]
    if k == 0:
        return np.asarray(sh, np.float32).copy()
    t = sh_rotation(q, {v: d for d, v in SH_REST_COUNTS.items()}[k])
    if np.all((t == 0) | (np.abs(t) == 1)) and np.all(np.abs(t).sum(1) == 1):  # signed permutation: exact
        order, sign = np.abs(t).argmax(1), t[np.arange(k), np.abs(t).argmax(1)]
        return (sh[:, order] * sign.astype(np.float32)[None, :, None]).astype(np.float32)
    return np.einsum("ij,njc->nic", t, sh.astype(np.float64)).astype(np.float32)


def flip_axes(cloud: GaussianCloud, signs) -> GaussianCloud:
    """The cloud turned 180 degrees about one axis: `signs` (3 of +-1, two of them -1, or all +1)
    multiply the coordinates. Exact (only signs change) and its own inverse; the quaternion's
    vector part flips with the axes (q -> d q d for the rotation d), which keeps every Gaussian's
    ellipsoid: its local axes only change sign. Extras are kept as they are."""
    s = np.asarray(signs, np.float64)
    if s.shape != (3,) or not np.all(np.abs(s) == 1) or np.prod(s) != 1:
        raise ValueError(f"flip_axes: signs must be three of +-1 with product +1, not {list(signs)}")
    c = cloud.numpy()
    s32 = s.astype(np.float32)
    return c.replace(means=c.means * s32, quats=c.quats * np.concatenate([[1.0], s]).astype(np.float32),
                     sh_rest=rotate_sh(c.sh_rest, np.diag(s)))


def affine(cloud: GaussianCloud, matrix) -> GaussianCloud:
    """The cloud moved by the 4x4 affine `matrix` (any invertible linear part: rotation, scale per
    axis, mirror): centres, covariances (as rotation and log-scales) and SH coefficients; the result
    in float32. Extras are kept as they are. ValueError for a singular or non-finite matrix."""
    m = np.asarray(matrix, np.float64).reshape(4, 4)
    a = m[:3, :3]
    if not np.isfinite(m).all() or abs(np.linalg.det(a)) < 1e-300:
        raise ValueError("the transform is singular or not finite")
    u, sv, vt = np.linalg.svd(a)
    rot = u @ vt  # the rotation part (orthogonal; a mirror when det(a) < 0)
    c = cloud.numpy()
    means = (np.asarray(c.means, np.float64) @ a.T + m[:3, 3]).astype(np.float32)
    sh_rest = rotate_sh(c.sh_rest, rot)
    if sv.max() - sv.min() <= 1e-9 * sv.max() and np.linalg.det(rot) > 0:
        quats = quaternions.multiply(quaternions.from_rotmat(rot)[None],
                                     quaternions.normalize(np.asarray(c.quats, np.float64)))
        scales = np.asarray(c.scales, np.float64) + math.log(sv[0])
    else:
        r = quaternions.to_rotmat(quaternions.normalize(np.asarray(c.quats, np.float64)))
        var = np.exp(2.0 * np.clip(np.asarray(c.scales, np.float64), *LOG_SCALE_RANGE))
        ar = a @ r  # (N, 3, 3): the Gaussian's axes carried by the map
        cov = np.einsum("nij,nj,nkj->nik", ar, var, ar)
        evals, evecs = np.linalg.eigh(cov)
        evecs[:, :, 2] *= np.sign(np.linalg.det(evecs))[:, None]  # a rotation, not a mirror
        quats = quaternions.from_rotmat(evecs)
        scales = 0.5 * np.log(np.maximum(evals, np.exp(2.0 * LOG_SCALE_RANGE[0])))
    return c.replace(means=means, quats=quats.astype(np.float32), scales=scales.astype(np.float32),
                     sh_rest=sh_rest)
