"""Hessian (Gauss-Newton) scores: convergence to the exact J^T J, finiteness, views."""

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud
from gvae_core.hessian import (default_views, hessian_blocks, hessian_blocks_reference, hessian_scores,
                               scores_from_blocks)
from gvae_core.rendering import RenderSettings


LOG_SCALE = math.log(0.15)


def _cloud(n=4, seed=0, spread=0.3, log_scale=LOG_SCALE) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(means=rng.uniform(-spread, spread, (n, 3)).astype(np.float32),
                         scales=(log_scale + rng.normal(0, 0.2, (n, 3))).astype(np.float32),
                         quats=rng.normal(size=(n, 4)).astype(np.float32),
                         opacities=np.full(n, 1.0, np.float32), sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.1, (n, 3, 3)).astype(np.float32))


def _tiny_cameras(size=10):
    return [Camera.look_at((2.5, 0.3, 1.0), (0, 0, 0), width=size, height=size),
            Camera.look_at((-0.5, 2.5, 1.0), (0, 0, 0), width=size, height=size)]


def test_estimator_converges_to_exact_gauss_newton_block():
    cloud, cams = _cloud(), _tiny_cameras(8)[:1]
    fast = RenderSettings(backward="autograd")  # many backward passes through one tiny graph
    exact = hessian_blocks_reference(cloud, cams, fast)
    assert exact.abs().sum() > 0
    # the exact blocks are symmetric positive semi-definite
    assert torch.allclose(exact, exact.transpose(1, 2))
    assert (torch.linalg.eigvalsh(exact) > -1e-6 * exact.abs().max()).all()

    estimates = {p: hessian_blocks(cloud, cams, probes=p, seed=1, render_settings=fast) for p in (4, 24, 200)}
    errors = [float(((est - exact).norm(dim=(1, 2)) / exact.norm(dim=(1, 2))).mean()) for est in estimates.values()]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.15
    # the score of the estimate approaches the score of the exact block
    s_est = scores_from_blocks(estimates[200])
    s_exact = scores_from_blocks(exact)
    assert torch.allclose(s_est, s_exact, rtol=0.1, atol=0.3)


def test_scores_finite_and_nonnegative_for_degenerate_clouds():
    cloud = _cloud(n=12, seed=2)
    cloud.quats[0] = 0.0                     # zero quaternion
    cloud.scales[1] = -30.0                  # vanishing
    cloud.scales[2] = 30.0                   # enormous
    cloud.opacities[3] = -50.0               # transparent
    cloud.opacities[4] = 50.0
    cloud.means[5] = [1e6, 0, 0]             # far away
    cloud.means[6] = [2.5, 0.3, 1.0]         # at a camera centre
    cams = _tiny_cameras(16)
    for score in ("logdet", "trace"):
        s = hessian_scores(cloud, cams, probes=2, score=score)
        assert s.shape == (12,) and torch.isfinite(s).all() and (s >= 0).all()
    s = hessian_scores(cloud, cams, probes=2)
    assert s[7:].min() > 0  # ordinary visible Gaussians score
    assert s[3] == 0        # a transparent Gaussian has no influence on the image


def test_scores_without_cameras_and_edge_cases():
    cloud = _cloud(n=6, seed=3)
    s = hessian_scores(cloud, views=2, probes=1, resolution=24)
    assert s.shape == (6,) and torch.isfinite(s).all() and (s > 0).all()
    assert hessian_scores(GaussianCloud.empty(), views=1).shape == (0,)
    everything_hidden = _cloud(n=3)
    everything_hidden.opacities[:] = -50
    assert (hessian_scores(everything_hidden, views=1, probes=1, resolution=16) == 0).all()
    with pytest.raises(ValueError, match="score"):
        hessian_scores(cloud, score="det")
    with pytest.raises(ValueError, match="probes"):
        hessian_scores(cloud, probes=0)


def test_default_views_frame_the_cloud():
    cloud = _cloud(n=200, seed=4, spread=5.0)
    cloud.means += np.float32(100.0)
    for cam in default_views(cloud, views=5, resolution=40):
        uv, z = cam.project(cloud.means)
        assert (z > 0).all()
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= 40) & (uv[:, 1] >= 0) & (uv[:, 1] <= 40)
        assert inside.mean() > 0.95


def test_scores_are_deterministic_per_seed():
    cloud, cams = _cloud(), _tiny_cameras()
    a = hessian_scores(cloud, cams, probes=3, seed=5)
    b = hessian_scores(cloud, cams, probes=3, seed=5)
    c = hessian_scores(cloud, cams, probes=3, seed=6)
    assert torch.equal(a, b) and not torch.equal(a, c)
