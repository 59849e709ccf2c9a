"""Codebooks for the palette formats (SOG): a 256-entry scalar codebook and k-means of vectors.

`codebook_1d` quantises a pool of scalars (the log-scales, or the colours, of every Gaussian) to
`k` sorted values: Lloyd's algorithm in one dimension, exact and cheap on sorted data (each
iteration is one search of the k - 1 decision boundaries and one prefix sum), started from a blend
of quantiles and an even spread over the range so that sparse tails keep centroids of their own.

`kmeans` clusters vectors (the SH rest coefficients of every Gaussian): Lloyd's algorithm from k
distinct points drawn with a seeded generator, nearest centroids found by matrix products in
blocks, empty clusters moved to the points farthest from their centroids. Large problems (n * k * d
beyond FLAT_LIMIT, about 8 s of Lloyd on the 2-core machine) are clustered in two levels:
k1 ~ sqrt(iterations * k) coarse clusters fitted on a sample, then each coarse cluster split into
leaves in proportion to its size; a point's leaf is the nearest one within its coarse cluster. That
makes 1M points of 45 values and 65536 centroids take tens of seconds instead of hours, for an
error a few percent above one-level Lloyd's. Same input and seed, same result.

`kmeans_reference` and `codebook_labels_reference` are the slow, obviously correct versions
(loops over points) that the tests hold the fast ones to.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["codebook_1d", "kmeans", "kmeans_reference", "nearest_in_codebook", "lloyd"]

#: Beyond n * k * d = FLAT_LIMIT (points, centroids, dimensions), `kmeans` clusters in two levels.
FLAT_LIMIT = 1 << 32
# Distances per block of the nearest-centroid search (a block stays in cache).
_BLOCK_VALUES = 1 << 18


# ---------------------------------------------------------------------------------- scalars

def nearest_in_codebook(values: np.ndarray, codebook: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of a sorted `codebook` for each value (the lower one on a tie),
    as uint8 when the codebook has at most 256 entries."""
    cb = np.asarray(codebook, np.float64)
    mid = (cb[:-1] + cb[1:]) * 0.5
    idx = np.searchsorted(mid, np.asarray(values, np.float64), side="left")
    idx = np.searchsorted(cb, cb[idx], side="left")  # the first of equal entries
    return idx.astype(np.uint8 if len(cb) <= 256 else np.int64)


