"""Assembling the compacted cloud: each group of input Gaussians becomes one (`merge_groups`), its
members' moments matched with mass weights; `merge_groups_reference` is the slow, obviously correct
definition (a loop over the groups) the tests hold it to. Where Numba is, the members' moments, the
groups' sums and their shapes are compiled kernels (`compiled`, in threads; the 3x3
eigen-decompositions `kernels.eigh3`, numpy's eigh up to each axis's sign); `merge_groups_numpy`
(all numpy) is their reference.
"""

from __future__ import annotations

import math

import numpy as np

from .. import quaternions
from ..antialias import DILATION_KEY, FILTER_KEY
from ..cloud import GaussianCloud
from ..conventions import LOG_SCALE_RANGE, activate_opacities
from . import compiled
from .moments import DIAG, floor_of, minors, moments, moments_numpy, outer, pack, unpack


def merge_groups(cloud: GaussianCloud, groups: np.ndarray) -> tuple[GaussianCloud, np.ndarray]:
    """The cloud with the Gaussians of each group (groups[i] = output row of input row i, -1:
    dropped; every output row 0..G-1 used) merged into one, and the input row each output row
    takes (its most massive member's). Single-member groups keep their values bit for bit; a
    merged one matches its members' moments with mass weights (mass = opacity x sqrt(sum of the
    2x2 principal minors of the covariance): the mean over directions of its projected area, up
    to a constant): centre, covariance, every SH coefficient, the anti-aliasing size
    (`filter_3D`, `gvae_dilation_3D`; mass-weighted in variance), and the opacity that keeps the
    total mass, capped by what the members draw together (1 - prod(1 - o)). By the compiled kernels
    where they run (`compiled.group_sums`), else `merge_groups_numpy`."""
    if not compiled.available():
        return merge_groups_numpy(cloud, groups)
    src = cloud.numpy()
    groups, multi, size, idx = _members(groups)
    m = moments(src, np.zeros(len(idx)), rows=idx)
    rows = np.zeros(len(size), np.int64)
    kept = np.flatnonzero(groups >= 0)
    rows[groups[kept]] = kept
    if len(multi):
        starts = np.concatenate([[0], np.cumsum(size[multi])[:-1]])
        opacity = activate_opacities(src.opacities.astype(np.float64))
        w, rows[multi], mass, mu, sigma, together, sh_dc, sh_rest = compiled.group_sums(
            starts, starts + size[multi], idx, m.mass, m.mu, m.sigma, opacity, src.sh_dc, src.sh_rest)
    out = src.select(rows)  # (a copy: selected by an index)
    if len(multi):
        out.means[multi] = mu + m.origin
        out.scales[multi], out.quats[multi], out.opacities[multi] = compiled.shapes(sigma, m.floor, mass, together)
        out.sh_dc[multi] = sh_dc
        if src.sh_rest.shape[1]:
            out.sh_rest[multi] = sh_rest
        grp = np.repeat(np.arange(len(multi)), size[multi])
        write_sizes(out, multi, {key: src.extra[key][idx] for key in (FILTER_KEY, DILATION_KEY) if key in src.extra},
                    grp, w)
    return out, rows


