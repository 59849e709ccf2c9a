"""Resolution-aware changes (gvae_core.octaves): stored per octave, drawn by sampling rate, baked."""

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, render
from gvae_core.antialias import with_dilation_3d
from gvae_core.examples import random_cloud
from gvae_core.octaves import (LIMIT_KEY, bake, field_keys, octave_fields, octaves_seen, training_rate, with_octaves,
                               without_octaves)
from gvae_core.ply import read_ply, write_ply
from gvae_core.rendering import RenderSettings


def _camera(height=32, distance=4.0):
    w2c = np.eye(4)
    w2c[2, 3] = distance
    f = 1.2 * height
    return Camera(world_to_cam=w2c, fx=f, fy=f, cx=height / 2, cy=height / 2, width=height, height=height)


def _small(n, seed):
    c = random_cloud(n, seed=seed)
    return c.replace(means=(0.25 * c.means).astype(np.float32), scales=(c.scales + 1.5).astype(np.float32))


def _cloud(n=60, seed=0):
    return with_dilation_3d(_small(n, seed), [_camera(32)])


def _changes(cloud, seed=1):
    rng = np.random.default_rng(seed)
    n = len(cloud)
    return {"scales": rng.normal(0, 0.3, (n, 3)).astype(np.float32),
            "opacities": rng.normal(0, 1.0, n).astype(np.float32),
            "sh_dc": rng.normal(0, 0.2, (n, 3)).astype(np.float32)}


def test_octaves_seen_follows_the_sampling_rate():
    cloud = _cloud()
    rate = training_rate(cloud)
    z = 4.0 + cloud.means[:, 2].astype(np.float64)
    # The training camera itself: f/z <= nu for every Gaussian it sees, so nothing is drawn changed.
    assert np.all(octaves_seen(cloud.means, rate, np.full(len(cloud), 3.0), _camera(32)) <= 1e-6)
    # Twice the resolution: log2(2 f / z / nu), at most the limit.
    t = octaves_seen(cloud.means, rate, np.full(len(cloud), 3.0), _camera(64))
    expected = np.clip(np.log2(2 * 1.2 * 32 / z / rate), 0, 3)
    np.testing.assert_allclose(t, expected, rtol=1e-9, atol=1e-9)
    assert np.all(octaves_seen(cloud.means, rate, np.full(len(cloud), 0.5), _camera(256)) <= 0.5)
    tt = octaves_seen(torch.from_numpy(cloud.means), torch.from_numpy(rate), torch.full((len(cloud),), 3.0),
                      _camera(64))
    np.testing.assert_allclose(tt.numpy(), t, rtol=1e-6, atol=1e-9)


def test_behind_the_camera_and_unknown_rates_draw_unchanged():
    means = np.array([[0, 0, -10.0], [0, 0, 0], [0, 0, 1e30], [0, 0, np.nan]])
    t = octaves_seen(means, np.array([1.0, 0.0, 1.0, 1.0]), np.ones(4), _camera(64, distance=4.0))
    assert np.all(t == 0) and np.isfinite(t).all()


def test_the_training_resolution_draws_the_input_exactly():
    cloud = _cloud()
    refined = with_octaves(cloud, _changes(cloud))
    cam = _camera(32)
    a = render(cloud, cam, settings=RenderSettings(antialias="matched")).image
    b = render(refined, cam, settings=RenderSettings(antialias="matched")).image
    assert torch.equal(a, b)
    # twice the resolution: the change shows; classic ignores it (the reference's view of the PLY)
    cam2 = _camera(64)
    assert not torch.allclose(render(cloud, cam2).image, render(refined, cam2).image, atol=1e-3)
    classic = RenderSettings(antialias="classic")
    assert torch.equal(render(cloud, cam2, settings=classic).image, render(refined, cam2, settings=classic).image)


