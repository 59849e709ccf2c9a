"""What merging needs of each Gaussian, and what merging a pair costs (float64 numpy).

A Gaussian's mass is its opacity times sqrt of the sum of its covariance's 2x2 principal minors
(the mean over directions of its projected area, up to a constant); a merge matches the members'
moments with mass weights. Covariances are packed symmetric 3x3 matrices (xx, xy, xz, yy, yz, zz)
with `floor` of variance on the diagonal, far below what a picture shows, so that flat Gaussians
have a finite log det.

`moments`, `pair_cost` and `merge_pairs` run as compiled kernels where Numba is (`compiled`); the
numpy code (`moments_numpy`, `pair_cost_numpy`, `merge_pairs_numpy`) is their reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import quaternions
from ..cloud import GaussianCloud, normalization_of
from ..conventions import LOG_SCALE_RANGE, SH_C0, activate_opacities
from . import compiled

#: Weight of the colour difference (RGB of the SH DC term, squared) against the shape change
#: (nats of KL divergence) in the merge cost.
COLOUR_WEIGHT = 10.0
#: Packed (6) index of each entry of a symmetric 3x3 matrix, and of the diagonal.
SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
DIAG = np.array([0, 3, 5])


@dataclass
class Moments:
    """Per Gaussian (float64): mass m, centre mu (relative to `origin`), covariance sigma (packed,
    `floor` on its diagonal), its log det, the DC colour and the merge weight; the weight of the
    colour difference in a pair's cost (`pair_cost`)."""

    mass: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    log_det: np.ndarray
    floor: float
    colour: np.ndarray
    weight: np.ndarray
    origin: np.ndarray
    colour_weight: float = COLOUR_WEIGHT


def unpack(s: np.ndarray) -> np.ndarray:
    return s[:, SYM]


def pack(full: np.ndarray) -> np.ndarray:
    """(N,6) packed upper triangles of (N,3,3) symmetric matrices."""
    return full.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]