def codebook_1d(values: np.ndarray, k: int = 256, *, iterations: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """(codebook, labels): `k` sorted float32 values (unused slots repeat the largest) and each
    value's nearest entry, for the finite float `values` (any shape; labels have its shape). At
    most k distinct float32 values are kept exactly."""
    flat = np.asarray(values, np.float64).reshape(-1)
    if flat.size == 0:
        return np.zeros(k, np.float32), np.zeros(np.shape(values), np.uint8)
    data = np.sort(flat)
    n = len(data)
    lo, hi = data[0], data[-1]
    data32 = data.astype(np.float32)  # still sorted
    distinct = data32[np.r_[True, data32[1:] != data32[:-1]]]
    if len(distinct) <= k:  # each value its own entry: exact
        book = np.concatenate([distinct, np.full(k - len(distinct), distinct[-1], np.float32)])
        return book, nearest_in_codebook(values, book).reshape(np.shape(values))
    # Start: half the centroids at quantiles (where the data are dense), half evenly over the range.
    q = data[np.minimum(((np.arange(k) + 0.5) / k * n).astype(np.int64), n - 1)]
    even = lo + (np.arange(k) + 0.5) / k * (hi - lo)
    centres = np.unique(np.concatenate([q[::2], even[1::2]]))
    prefix = np.concatenate([[0.0], np.cumsum(data)])
    for _ in range(iterations):
        cut = np.searchsorted(data, (centres[:-1] + centres[1:]) * 0.5, side="left")
        start = np.concatenate([[0], cut])
        stop = np.concatenate([cut, [n]])
        count = stop - start
        keep = count > 0
        new = (prefix[stop[keep]] - prefix[start[keep]]) / count[keep]
        if len(new) == len(centres) and np.array_equal(new, centres):
            break
        centres = np.unique(new)
    book = np.empty(k, np.float32)
    book[:len(centres)] = centres
    book[len(centres):] = np.float32(centres[-1])
    book = np.sort(book)
    return book, nearest_in_codebook(values, book).reshape(np.shape(values))


# ---------------------------------------------------------------------------------- vectors

def _nearest(points: np.ndarray, centroids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels, squared distances) of each point's nearest centroid (the first on a tie)."""
    n, k = len(points), len(centroids)
    labels = np.empty(n, np.int64)
    dist = np.empty(n, np.float64)
    c = np.ascontiguousarray(centroids, np.float32)
    c_sq = np.einsum("ij,ij->i", c, c)
    minus_2c = (-2.0 * c).T.copy()
    rows = max(64, _BLOCK_VALUES // max(1, k))
    buf = np.empty((min(rows, n), k), np.float32)
    for start in range(0, n, rows):
        x = points[start:start + rows]
        d = buf[:len(x)]
        np.matmul(x, minus_2c, out=d)
        d += c_sq
        lab = d.argmin(1)
        labels[start:start + len(x)] = lab
        dist[start:start + len(x)] = d[np.arange(len(x)), lab] + np.einsum("ij,ij->i", x, x)
    return labels, np.maximum(dist, 0.0)


def _means(points: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(sums (k, d) in float64, counts (k,)) of the points of each label."""
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    starts = np.flatnonzero(np.r_[True, sorted_labels[1:] != sorted_labels[:-1]])
    sums = np.zeros((k, points.shape[1]), np.float64)
    sums[sorted_labels[starts]] = np.add.reduceat(points[order].astype(np.float64), starts, axis=0)
    return sums, np.bincount(labels, minlength=k)


def lloyd(points: np.ndarray, centroids: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """`iterations` Lloyd steps from `centroids` (fewer when the labels stop changing, which is
    where more steps would change nothing): (centroids (k, d) float32, labels of the final
    centroids). An empty cluster moves to the point farthest from its centroid (the next farthest
    for the next empty one)."""
    points = np.ascontiguousarray(points, np.float32)
    c = np.array(centroids, np.float32)
    k = len(c)
    labels, dist = _nearest(points, c)
    for _ in range(iterations):
        sums, counts = _means(points, labels, k)
        full = counts > 0
        c[full] = (sums[full] / counts[full, None]).astype(np.float32)
        empty = np.flatnonzero(~full)
        if len(empty):
            far = np.argsort(-dist, kind="stable")[:len(empty)]
            c[empty[:len(far)]] = points[far]
        new, dist = _nearest(points, c)
        if np.array_equal(new, labels):  # a fixed point: more steps would change nothing
            break
        labels = new
    return c, labels


def _initial(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    return points[np.sort(rng.choice(len(points), size=k, replace=False))]


def kmeans(points: np.ndarray, k: int, *, iterations: int = 10, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(centroids (m, d) float32, labels (n,) int64) of `points` (n, d): k-means with m = min(k, n)
    clusters (every point its own centroid when n <= k), deterministic for a given `seed`."""
    points = np.ascontiguousarray(points, np.float32)
    return _kmeans(points, k, iterations, np.random.default_rng(seed), two_level=True)


def _kmeans(points: np.ndarray, k: int, iterations: int, rng: np.random.Generator, *, two_level: bool):
    n = len(points)
    if n <= k:
        return points.copy(), np.arange(n, dtype=np.int64)
    if not two_level or n * k * points.shape[1] <= FLAT_LIMIT:
        return lloyd(points, _initial(points, k, rng), iterations)
    # Two levels: k1 coarse clusters from a sample, then leaves inside each in proportion to its size.
    k1 = int(min(k, max(2, round(math.sqrt(iterations * k)))))
    sample = points[np.sort(rng.choice(n, size=min(n, 32 * k1), replace=False))]
    coarse, _ = lloyd(sample, _initial(sample, k1, rng), iterations)
    top, _ = _nearest(points, coarse)
    counts = np.bincount(top, minlength=k1)
    leaves = _apportion(counts, k)
    order = np.argsort(top, kind="stable")
    bounds = np.r_[0, np.cumsum(counts)]
    centroids, labels, used = [], np.empty(n, np.int64), 0
    for c in np.flatnonzero(counts):
        members = order[bounds[c]:bounds[c + 1]]
        sub, sub_labels = _kmeans(points[members], int(leaves[c]), iterations, rng, two_level=False)
        centroids.append(sub)
        labels[members] = sub_labels + used
        used += len(sub)
    return np.concatenate(centroids), labels


def _apportion(counts: np.ndarray, k: int) -> np.ndarray:
    """Integers in proportion to `counts` that sum to min(k, counts.sum()), at least 1 and at most
    the count for every non-zero count (largest remainders)."""
    counts = counts.astype(np.int64)
    nonzero = counts > 0
    total = min(k, int(counts.sum()))
    share = counts * (total / counts.sum())
    out = np.where(nonzero, np.maximum(1, np.floor(share)), 0).astype(np.int64)
    out = np.minimum(out, counts)
    while out.sum() < total:
        room = np.flatnonzero(out < counts)
        give = room[np.argsort(-(share[room] - out[room]), kind="stable")][:total - out.sum()]
        out[give] += 1
    while out.sum() > total:
        take = np.flatnonzero(out > 1)
        take = take[np.argsort(share[take] - out[take], kind="stable")][:out.sum() - total]
        out[take] -= 1
    return out


# ------------------------------------------------------------------------ slow references

def codebook_labels_reference(values, codebook) -> np.ndarray:
    """`nearest_in_codebook` by a loop: the first entry at the smallest distance to each value."""
    out = []
    for v in np.asarray(values, np.float64).reshape(-1):
        dists = [abs(float(v) - float(c)) for c in codebook]
        out.append(dists.index(min(dists)))
    return np.array(out, np.int64)


def kmeans_reference(points, centroids, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """`lloyd` by loops over points and centroids, in float64: nearest centroid (the first on a
    tie), means, empty clusters to the farthest points."""
    pts = [list(map(float, p)) for p in np.asarray(points)]
    cs = [list(map(float, c)) for c in np.asarray(centroids)]

    def assign():
        labels, dists = [], []
        for p in pts:
            d = [sum((a - b) ** 2 for a, b in zip(p, c)) for c in cs]
            best = d.index(min(d))
            labels.append(best)
            dists.append(d[best])
        return labels, dists

    labels, dists = assign()
    for _ in range(iterations):
        members = [[] for _ in cs]
        for p, lab in zip(pts, labels):
            members[lab].append(p)
        far = sorted(range(len(pts)), key=lambda i: -dists[i])
        empty = 0
        for j, m in enumerate(members):
            if m:
                cs[j] = [sum(col) / len(m) for col in zip(*m)]
            else:
                cs[j] = list(pts[far[empty]])
                empty += 1
        labels, dists = assign()
    return np.array(cs), np.array(labels)
