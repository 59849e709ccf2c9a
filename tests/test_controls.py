"""Controls at equal output count: split, duplicate-in-place, thinning."""

import math

import numpy as np
import pytest

from gvae_core import Camera, GaussianCloud, render
from gvae_core.controls import duplicate_control, split_control, thin_added
from gvae_core.conventions import activate_opacities
from gvae_core.refinement import RefineResult


def _cloud(n=30, seed=0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(means=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                         scales=(math.log(0.05) + rng.normal(0, 0.3, (n, 3))).astype(np.float32),
                         quats=rng.normal(size=(n, 4)).astype(np.float32),
                         opacities=rng.normal(0, 1, n).astype(np.float32),
                         sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.1, (n, 3, 3)).astype(np.float32),
                         extra={"gvae_id": np.arange(100, 100 + n, dtype=np.int64),
                                "gvae_parent": np.full(n, -1, np.int64)})


@pytest.mark.parametrize("control", [split_control, duplicate_control])
def test_controls_add_exactly_the_target_counts(control):
    cloud = _cloud()
    scores = np.arange(30, dtype=np.float32)  # row 29 scores highest
    out = list(control(cloud, scores, [3, 7, 7, 12], seed=1))
    assert [len(r.added) for r in out] == [3, 7, 7, 12]
    first = out[0]
    assert set(first.selected.tolist()) == {27, 28, 29}  # untouched Gaussians go by score
    for r in out:
        assert len(r.cloud) == 30 + len(r.added) and np.isfinite(r.cloud.means).all()
        assert r.cloud.extra["gvae_id"].tolist()[:30] == list(range(100, 130))
        assert len(set(r.cloud.extra["gvae_id"].tolist())) == len(r.cloud)  # fresh ids for the added
        assert np.isin(r.parents, np.arange(30)).all()
    # rows never chosen are untouched
    untouched = np.setdiff1d(np.arange(30), out[-1].selected)
    np.testing.assert_array_equal(out[-1].cloud.means[untouched], cloud.means[untouched])


def test_split_control_follows_the_3dgs_rule():
    cloud = _cloud()
    r = next(split_control(cloud, np.arange(30), [2], seed=3))
    rows = r.parents  # the appended children follow the order of their parents
    np.testing.assert_allclose(r.cloud.scales[rows], cloud.scales[rows] - math.log(1.6), atol=1e-6)
    np.testing.assert_allclose(r.cloud.scales[30:], cloud.scales[rows] - math.log(1.6), atol=1e-6)
    np.testing.assert_array_equal(r.cloud.sh_dc[30:], cloud.sh_dc[rows])
    assert not np.allclose(r.cloud.means[rows], cloud.means[rows])


def test_duplicate_in_place_keeps_the_render():
    cloud = _cloud(n=12, seed=2)
    cam = Camera.look_at((0, -4, 1), (0, 0, 0), width=48, height=48)
    before = render(cloud, cam).image.numpy()
    r = next(duplicate_control(cloud, np.zeros(12), [12]))
    o = activate_opacities(cloud.opacities.astype(np.float64))
    shared = activate_opacities(r.cloud.opacities.astype(np.float64))
    np.testing.assert_allclose(1 - (1 - shared[:12]) ** 2, o, atol=1e-6)
    np.testing.assert_array_equal(r.cloud.means[12:], cloud.means)
    after = render(r.cloud, cam).image.numpy()
    assert np.abs(after - before).max() < 0.05 and np.abs(after - before).mean() < 0.005


def test_thin_added_keeps_inputs_and_a_random_subset():
    cloud = _cloud(n=10)
    grown = GaussianCloud.concat([cloud, cloud.select(np.arange(6))])
    result = RefineResult(cloud=grown, added=np.arange(10, 16), parents=np.arange(6), step=np.ones(6, np.int64),
                          scores=np.zeros(10, np.float32), selected=np.arange(6))
    thin = thin_added(result, 4, seed=0)
    assert len(thin.cloud) == 14 and len(thin.added) == 4 and len(thin.parents) == 4
    np.testing.assert_array_equal(thin.cloud.means[:10], cloud.means)
    np.testing.assert_array_equal(thin.cloud.means[10:], cloud.means[thin.parents])
    assert len(thin_added(result, 99).added) == 6
