"""Compaction's compiled CPU path: the kernels of `compaction.kernels` (Numba) driven in threads.

As the renderer's `rendering.compiled` does it: the work is cut into chunks (of tiles, Gaussians,
edges, groups) run in `parallel.count()` threads (the kernels release the GIL; nothing
global is set). Where Numba is missing (`rendering.compiled.numba_missing`) `available()` is False
and the numpy / torch references run instead. Each function here says which reference it stands
for; the tests hold them to it.
"""

from __future__ import annotations

import importlib

import numpy as np

from ..conventions import LOG_SCALE_RANGE
from ..parallel import chunks, count, run, split
from ..rendering.compiled import numba_missing

#: Items (tile pairs, Gaussians, edges, groups) below which work is not split into threads.
SMALL = 1 << 14


def available() -> bool:
    """Whether the kernels can run here (Numba installed and importable)."""
    return numba_missing() is None


def kernels():
    """The `kernels` module (imports Numba on first use)."""
    return importlib.import_module(".kernels", __package__)


# ------------------------------------------------------------------------------ pixel hits

def table_hits(table: np.ndarray, ids: np.ndarray, offsets: np.ndarray, tiles_x: int, tile_size: int, width: int,
               height: int, wanted: np.ndarray | None = None) -> np.ndarray:
    """(R+1,) int64 hits of each row of a packed float32 table (R+1, 11) over the tile lists `ids`,
    `offsets` (`scoring._table_hits`, the torch sweep, by `kernels.tile_hits`); `wanted` (R+1,) bool:
    only the tiles that list a wanted row are swept (None: all)."""
    k = kernels()
    table = np.ascontiguousarray(table, np.float32)
    hits = np.zeros(table.shape[0], np.int64)
    if len(ids) == 0:
        return hits
    counts = np.diff(offsets)
    pair_hits = np.zeros(len(ids), np.int32)
    want = np.zeros(0, np.bool_) if wanted is None else np.ascontiguousarray(wanted, np.bool_)
    parts = 1 if len(ids) * tile_size ** 2 < SMALL or count() == 1 else 8 * count()
    run([lambda a=a, b=b: k.tile_hits(table, ids, offsets, a, b, tiles_x, tile_size, width, height, want, pair_hits)
         for a, b in split(counts + 1.0, parts)])
    k.add_pair_hits(pair_hits, ids, hits)
    hits[-1] = 0
    return hits


# ------------------------------------------------------------------------------ moments

