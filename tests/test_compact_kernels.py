"""Compaction's compiled kernels (`gvae_core.compaction.compiled`, Numba) held to the numpy and torch
code they stand for: the pixel hits of the torch sweep, the moments, merge costs, merges, matching
and neighbour edges of the numpy code, the grid's nearest neighbours of scipy's k-d tree, the
merged groups of `merge_groups_numpy`, and a whole removal with and without them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gvae_core import Camera
from gvae_core.compaction import compiled, graph, merge, moments, pixel_hits, pixel_hits_reference, removal_groups
from gvae_core.compaction.scoring import frame_hits
from gvae_core.examples import example_cloud
from gvae_core.rendering import RenderSettings
from gvae_core.rendering.frames import make_frame

from .test_compact import _cloud, _covariances, _groups

pytestmark = pytest.mark.skipif(not compiled.available(), reason="Numba is not installed or does not load")

CAMS = [Camera.look_at((0.0, -3.0, 1.5), (0, 0, 0), width=30, height=21, fov_x=1.0),
        Camera.look_at((2.5, 1.0, 2.0), (0, 0, 0), width=19, height=26, fov_x=0.8)]


def _moments(n=400, seed=0):
    """Moments of a cloud with some degenerate Gaussians: zero and huge quaternions, flat and huge scales."""
    c = example_cloud(n, seed=seed).with_sh_degree(1).numpy().copy()
    c.quats[:5] = 0.0
    c.quats[5:8] *= 1e20
    c.scales[8:12, 0] = -np.inf
    c.scales[12:14] = 25.0
    weight = np.random.default_rng(seed).random(n)
    return c, weight


def _close(x, y, rtol, name):
    """x equals y to `rtol` of the largest magnitude in each row (covariances of huge Gaussians
    cancel in their off-diagonal entries: their rounding is relative to the diagonal)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    scale = np.abs(y).reshape(len(y), -1).max(1).reshape((-1,) + (1,) * (y.ndim - 1)) if y.ndim > 1 else np.abs(y)
    bad = np.abs(x - y) > rtol * scale
    assert not bad.any(), f"{name}: {int(bad.sum())} entries differ, max {np.abs(x - y)[bad].max():.3g}"


def test_pixel_hits_are_the_torch_sweeps():
    cloud = example_cloud(500, seed=4).with_sh_degree(1)
    fast = pixel_hits(cloud, CAMS, RenderSettings(tile_size=4))
    torch_sweep = pixel_hits(cloud, CAMS, RenderSettings(tile_size=4, kernels="torch"))
    assert fast.sum() > 1000 and (fast > 0).sum() > 50
    np.testing.assert_array_equal(fast, torch_sweep)
    small = example_cloud(60, seed=2).with_sh_degree(0)
    np.testing.assert_array_equal(pixel_hits(small, CAMS[:1], RenderSettings(tile_size=8)),
                                  pixel_hits_reference(small, CAMS[:1], "auto"))


def test_frame_hits_sweep_only_what_is_asked_and_agree_with_torch():
    cloud = example_cloud(500, seed=5).with_sh_degree(1)
    frame = make_frame(cloud, CAMS[0], RenderSettings(tile_size=4))
    frame = dataclasses.replace(frame, rows=frame.rows.flip(0))  # table row i draws cloud row n-1-i
    rows = np.random.default_rng(0).choice(len(cloud), 80, replace=False)
    fast = frame_hits(frame, len(cloud), rows)
    slow = frame_hits(dataclasses.replace(frame, settings=RenderSettings(tile_size=4, kernels="torch")), len(cloud),
                      rows)
    assert (fast > 0).sum() > 10
    np.testing.assert_array_equal(fast, slow)
    everything = pixel_hits(cloud, CAMS[:1], RenderSettings(tile_size=4))  # (of the table's own rows)
    np.testing.assert_array_equal(fast, everything[len(cloud) - 1 - rows])