def outer(d: np.ndarray) -> np.ndarray:
    """Packed d dᵀ of (N,3) vectors."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack([x * x, x * y, x * z, y * y, y * z, z * z], 1)


def det(s: np.ndarray) -> np.ndarray:
    """det of packed symmetric 3x3 matrices."""
    xx, xy, xz, yy, yz, zz = s.T
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def minors(s: np.ndarray) -> np.ndarray:
    """The sum of the 2x2 principal minors of packed symmetric 3x3 matrices: 3 x the mean over
    directions of the determinant of the projection along them (projected area squared)."""
    xx, xy, xz, yy, yz, zz = s.T
    return xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz


def log_det(s: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(det(s), 1e-300))


def covariances(src: GaussianCloud) -> np.ndarray:
    """Packed covariances R diag(exp(2 log-scale)) Rᵀ (float64)."""
    rot = quaternions.to_rotmat(quaternions.normalize(src.quats.astype(np.float64)))
    scaled = rot * np.exp(np.clip(src.scales.astype(np.float64), *LOG_SCALE_RANGE))[:, None, :]
    return pack(scaled @ scaled.transpose(0, 2, 1))


def floor_of(half: float) -> float:
    """The variance added to every covariance's diagonal: (1/4000 of the scene's size)², far below
    a pixel of any view of it."""
    return (2.5e-4 * half) ** 2


def moments(src: GaussianCloud, weight: np.ndarray, rows: np.ndarray | None = None,
            colour_weight: float = COLOUR_WEIGHT) -> Moments:
    """The stored Gaussians as they are (their anti-aliasing filter left out: with it, and
    Mip-Splatting's opacity compensation, the merges drew worse). `rows`: of these rows only (as of
    `src.select(rows)`, without copying the rest of their fields). `colour_weight`: of the merge cost
    (`pair_cost`). By `compiled.gaussian_moments` where it runs, else `moments_numpy`."""
    src = src.numpy()
    if not compiled.available():
        return moments_numpy(src if rows is None else src.select(rows), weight, colour_weight)
    rows = np.arange(len(src)) if rows is None else np.asarray(rows, np.int64)
    center, half = normalization_of(src.means[rows])
    floor = floor_of(half)
    opacity = activate_opacities(src.opacities.astype(np.float64))
    mu, sigma, mass, ld = compiled.gaussian_moments(rows, src.means, src.scales, src.quats, opacity, center, floor)
    return Moments(mass=mass, mu=mu, sigma=sigma, log_det=ld, floor=floor,
                   colour=SH_C0 * src.sh_dc[rows].astype(np.float64), weight=np.array(weight, np.float64),
                   origin=center, colour_weight=float(colour_weight))


def moments_numpy(src: GaussianCloud, weight: np.ndarray, colour_weight: float = COLOUR_WEIGHT) -> Moments:
    """`moments` in numpy (float64): the reference of the compiled path."""
    center, half = src.normalization()
    floor = floor_of(half)
    sigma = covariances(src)
    sigma[:, DIAG] += floor
    mass = activate_opacities(src.opacities.astype(np.float64)) * np.sqrt(np.maximum(minors(sigma), 0.0))
    return Moments(mass=mass, mu=src.means.astype(np.float64) - center, sigma=sigma, log_det=log_det(sigma),
                   floor=floor, colour=SH_C0 * src.sh_dc.astype(np.float64), weight=np.asarray(weight, np.float64),
                   origin=center, colour_weight=float(colour_weight))


def pair(m: Moments, a: np.ndarray, b: np.ndarray):
    """Mass weights of a and b in each pair, the pair's total mass and its moment-matched covariance."""
    ma, mb = m.mass[a], m.mass[b]
    total = np.maximum(ma + mb, 1e-300)
    wa = ma / total
    wb = 1.0 - wa
    s = wa[:, None] * m.sigma[a] + wb[:, None] * m.sigma[b] + (wa * wb)[:, None] * outer(m.mu[a] - m.mu[b])
    return wa, wb, total, s


def pair_cost(m: Moments, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`pair_cost_numpy` by `compiled.pair_costs` where it runs."""
    if compiled.available():
        return compiled.pair_costs(m, a, b, m.colour_weight)
    return pair_cost_numpy(m, a, b)


def pair_cost_numpy(m: Moments, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cost of merging each pair (a[i], b[i]): (weight_a + weight_b) x (mass_a + mass_b) x (the
    mass-weighted KL divergence of the two from their moment match, 1/2 (log det S - w_a log det
    S_a - w_b log det S_b), plus `m.colour_weight` x w_a w_b |colour_a - colour_b|²)."""
    wa, wb, total, s = pair(m, a, b)
    shape = 0.5 * (log_det(s) - wa * m.log_det[a] - wb * m.log_det[b])
    colour = wa * wb * np.square(m.colour[a] - m.colour[b]).sum(1)
    return (m.weight[a] + m.weight[b]) * total * (np.maximum(shape, 0.0) + m.colour_weight * colour)


def merge_pairs(m: Moments, a: np.ndarray, b: np.ndarray) -> None:
    """`merge_pairs_numpy` by `compiled.merge_pairs` where it runs."""
    if compiled.available():
        compiled.merge_pairs(m, a, b)
    else:
        merge_pairs_numpy(m, a, b)


def merge_pairs_numpy(m: Moments, a: np.ndarray, b: np.ndarray) -> None:
    """Merge each b[i] into a[i] in place (moments and weights add; b's entries are left stale)."""
    wa, wb, total, s = pair(m, a, b)
    m.sigma[a] = s
    m.log_det[a] = log_det(s)
    m.mu[a] = wa[:, None] * m.mu[a] + wb[:, None] * m.mu[b]
    m.colour[a] = wa[:, None] * m.colour[a] + wb[:, None] * m.colour[b]
    m.mass[a] = total
    m.weight[a] = m.weight[a] + m.weight[b]