def test_render_at_twice_the_rate_matches_the_baked_cloud_for_a_flat_object():
    # Every Gaussian at one depth, seen by the training camera straight on: at 2x the resolution
    # each one is exactly one octave up, which is what bake(factor=2) writes.
    rng = np.random.default_rng(3)
    cloud = _small(40, 3)
    cloud = cloud.replace(means=np.c_[rng.uniform(-0.5, 0.5, (40, 2)), np.zeros(40)].astype(np.float32))
    cloud = with_dilation_3d(cloud, [_camera(32)])
    cloud = cloud.replace(extra={**cloud.extra, "gvae_dilation_3D": np.full(40, cloud.extra["gvae_dilation_3D"].min(),
                                                                                np.float32)})
    refined = with_octaves(cloud, _changes(cloud), limit=1.0)
    baked = bake(refined, 2.0)
    assert not any(k.startswith("gvae_octave") for k in baked.extra)
    cam = _camera(64)
    np.testing.assert_allclose(render(refined, cam).image.numpy(), render(baked, cam).image.numpy(), atol=2e-4)
    np.testing.assert_array_equal(bake(refined, 1.0).scales, cloud.scales)


def test_gradients_reach_the_stored_changes_and_stay_finite():
    cloud = _cloud().to_torch()
    changes = {k: torch.zeros_like(torch.as_tensor(v), requires_grad=True) for k, v in _changes(cloud.numpy()).items()}
    out = render(with_octaves(cloud, changes), _camera(64))
    out.image.sum().backward()
    for v in changes.values():
        assert v.grad is not None and torch.isfinite(v.grad).all() and v.grad.abs().sum() > 0


def test_round_trip_through_ply(tmp_path):
    cloud = _cloud()
    refined = with_octaves(cloud, _changes(cloud), limit=2.0)
    back = read_ply(write_ply(refined, tmp_path / "r.ply"))
    for field, change in octave_fields(refined).items():
        np.testing.assert_array_equal(octave_fields(back)[field], change)
    np.testing.assert_array_equal(back.extra[LIMIT_KEY], np.full(len(cloud), 2.0, np.float32))
    assert field_keys("opacities", 1) == ["gvae_octave_opacity"]
    assert field_keys("scales", 3) == ["gvae_octave_scale_0", "gvae_octave_scale_1", "gvae_octave_scale_2"]
    assert set(without_octaves(refined).extra) == set(cloud.extra)


def test_refuses_a_cloud_without_a_training_rate():
    cloud = random_cloud(5, seed=0)
    with pytest.raises(ValueError, match="anti-aliasing size"):
        with_octaves(cloud, {"scales": np.zeros((5, 3), np.float32)})
    with pytest.raises(ValueError, match="limit"):
        with_octaves(_cloud(), {}, limit=math.inf)


def test_octaves_seen_in_threads_is_the_torch_branch():
    """Enough Gaussians to be split into ranges run in threads (numpy, what `drawn_fields` runs on
    the CPU): the torch branch's values (the same float64 arithmetic), limits per Gaussian, and
    unknown rates, points behind the camera and NaN centres drawn unchanged."""
    rng = np.random.default_rng(2)
    n = 100_003
    means = rng.normal(0.0, 1.0, (n, 3)).astype(np.float32)
    means[:3] = [[0, 0, -10.0], [np.nan, 0, 0], [0, 0, 3.9]]
    rate = rng.uniform(5.0, 60.0, n)
    rate[3], rate[4] = 0.0, np.inf
    limit = rng.choice(np.float32([0.5, 1.0, 3.0]), n)
    cam = _camera(64, distance=4.0)
    t = octaves_seen(means, rate, limit, cam)
    tt = octaves_seen(torch.from_numpy(means), torch.from_numpy(rate), torch.from_numpy(limit), cam).numpy()
    np.testing.assert_allclose(t, tt, rtol=1e-12, atol=1e-12)
    assert t.dtype == np.float64 and np.isfinite(t).all() and (t[:5] == 0).all() and (t <= limit).all()
    assert (t > 0).mean() > 0.2