def gaussian_moments(rows: np.ndarray, means, log_scales, quats, opacity: np.ndarray, center: np.ndarray,
                     floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mu (M,3), sigma (M,6), mass (M,), log_det (M,)) float64 of the Gaussians `rows` of the given
    fields (`opacity` activated, float64; `moments.moments` by `kernels.gaussian_moments`)."""
    k = kernels()
    rows = np.ascontiguousarray(rows, np.int64)
    m = len(rows)
    mu, sigma = np.empty((m, 3)), np.empty((m, 6))
    mass, log_det = np.empty(m), np.empty(m)
    args = (np.ascontiguousarray(means), np.ascontiguousarray(log_scales), np.ascontiguousarray(quats),
            np.ascontiguousarray(opacity, np.float64), np.ascontiguousarray(center, np.float64), float(floor),
            float(LOG_SCALE_RANGE[0]), float(LOG_SCALE_RANGE[1]))
    run([lambda a=a, b=b: k.gaussian_moments(rows, *args, a, b, mu, sigma, mass, log_det)
         for a, b in chunks(m, m, SMALL)])
    return mu, sigma, mass, log_det


def pair_costs(m, a: np.ndarray, b: np.ndarray, colour_weight: float) -> np.ndarray:
    """`moments.pair_cost` of the edges (a, b) of the `moments.Moments` m, by `kernels.pair_costs`."""
    k = kernels()
    a, b = np.ascontiguousarray(a, np.int64), np.ascontiguousarray(b, np.int64)
    out = np.empty(len(a))
    run([lambda lo=lo, hi=hi: k.pair_costs(m.mass, m.mu, m.sigma, m.log_det, m.colour, m.weight, a, b,
                                           float(colour_weight), lo, hi, out)
         for lo, hi in chunks(len(a), len(a), SMALL)])
    return out


def merge_pairs(m, a: np.ndarray, b: np.ndarray) -> None:
    """`moments.merge_pairs` (disjoint pairs, in place) by `kernels.merge_pairs`."""
    kernels().merge_pairs(m.mass, m.mu, m.sigma, m.log_det, m.colour, m.weight, np.ascontiguousarray(a, np.int64),
                          np.ascontiguousarray(b, np.int64))


def matching(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n: int, limit: int, rounds: int = 4) -> np.ndarray:
    """`graph.matching` (the same edges, cheapest first) by `kernels.greedy_matching`: the rounds
    compare (cost, index) pairs instead of ranking every edge by a sort."""
    chosen = np.zeros(len(a), np.bool_)
    kernels().greedy_matching(np.ascontiguousarray(a, np.int64), np.ascontiguousarray(b, np.int64),
                              np.ascontiguousarray(cost, np.float64), int(n), int(limit), int(rounds), chosen)
    picked = np.flatnonzero(chosen)
    return picked[np.argsort(cost[picked], kind="stable")][:max(int(limit), 0)]


# ------------------------------------------------------------------------------ merged groups

def group_sums(starts: np.ndarray, ends: np.ndarray, rows: np.ndarray, mass, mu, sigma, opacity, sh_dc, sh_rest):
    """(w, heaviest, mass, mu, sigma, together, sh_dc, sh_rest) of each group of members
    (consecutive, starts..ends, in ascending rows; member i is the cloud's row rows[i], of activated
    `opacity` and SH; `merge.merge_groups`' reductions and representatives by `kernels.group_sums`)."""
    k = kernels()
    g, m = len(starts), len(mass)
    w, heaviest = np.empty(m), np.empty(g, np.int64)
    out = (np.empty(g), np.empty((g, 3)), np.empty((g, 6)), np.empty(g), np.empty((g, 3), np.float32),
           np.empty((g,) + sh_rest.shape[1:], np.float32))
    args = (np.ascontiguousarray(starts, np.int64), np.ascontiguousarray(ends, np.int64),
            np.ascontiguousarray(rows, np.int64), mass, mu, sigma,
            np.ascontiguousarray(opacity, np.float64), np.ascontiguousarray(sh_dc, np.float32),
            np.ascontiguousarray(sh_rest, np.float32))
    run([lambda a=a, b=b: k.group_sums(*args, a, b, w, heaviest, *out) for a, b in chunks(g, g, SMALL)])
    return (w, heaviest, *out)


def unique_edges(nb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a, b): the edges a < b, each once, in ascending order, between each row i of the
    neighbour table nb (M, k+1) and nb[i, 1:] (`graph.knn_edges`' np.unique, by `kernels.unique_edges`)."""
    nb = np.ascontiguousarray(nb, np.int64)
    a = np.empty(nb.shape[0] * max(nb.shape[1] - 1, 0), np.int64)
    b = np.empty_like(a)
    count = kernels().unique_edges(nb, a, b)
    return a[:count], b[:count]


def shapes(sigma: np.ndarray, floor: float, mass: np.ndarray, together: np.ndarray):
    """(log-scales (G,3), quaternions (G,4), opacity logits (G,)) of merged Gaussians of packed
    covariances `sigma` (`merge.write_shapes`): `kernels.eigh3` (numpy's eigh's eigenvalues and
    axes, each axis up to its sign: the same Gaussians as the reference's), then `kernels.shapes`,
    chunk by chunk in threads."""
    k = kernels()
    g = len(sigma)
    log_scale, quats, logits = np.empty((g, 3)), np.empty((g, 4)), np.empty(g)
    mass, together = np.ascontiguousarray(mass, np.float64), np.ascontiguousarray(together, np.float64)
    sigma = np.ascontiguousarray(sigma, np.float64)

    def part(lo: int, hi: int) -> None:
        vals, vecs = np.empty((hi - lo, 3)), np.empty((hi - lo, 3, 3))
        k.eigh3(sigma[lo:hi], 0, hi - lo, vals, vecs)
        k.shapes(vals, vecs, float(floor), mass[lo:hi], together[lo:hi],
                 float(LOG_SCALE_RANGE[0]), float(LOG_SCALE_RANGE[1]), 0, hi - lo, log_scale[lo:hi], quats[lo:hi],
                 logits[lo:hi])

    run([lambda a=a, b=b: part(a, b) for a, b in chunks(g, g, SMALL)])
    return log_scale, quats, logits


#: Points per occupied cell that `nearest` aims at, and the most one cell may hold before the
#: grid is given up for the k-d tree (clouds of many coincident or far scattered Gaussians).
CELL_POINTS, CELL_LIMIT = 6.0, 256
#: The most points whose cells cannot tell that `nearest` sweeps every point for
#: (`kernels.brute_neighbours`); more go to scipy's k-d tree (building one over 1M points takes
#: about 0.5 s, a sweep of 1M points about 2 ms a point).
SWEEP_LIMIT = 128


def nearest(points: np.ndarray, k: int, sweep_limit: int = SWEEP_LIMIT) -> np.ndarray | None:
    """(M, k) int64: each point's k nearest others (exact, squared distances in float64; nearest
    first), by a grid of cells: the points of each cell compared with those of the 3 x 3 x 3
    cells around it (`kernels.cell_neighbours`, cells in threads); a point whose k-th nearest
    could lie beyond those cells is found by a sweep over every point (`kernels.brute_neighbours`)
    where there are at most `sweep_limit` such points, else asked of scipy's k-d tree. The same
    neighbours as the k-d tree's but among points at exactly equal distances. None where the points
    do not suit a grid (a cell would hold more than CELL_LIMIT): the caller asks the k-d tree."""
    kern = kernels()
    points = np.ascontiguousarray(points, np.float64)
    m = len(points)
    origin = points.min(0)
    extent = points.max(0) - origin
    low, high = np.percentile(points, [1, 99], axis=0)
    box = np.maximum(high - low, 1e-12 * max(float(extent.max()), 1e-300))
    h = max(float(np.cbrt(np.prod(box) / m * CELL_POINTS)), float(extent.max()) / ((1 << 20) - 2), 1e-300)
    for _ in range(3):  # (surfaces fill few cells: scale the cells to their occupancy)
        ix = np.minimum(((points - origin) / h).astype(np.int64), (1 << 21) - 1)
        key = (ix[:, 0] << 42) | (ix[:, 1] << 21) | ix[:, 2]
        perm = np.argsort(key, kind="stable")
        sk = key[perm]
        first = np.flatnonzero(np.concatenate([[True], sk[1:] != sk[:-1]]))
        occupancy = m / len(first)
        if 0.5 * CELL_POINTS <= occupancy <= 2.0 * CELL_POINTS:
            break
        h = max(h * (CELL_POINTS / occupancy) ** 0.5, float(extent.max()) / ((1 << 20) - 2), 1e-300)
    starts = np.append(first, m)
    if np.diff(starts).max() > CELL_LIMIT:
        return None
    keys = sk[first]
    slots = np.empty(1 << int(2 * len(keys) - 1).bit_length(), np.int64)
    kern.cell_table(keys, slots)
    cell_ix = np.ascontiguousarray(ix[perm[first]])
    dims = ix.max(0) + 1
    nb = np.empty((m, k), np.int64)
    certain = np.zeros(m, np.bool_)
    ordered = np.ascontiguousarray(points[perm])  # (each cell's points together: read in order)
    run([lambda a=a, b=b: kern.cell_neighbours(ordered, perm, cell_ix, keys, starts, slots, origin, float(h), dims, k,
                                               a, b, nb, certain)
         for a, b in split(np.diff(starts).astype(np.float64) ** 2 + 1.0, 1 if m < SMALL else 8 * count())])
    doubt = np.flatnonzero(~certain)
    if 0 < len(doubt) <= sweep_limit:
        run([lambda a=a, b=b: kern.brute_neighbours(points, doubt, k, a, b, nb)
             for a, b in chunks(len(doubt), len(doubt) * m, SMALL)])
    elif len(doubt):
        from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import; only merging needs it

        _, near = cKDTree(points).query(points[doubt], k + 1, workers=-1)
        near = np.take_along_axis(near, np.argsort(near == doubt[:, None], axis=1, kind="stable"), 1)
        nb[doubt] = near[:, :k]
    return nb
