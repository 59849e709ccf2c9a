"""Lineages: invariants, features, sequences/transitions against a brute-force walk, files."""

import numpy as np
import pytest

from gvae_core.cloud import GaussianCloud
from gvae_core.lineage import (APP_EXIST, APP_OPACITY, APP_SH_DC, APP_SH_REST, GEO_EXIST, GEO_LOG_SCALE, GEO_POSITION,
                               GEO_QUAT, Lineage, appearance_features, cloud_from_features, geometry_features)


def random_cloud(n, rng, degree=3):
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return GaussianCloud(
        means=rng.normal(size=(n, 3)).astype(np.float32) * 2 + 5,
        scales=rng.normal(-3, 0.5, size=(n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.normal(size=n).astype(np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(size=(n, k, 3)).astype(np.float32),
    )


def simulate(rng, n0=30, stages=4, degrees=(1, 2, 3, 3)):
    """A random densification history (independent of the trainer): within each stage Gaussians
    are cloned, split (parent removed) and pruned several times; returns the Lineage and, for a
    brute-force check, every id's direct parent."""
    lin = Lineage()
    direct_parent = {}
    ids = list(range(n0))
    anchor = {i: -1 for i in ids}
    next_id = n0
    for s in range(stages):
        if s > 0:
            anchor = {i: i for i in ids}
        for _ in range(3):
            new_ids = []
            for i in ids:
                r = rng.random()
                if r < 0.15:  # clone
                    new_ids += [i, next_id]
                    direct_parent[next_id], anchor[next_id] = i, anchor[i]
                    next_id += 1
                elif r < 0.25:  # split: two children, parent gone
                    for _ in range(2):
                        new_ids.append(next_id)
                        direct_parent[next_id], anchor[next_id] = i, anchor[i]
                        next_id += 1
                elif r < 0.32 and len(ids) > 3:  # prune
                    pass
                else:
                    new_ids.append(i)
            ids = new_ids
        cloud = random_cloud(len(ids), rng, degrees[s])
        lin.add_stage(cloud, ids, [anchor[i] for i in ids], 100 + 50 * s)
    return lin, direct_parent


def nearest_alive_ancestor(i, alive, direct_parent):
    while i not in alive:
        if i not in direct_parent:
            return None
        i = direct_parent[i]
    return i


def test_sequences_match_brute_force_walk():
    rng = np.random.default_rng(0)
    lin, direct_parent = simulate(rng)
    for k in range(lin.n_stages):
        batch = lin.sequences(k)
        snap = lin.snapshots[k]
        assert batch.geometry.shape == (len(snap), k + 1, 11)
        assert batch.appearance.shape == (len(snap), k + 1, 50)
        assert np.array_equal(batch.ids, snap.ids)
        for m, gid in enumerate(batch.ids):
            for s in range(k + 1):
                alive = {int(x): r for r, x in enumerate(lin.snapshots[s].ids)}
                anc = nearest_alive_ancestor(int(gid), alive, direct_parent)
                assert anc is not None  # the simulator never creates orphans
                row = alive[anc]
                c = lin.snapshots[s].cloud
                geo = geometry_features(c.select([row]), lin.center, lin.scale)[0]
                app = appearance_features(c.select([row]))[0]
                exist = float(anc == gid)
                assert batch.geometry[m, s, GEO_EXIST] == exist
                assert batch.appearance[m, s, APP_EXIST] == exist
                np.testing.assert_array_equal(batch.geometry[m, s, :10], geo[:10])
                np.testing.assert_array_equal(batch.appearance[m, s, :49], app[:49])
        # exist flags are monotone: once a Gaussian exists it exists until the last node
        e = batch.geometry[..., GEO_EXIST]
        assert (np.diff(e, axis=1) >= 0).all() and (e[:, -1] == 1).all()


def test_transitions_group_children_by_parent():
    rng = np.random.default_rng(1)
    lin, _ = simulate(rng)
    for k in range(1, lin.n_stages):
        tr = lin.transitions(k, max_children=64)
        prev, cur = lin.snapshots[k - 1], lin.snapshots[k]
        assert len(tr) == len(prev) and tr.history_geometry.shape[1] == k
        assert tr.dropped == 0 and tr.orphans == 0
        assert tr.child_mask.sum() == len(cur)  # every stage-k Gaussian is someone's child
        geo_k = geometry_features(cur.cloud, lin.center, lin.scale)
        row_of = {int(x): r for r, x in enumerate(cur.ids)}
        for m, pid in enumerate(prev.ids):
            expect = sorted(int(i) for i, p in zip(cur.ids, cur.parents) if p == pid)
            if pid in expect:  # the survivor comes first
                expect.remove(int(pid))
                expect = [int(pid)] + expect
            got = [int(i) for i in tr.child_ids[m][tr.child_mask[m]]]
            assert got == expect
            assert not tr.child_mask[m, len(got):].any()
            for c, cid in enumerate(got):
                np.testing.assert_array_equal(tr.child_geometry[m, c], geo_k[row_of[cid]])


def test_transitions_cap_reports_dropped_children():
    lin = Lineage()
    lin.add_stage(random_cloud(2, np.random.default_rng(2)), [0, 1], [-1, -1], 10)
    lin.add_stage(random_cloud(6, np.random.default_rng(3)), [0, 2, 3, 4, 5, 1], [0, 0, 0, 0, 0, 1], 20)
    tr = lin.transitions(1, max_children=3)
    assert tr.child_mask.shape == (2, 3)
    assert tr.dropped == 2
    assert tr.child_ids[0].tolist() == [0, 2, 3] and tr.child_ids[1].tolist() == [1, -1, -1]
    with pytest.raises(ValueError):
        lin.transitions(0)


def test_feature_layout_and_inverse():
    rng = np.random.default_rng(4)
    cloud = random_cloud(20, rng, degree=2)
    center, scale = np.array([1.0, -2.0, 0.5]), 3.0
    geo = geometry_features(cloud, center, scale)
    app = appearance_features(cloud)
    np.testing.assert_allclose(geo[:, GEO_POSITION], (cloud.means - center) / scale, rtol=1e-5, atol=1e-6)
    q = geo[:, GEO_QUAT]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-6)
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(geo[:, GEO_LOG_SCALE], cloud.scales - np.log(scale), rtol=1e-6, atol=1e-6)
    # SH rest is coefficient-major: index k*3 + channel, zero-padded past degree 2 (8 coefficients)
    for k in range(15):
        for ch in range(3):
            want = cloud.sh_rest[:, k, ch] if k < 8 else 0.0
            np.testing.assert_array_equal(app[:, APP_SH_REST][:, k * 3 + ch], want)
    np.testing.assert_array_equal(app[:, APP_SH_DC], cloud.sh_dc)
    np.testing.assert_array_equal(app[:, APP_OPACITY], cloud.opacities)
    back = cloud_from_features(geo, app, center, scale, sh_degree=2)
    np.testing.assert_allclose(back.means, cloud.means, atol=1e-5)
    np.testing.assert_allclose(back.scales, cloud.scales, atol=1e-5)
    np.testing.assert_allclose(back.rotation_matrices(), cloud.rotation_matrices(), atol=1e-5)
    np.testing.assert_array_equal(back.sh_rest, cloud.sh_rest)


def test_from_cloud_is_one_node_lineages():
    rng = np.random.default_rng(6)
    cloud = random_cloud(7, rng).replace(extra={"gvae_id": np.arange(10, 17, dtype=np.int64)})
    lin = Lineage.from_cloud(cloud)
    batch = lin.sequences(0)
    assert batch.geometry.shape == (7, 1, 11)
    assert batch.ids.tolist() == list(range(10, 17))
    assert (batch.geometry[:, 0, GEO_EXIST] == 1).all()
    # normalised positions are O(1)
    assert np.abs(batch.geometry[:, 0, GEO_POSITION]).max() < 3


def test_add_stage_rejects_broken_invariants():
    rng = np.random.default_rng(7)
    lin = Lineage()
    with pytest.raises(ValueError, match="-1"):
        lin.add_stage(random_cloud(2, rng), [0, 1], [0, -1], 10)
    with pytest.raises(ValueError, match="unique"):
        lin.add_stage(random_cloud(2, rng), [0, 0], [-1, -1], 10)
    lin.add_stage(random_cloud(3, rng), [0, 1, 2], [-1, -1, -1], 10)
    with pytest.raises(ValueError, match="not alive"):
        lin.add_stage(random_cloud(2, rng), [0, 5], [0, 9], 20)
    with pytest.raises(ValueError, match="own parent"):
        lin.add_stage(random_cloud(2, rng), [0, 1], [0, 0], 20)
    lin.add_stage(random_cloud(2, rng), [0, 3], [0, 1], 20)
    with pytest.raises(ValueError, match="reappears"):
        lin.add_stage(random_cloud(2, rng), [0, 2], [0, 0], 30)
    with pytest.raises(ValueError, match="ids"):
        lin.add_stage(random_cloud(2, rng), [0], [0], 30)


def test_save_load_round_trip_and_bad_files(tmp_path):
    rng = np.random.default_rng(8)
    lin, _ = simulate(rng, stages=3)
    lin.set_normalization(np.array([0.5, 1.0, -1.0]), 2.5)
    path = lin.save(tmp_path / "lineage.npz")
    assert not list(tmp_path.glob("*.tmp"))
    back = Lineage.load(path)
    assert back.resolutions == lin.resolutions and back.scale == lin.scale
    np.testing.assert_array_equal(back.center, lin.center)
    for k in range(lin.n_stages):
        a, b = lin.sequences(k), back.sequences(k)
        np.testing.assert_array_equal(a.geometry, b.geometry)
        np.testing.assert_array_equal(a.appearance, b.appearance)
        np.testing.assert_array_equal(a.ids, b.ids)
    cloud = back.stage_cloud(2)
    assert cloud.extra["gvae_id"].dtype == np.int64
    np.testing.assert_array_equal(cloud.extra["gvae_parent"], lin.snapshots[2].parents)

    with pytest.raises(FileNotFoundError):
        Lineage.load(tmp_path / "missing.npz")
    bad = tmp_path / "other.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(ValueError, match="other.npz"):
        Lineage.load(bad)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="garbage.npz"):
        Lineage.load(garbage)
    truncated = tmp_path / "trunc.npz"
    truncated.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(ValueError, match="trunc.npz"):
        Lineage.load(truncated)


def test_prefix_keeps_the_first_stages_and_renormalises():
    rng = np.random.default_rng(5)
    lin, _ = simulate(rng)
    pre = lin.prefix(2)
    assert pre.n_stages == 2 and pre.resolutions == lin.resolutions[:2]
    for s in range(2):
        np.testing.assert_array_equal(pre.snapshot(s).ids, lin.snapshot(s).ids)
        np.testing.assert_array_equal(pre.snapshot(s).cloud.means, lin.snapshot(s).cloud.means)
    center, scale = lin.snapshot(1).cloud.normalization()  # nothing from later stages
    np.testing.assert_allclose(pre.center, center)
    assert pre.scale == pytest.approx(scale)
    a, b = pre.sequences(1), lin.sequences(1)
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.geometry[..., GEO_QUAT], b.geometry[..., GEO_QUAT])  # frame-independent
    for bad in (0, lin.n_stages + 1):
        with pytest.raises(ValueError, match="n_stages"):
            lin.prefix(bad)