def test_moments_costs_and_merges_are_the_numpy_ones():
    c, weight = _moments()
    rows = np.sort(np.random.default_rng(1).choice(len(c), 300, replace=False))
    fast = moments.moments(c, weight[rows], rows=rows)
    slow = moments.moments_numpy(c.select(rows), weight[rows])
    for name in ("mass", "mu", "sigma", "log_det", "colour", "weight", "origin"):
        _close(getattr(fast, name), getattr(slow, name), 1e-12, name)
    assert fast.floor == slow.floor
    a, b = graph.knn_edges(slow.mu, np.arange(len(rows)), 4)
    _close(moments.pair_cost(fast, a, b), moments.pair_cost_numpy(slow, a, b), 1e-9, "cost")
    heavy, heavy_numpy = (moments.moments(c, weight[rows], rows=rows, colour_weight=40.0),
                          moments.moments_numpy(c.select(rows), weight[rows], colour_weight=40.0))
    _close(moments.pair_cost(heavy, a, b), moments.pair_cost_numpy(heavy_numpy, a, b), 1e-9, "cost, colour weight")
    assert (moments.pair_cost_numpy(heavy_numpy, a, b) > moments.pair_cost_numpy(slow, a, b)).any()
    pick = graph.matching_numpy(a, b, moments.pair_cost_numpy(slow, a, b), len(rows), 100)
    moments.merge_pairs(fast, a[pick], b[pick])
    moments.merge_pairs_numpy(slow, a[pick], b[pick])
    for name in ("mass", "mu", "sigma", "log_det", "colour", "weight"):
        _close(getattr(fast, name), getattr(slow, name), 1e-9, name)


@pytest.mark.parametrize("ties", [False, True])
def test_matching_takes_the_edges_numpy_takes(ties):
    rng = np.random.default_rng(2)
    n = 300
    a = rng.integers(0, n, 2000)
    b = rng.integers(0, n, 2000)
    a, b = np.minimum(a, b)[a != b], np.maximum(a, b)[a != b]
    cost = rng.integers(0, 5, len(a)).astype(np.float64) if ties else rng.random(len(a))
    if ties:
        cost[::17] = np.nan
    for limit in (10, 60, 10_000):
        fast = compiled.matching(a, b, cost, n, limit)
        slow = graph.matching_numpy(a, b, cost, n, limit)
        np.testing.assert_array_equal(fast, slow)
        ends = np.concatenate([a[fast], b[fast]])
        assert len(np.unique(ends)) == len(ends)  # a matching
    assert len(slow) > 60


def test_unique_edges_are_numpys():
    rng = np.random.default_rng(3)
    m = 200
    nb = rng.integers(0, m + 3, (m, 5))  # some out of range (no neighbour), some repeated, some the row itself
    nb[:, 0] = np.arange(m)
    nb[::7, 2] = np.arange(m)[::7]
    a, b = compiled.unique_edges(nb)
    aa = np.repeat(np.arange(m), 4)
    bb = nb[:, 1:].reshape(-1)
    ok = (bb < m) & (aa != bb)
    key = np.unique(np.minimum(aa[ok], bb[ok]) * m + np.maximum(aa[ok], bb[ok]))
    np.testing.assert_array_equal(a, key // m)
    np.testing.assert_array_equal(b, key % m)


@pytest.mark.parametrize("shape", ["volume", "surface", "floaters"])
def test_grid_neighbours_are_the_kd_trees(shape, monkeypatch):
    rng = np.random.default_rng(7)
    points = {"volume": lambda: rng.random((6000, 3)),
              "surface": lambda: (lambda v: v / np.linalg.norm(v, axis=1, keepdims=True))(rng.normal(size=(6000, 3))),
              "floaters": lambda: np.concatenate([rng.random((6000, 3)), rng.normal(0, 300, (60, 3))])}[shape]()
    near = compiled.nearest(points, 4)  # (floaters: the points whose cells cannot tell go to the k-d tree)
    _, ref = cKDTree(points).query(points, 5)
    np.testing.assert_array_equal(near, ref[:, 1:])
    a, b = graph.knn_edges(points, np.arange(len(points)), 4)
    monkeypatch.setattr(compiled, "available", lambda: False)
    a_ref, b_ref = graph.knn_edges(points, np.arange(len(points)), 4)
    np.testing.assert_array_equal(a, a_ref)
    np.testing.assert_array_equal(b, b_ref)


def test_the_sweep_for_doubtful_points_is_the_kd_trees():
    """Floaters the grid cannot tell about: swept over every point (the default, a few of them) or
    asked of the k-d tree (sweep_limit 0), the same neighbours as the k-d tree's over all points."""
    rng = np.random.default_rng(9)
    points = np.concatenate([rng.random((5000, 3)), rng.normal(0, 300, (40, 3))])
    swept, asked = compiled.nearest(points, 4), compiled.nearest(points, 4, sweep_limit=0)
    _, ref = cKDTree(points).query(points, 5)
    np.testing.assert_array_equal(swept, ref[:, 1:])
    np.testing.assert_array_equal(asked, ref[:, 1:])


def test_grid_neighbours_of_coincident_points():
    """Many copies of a few points: no grid (a cell would hold too many), the k-d tree answers; a
    few twins: each point's nearest others, never itself."""
    rng = np.random.default_rng(8)
    assert compiled.nearest(np.repeat(rng.random((20, 3)), 300, 0), 4) is None
    a, b = graph.knn_edges(np.repeat(rng.random((20, 3)), 300, 0), np.arange(6000), 4)
    assert len(a) > 0 and (a < b).all()
    points = np.concatenate([rng.random((3000, 3)), rng.random((10, 3))])
    points[-10:] = points[:10]
    near = compiled.nearest(points, 4)
    assert (near != np.arange(len(points))[:, None]).all()
    d = np.linalg.norm(points[near] - points[:, None], axis=2)
    _, ref = cKDTree(points).query(points, 5)
    np.testing.assert_allclose(d, np.sort(np.linalg.norm(points[ref] - points[:, None], axis=2), 1)[:, 1:])


def test_eigh3_is_numpys_eigh():
    """The merged shapes' eigen-decompositions: numpy's eigenvalues, axes that rebuild the matrix
    and are numpy's up to sign where the eigenvalues are apart; diagonal, round, flat and zero too."""
    rng = np.random.default_rng(10)
    q = np.linalg.qr(rng.normal(size=(200, 3, 3)))[0]
    vals = np.exp(rng.uniform(-12, 2, (200, 3)))
    vals[:20, 1] = vals[:20, 0]  # two equal axes
    vals[20:30] = vals[20:30, :1]  # round
    vals[30:40, 0] = 0.0  # flat
    full = np.einsum("nij,nj,nkj->nik", q, vals, q)
    full[40:50] = np.diag([3.0, 1.0, 2.0])
    full[50] = 0.0
    sigma = np.ascontiguousarray(full[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]])
    got_vals, got_vecs = np.empty((200, 3)), np.empty((200, 3, 3))
    compiled.kernels().eigh3(sigma, 0, 200, got_vals, got_vecs)
    full = sigma[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    ref_vals, ref_vecs = np.linalg.eigh(full)
    size = np.abs(ref_vals).max(1, keepdims=True) + 1e-300
    np.testing.assert_allclose(got_vals / size, ref_vals / size, atol=1e-13)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", got_vecs, got_vecs), np.broadcast_to(np.eye(3), (200, 3, 3)),
                               atol=1e-13)
    rebuilt = np.einsum("nij,nj,nkj->nik", got_vecs, got_vals, got_vecs)
    np.testing.assert_allclose(rebuilt / size[:, :, None], full / size[:, :, None], atol=1e-13)
    apart = np.ones((200, 3), bool)
    apart[:30] = False
    dots = np.abs((got_vecs * ref_vecs).sum(1))
    np.testing.assert_allclose(dots[apart], 1.0, atol=1e-9)


