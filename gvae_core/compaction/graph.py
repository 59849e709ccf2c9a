"""The neighbour graph merging runs on: each Gaussian's k nearest others (by centre), and the
passes that merge pairs over it, cheapest first, each pass taking disjoint pairs (the edges that are
the cheapest of both their ends: what greedy matching takes, found in parallel), until the count
is reached. The matching runs as a compiled kernel where Numba is (`compiled.matching`; its
reference: `matching_numpy`), as do the costs and the merges (`moments`).
"""

from __future__ import annotations

import numpy as np

from . import compiled
from .moments import Moments, merge_pairs, pair_cost

#: Neighbours per Gaussian in the merge graph (more gain nothing and cost time).
NEIGHBOURS = 4


def matching(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n: int, limit: int, rounds: int = 4) -> np.ndarray:
    """Edges (indices) of a matching: repeatedly every edge that is the cheapest of both its ends
    among the edges whose ends are both free (what greedy matching takes, found in parallel), for
    a few rounds or until `limit` edges; the `limit` cheapest of them, cheapest first (ties: the
    lower index). `compiled.matching` where it runs, else `matching_numpy`."""
    if compiled.available():
        return compiled.matching(a, b, cost, n, limit, rounds)
    return matching_numpy(a, b, cost, n, limit, rounds)


def matching_numpy(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n: int, limit: int, rounds: int = 4) -> np.ndarray:
    """`matching` in numpy: the edges ranked by a stable sort of their costs."""
    order = np.argsort(cost, kind="stable")
    sa, sb = a[order], b[order]
    free = np.ones(n, bool)
    chosen: list[np.ndarray] = []
    total = 0
    for _ in range(rounds):
        live = np.flatnonzero(free[sa] & free[sb])  # ranks, ascending
        if len(live) == 0:
            break
        first = np.full(n, len(order), np.int64)
        np.minimum.at(first, sa[live], live)
        np.minimum.at(first, sb[live], live)
        pick = live[(first[sa[live]] == live) & (first[sb[live]] == live)]
        chosen.append(pick)
        free[sa[pick]] = False
        free[sb[pick]] = False
        total += len(pick)
        if total >= limit:
            break
    ranks = np.sort(np.concatenate(chosen))[:limit] if chosen else np.zeros(0, np.int64)
    return order[ranks]


def knn_edges(mu: np.ndarray, nodes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (a < b, each once, ascending) between each of `nodes` and its `k` nearest others (by
    centre). Where the kernels run: the neighbours from a grid of cells (`compiled.nearest`; the
    k-d tree's but among points at exactly equal distances), the edges made unique by
    `compiled.unique_edges`; else (the reference) scipy's k-d tree and np.unique."""
    k = min(k, len(nodes) - 1)
    if k < 1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if compiled.available():
        near = compiled.nearest(mu[nodes], k)
        nb = _kd_tree(mu[nodes], k) if near is None else np.concatenate([np.arange(len(nodes))[:, None], near], 1)
        a, b = compiled.unique_edges(nb)
        return nodes[a], nodes[b]
    nb = _kd_tree(mu[nodes], k)
    a = np.repeat(np.arange(len(nodes)), k)
    b = nb[:, 1:].reshape(-1)
    ok = (b < len(nodes)) & (a != b)
    key = np.unique(np.minimum(a[ok], b[ok]) * len(nodes) + np.maximum(a[ok], b[ok]))
    return nodes[key // len(nodes)], nodes[key % len(nodes)]


def _kd_tree(points: np.ndarray, k: int) -> np.ndarray:
    """(M, k+1): each point and its k nearest others by scipy's k-d tree (imported here: scipy is slow
    to import, and the grid of `compiled.nearest` answers without it)."""
    from scipy.spatial import cKDTree  # noqa: PLC0415

    return cKDTree(points).query(points, k + 1, workers=-1)[1]


def merge_owner(m: Moments, target: int, neighbours: int, progress=None) -> np.ndarray:
    """(N,) the group (0..target-1) of each Gaussian after merging pairs, cheapest first, pass
    after pass over the k-nearest-neighbour graph (contracted as groups form; made again among
    the groups if it runs out of edges), until `target` groups are left. Each pass recomputes
    only the costs of the edges whose ends changed."""
    n = len(m.mass)
    owner = np.arange(n)
    a, b = knn_edges(m.mu, owner, neighbours)
    cost = pair_cost(m, a, b)
    alive = n
    while alive > target:
        if len(a) == 0:
            a, b = knn_edges(m.mu, np.flatnonzero(owner == np.arange(n)), neighbours)
            if len(a) == 0:
                break
            cost = pair_cost(m, a, b)
        pick = matching(a, b, cost, n, alive - target)
        pa, pb = a[pick], b[pick]
        merge_pairs(m, pa, pb)
        owner[pb] = pa
        alive -= len(pick)
        touched = np.zeros(n, bool)
        touched[pa] = touched[pb] = True
        changed = touched[a] | touched[b]
        owner = owner_root(owner)
        a, b = owner[a], owner[b]  # contract the graph onto the groups' representatives
        keep = a != b
        a, b, cost, changed = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep]), cost[keep], changed[keep]
        if alive > target:  # (after the last pass the costs are not read again)
            redo = np.flatnonzero(changed)
            cost[redo] = pair_cost(m, a[redo], b[redo])
        if progress is not None:
            progress(1.0 - (alive - target) / max(n - target, 1), f"merging: {alive:,} Gaussians")
    _, groups = np.unique(owner, return_inverse=True)
    return groups


def owner_root(owner: np.ndarray) -> np.ndarray:
    """Each entry's root in a forest given by parent pointers (roots point at themselves)."""
    while True:
        nxt = owner[owner]
        if np.array_equal(nxt, owner):
            return owner
        owner = nxt