def _members(groups) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(groups as int64, the groups of more than one member, every group's size, the rows of
    those groups' members sorted by group: each group's members one segment)."""
    groups = np.asarray(groups, np.int64)
    g = int(groups.max(initial=-1)) + 1
    member = groups >= 0
    size = np.bincount(groups[member], minlength=g)
    multi = np.flatnonzero(size > 1)
    idx = np.flatnonzero(member & (size[np.maximum(groups, 0)] > 1))
    return groups, multi, size, idx[np.argsort(groups[idx], kind="stable")]


def merge_groups_numpy(cloud: GaussianCloud, groups: np.ndarray) -> tuple[GaussianCloud, np.ndarray]:
    """`merge_groups` in numpy (the reference of its compiled path)."""
    src = cloud.numpy()
    groups, multi, size, idx = _members(groups)
    members = src.select(idx)
    m = moments_numpy(members, np.zeros(len(idx)))
    rows = representatives(groups, idx, m.mass)
    out = src.select(rows).copy()
    if len(multi):
        grp = np.repeat(np.arange(len(multi)), size[multi])  # (idx is sorted by group)
        starts = np.concatenate([[0], np.cumsum(size[multi])[:-1]])
        mass = np.add.reduceat(m.mass, starts)
        w = m.mass / np.maximum(mass[grp], 1e-300)
        mu = np.add.reduceat(w[:, None] * m.mu, starts)
        sigma = np.add.reduceat(w[:, None] * (m.sigma + outer(m.mu - mu[grp])), starts)
        write_merged(out, multi, members, grp, starts, w, mu + m.origin, sigma, mass, m.floor)
    return out, rows


def representatives(groups: np.ndarray, idx: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """The input row each output row takes: its own, or the most massive of the rows `idx` (with
    `mass`) merged into it (ties: the lower row)."""
    g = int(groups.max(initial=-1)) + 1
    rows = np.zeros(g, np.int64)
    kept = np.flatnonzero(groups >= 0)
    rows[groups[kept]] = kept
    order = idx[np.lexsort((-idx, mass))]  # ascending mass: the heaviest written last
    rows[groups[order]] = order
    return rows


def write_merged(out: GaussianCloud, multi, members: GaussianCloud, grp, starts, w, mu, sigma, mass,
                 floor: float) -> None:
    """Write the merged Gaussians (their moments given; `floor` on the covariances' diagonal)
    into rows `multi` of `out`; `members`: the rows merged, sorted by their group `grp` (each
    group's first row at `starts`), mass weight `w`."""
    o = activate_opacities(members.opacities.astype(np.float64))
    together = -np.expm1(np.bincount(grp, np.log1p(-np.minimum(o, 1.0 - 1e-12)), len(multi)))
    write_shapes(out, multi, mu, sigma, mass, floor, together)
    w32 = w.astype(np.float32)  # (the SH sums in the cloud's precision: they are most of the work)
    out.sh_dc[multi] = np.add.reduceat(w32[:, None] * members.sh_dc, starts)
    if members.sh_rest.shape[1]:
        out.sh_rest[multi] = np.add.reduceat(w32[:, None, None] * members.sh_rest, starts)
    write_sizes(out, multi, members.extra, grp, w)


def write_shapes(out: GaussianCloud, multi, mu, sigma, mass, floor: float, together) -> None:
    """Write the merged Gaussians' centres `mu`, shapes (from their covariances `sigma`, less
    `floor` on the diagonal) and opacities (the mass kept, at most what the members draw
    `together`) into rows `multi` of `out` (numpy: the reference of `compiled.shapes`)."""
    vals, vecs = np.linalg.eigh(unpack(sigma))
    vecs[np.linalg.det(vecs) < 0, :, 0] *= -1.0  # a rotation, not a reflection
    log_scale = np.clip(0.5 * np.log(np.maximum(vals - floor, 1e-300)), *LOG_SCALE_RANGE)
    scaled = vecs * np.exp(log_scale)[:, None, :]
    stored = pack(scaled @ scaled.transpose(0, 2, 1))  # as stored (scales clamped)
    stored[:, DIAG] += floor
    opacity = mass / np.maximum(np.sqrt(np.maximum(minors(stored), 0.0)), 1e-300)
    opacity = np.clip(np.minimum(opacity, together), 1e-6, 1.0 - 1e-6)
    out.means[multi] = mu
    out.scales[multi] = log_scale
    out.quats[multi] = quaternions.from_rotmat(vecs)
    out.opacities[multi] = np.log(opacity / (1.0 - opacity))


def write_sizes(out: GaussianCloud, multi, extra: dict, grp, w) -> None:
    """The merged Gaussians' anti-aliasing sizes (`filter_3D`, `gvae_dilation_3D`): mass-weighted
    (`w`) in variance over their members (`extra`: the members' values, by group `grp`)."""
    for key in (FILTER_KEY, DILATION_KEY):
        if key in out.extra and np.asarray(out.extra[key]).ndim == 1:
            v = np.square(np.asarray(extra[key], np.float64))
            out.extra[key][multi] = np.sqrt(np.bincount(grp, w * v, len(multi)))


def merge_groups_reference(cloud: GaussianCloud, groups: np.ndarray) -> GaussianCloud:
    """Slow definition of `merge_groups` (one group at a time, plain formulas)."""
    src = cloud.numpy()
    groups = np.asarray(groups, np.int64)
    center, half = src.normalization()
    floor = floor_of(half) * np.eye(3)
    area2 = lambda s: sum(np.linalg.det(s[np.ix_(p, p)]) for p in ([0, 1], [0, 2], [1, 2]))  # noqa: E731
    parts = []
    for j in range(int(groups.max(initial=-1)) + 1):
        idx = np.flatnonzero(groups == j)
        if len(idx) == 1:
            parts.append(src.select(idx))
            continue
        mass, mus, sigmas, ops = [], [], [], []
        for i in idx:
            rot = quaternions.to_rotmat(quaternions.normalize(src.quats[i].astype(np.float64)))
            s = rot @ np.diag(np.exp(2 * np.clip(src.scales[i].astype(np.float64), *LOG_SCALE_RANGE))) @ rot.T
            o = float(activate_opacities(np.float64(src.opacities[i])))
            mass.append(o * math.sqrt(area2(s + floor)))
            mus.append(src.means[i].astype(np.float64) - center)
            sigmas.append(s + floor)
            ops.append(o)
        mass = np.array(mass)
        w = mass / mass.sum()
        mu = sum(wi * x for wi, x in zip(w, mus))
        second = sum(wi * (s + np.outer(x - mu, x - mu)) for wi, s, x in zip(w, sigmas, mus))
        vals, vecs = np.linalg.eigh(second - floor)
        if np.linalg.det(vecs) < 0:
            vecs[:, 0] *= -1
        ls = np.clip(0.5 * np.log(np.maximum(vals, 1e-300)), *LOG_SCALE_RANGE)
        s = vecs @ np.diag(np.exp(2 * ls)) @ vecs.T
        o = min(mass.sum() / math.sqrt(area2(s + floor)), 1.0 - np.prod([1.0 - min(x, 1.0 - 1e-12) for x in ops]))
        o = min(max(o, 1e-6), 1.0 - 1e-6)
        one = src.select([idx[np.lexsort((-idx, mass))[-1]]]).copy()
        one.means[0] = mu + center
        one.scales[0] = ls
        one.quats[0] = quaternions.from_rotmat(vecs)
        one.opacities[0] = math.log(o / (1 - o))
        one.sh_dc[0] = sum(wi * src.sh_dc[i] for wi, i in zip(w, idx))
        one.sh_rest[0] = sum(wi * src.sh_rest[i] for wi, i in zip(w, idx))
        for key in (FILTER_KEY, DILATION_KEY):
            if key in one.extra:
                one.extra[key][0] = math.sqrt(sum(wi * float(src.extra[key][i]) ** 2 for wi, i in zip(w, idx)))
        parts.append(one)
    return GaussianCloud.concat(parts) if parts else GaussianCloud.empty(src.sh_degree)


def ordered(groups: np.ndarray, rows: np.ndarray, cloud: GaussianCloud) -> tuple:
    """Output rows sorted by their representative's input row (the input's order kept)."""
    order = np.argsort(rows, kind="stable")
    if np.array_equal(order, np.arange(len(rows))):
        return groups, rows, cloud
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    return np.where(groups >= 0, inverse[np.maximum(groups, 0)], -1), rows[order], cloud.select(order)