def test_merged_groups_are_the_numpy_ones():
    rng = np.random.default_rng(4)
    cloud = _cloud(300)
    groups = _groups(len(cloud), rng)
    fast, rows = merge.merge_groups(cloud, groups)
    slow, rows_slow = merge.merge_groups_numpy(cloud, groups)
    np.testing.assert_array_equal(rows, rows_slow)
    for name in ("means", "scales", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=1e-5, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(_covariances(fast), _covariances(slow), atol=1e-5)  # (the axes: each up to its sign)
    singles = np.bincount(groups[groups >= 0]) == 1
    np.testing.assert_array_equal(fast.quats[singles], slow.quats[singles])
    for key, value in slow.extra.items():
        np.testing.assert_allclose(fast.extra[key], value, rtol=1e-6, err_msg=key)
    twins = cloud.select(np.repeat(np.arange(50), 3))  # equal masses: the lowest row represents its group
    groups = np.repeat(np.arange(50), 3)[::-1].copy()
    np.testing.assert_array_equal(merge.merge_groups(twins, groups)[1], merge.merge_groups_numpy(twins, groups)[1])
    np.testing.assert_array_equal(merge.merge_groups(twins, groups)[1], np.arange(147, -1, -3))


def test_removal_with_and_without_the_kernels_is_the_same(monkeypatch):
    cloud = example_cloud(3000, seed=6).with_sh_degree(1)
    scores = np.random.default_rng(5).random(len(cloud))
    scores[:100] = 0.0  # unseen: dropped
    fast = removal_groups(cloud, scores, 1200)
    out_fast, _ = merge.merge_groups(cloud, fast)
    monkeypatch.setattr(compiled, "available", lambda: False)
    slow = removal_groups(cloud, scores, 1200)
    out_slow, _ = merge.merge_groups(cloud, slow)
    assert fast.max() == 1199 and (fast[:100] < 0).all()
    np.testing.assert_array_equal(fast, slow)
    np.testing.assert_allclose(out_fast.means, out_slow.means, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(out_fast.sh_rest, out_slow.sh_rest, rtol=1e-5, atol=1e-7)
