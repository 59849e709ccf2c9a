"""Hessian (Gauss-Newton) scores: the exact J^T J, finiteness, views for objects and for scenes."""

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import DILATION_KEY, FILTER_KEY
from gvae_core.budget import select_budget
from gvae_core.capture import default_views, scoring_views, surround_radius
from gvae_core.conventions import rgb_to_dc
from gvae_core.examples import example_cloud
from gvae_core.hessian import (_TRIU, hessian_blocks, hessian_blocks_reference, hessian_scores, scores_from_blocks,
                               scores_from_packed)
from gvae_core.rendering import RenderSettings, compiled, render

LOG_SCALE = math.log(0.15)


def _cloud(n=4, seed=0, spread=0.3, log_scale=LOG_SCALE, degree=1) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 3: 15}[degree]
    return GaussianCloud(means=rng.uniform(-spread, spread, (n, 3)).astype(np.float32),
                         scales=(log_scale + rng.normal(0, 0.2, (n, 3))).astype(np.float32),
                         quats=rng.normal(size=(n, 4)).astype(np.float32),
                         opacities=np.full(n, 1.0, np.float32), sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.3, (n, k, 3)).astype(np.float32))


def _tiny_cameras(size=10):
    return [Camera.look_at((2.5, 0.3, 1.0), (0, 0, 0), width=size, height=size - 1),
            Camera.look_at((-0.5, 2.5, 1.0), (0, 0, 0), width=size, height=size)]


def _relative_error(est, exact):
    return ((est - exact).norm(dim=(1, 2)) / exact.norm(dim=(1, 2)).clamp(min=1e-300)).max().item()


@pytest.mark.parametrize("dtype, tile_size, degree, spread, tol", [
    (torch.float64, 4, 1, 0.3, 1e-9), (torch.float64, 8, 3, 0.3, 1e-9), (torch.float32, 4, 3, 0.3, 1e-4),
    (torch.float64, 4, 3, 1.2, 1e-9)])  # spread 1.2: Gaussians across the image's edges
def test_blocks_are_the_exact_gauss_newton_blocks(dtype, tile_size, degree, spread, tol):
    """The blocks equal J^T J summed pixel by pixel and channel by channel from backward passes
    through `render` (the definition), to the working precision: no estimate, no variance."""
    cloud, cams = _cloud(n=8, seed=1, degree=degree, spread=spread), _tiny_cameras(9)
    settings = RenderSettings(backward="autograd", dtype=dtype, tile_size=tile_size, block=3)
    exact = hessian_blocks_reference(cloud, cams, settings)
    fast = hessian_blocks(cloud, cams, views=0, render_settings=settings)
    assert exact.abs().sum() > 0 and (exact.norm(dim=(1, 2)) > 0).sum() >= 6
    assert torch.allclose(fast, fast.transpose(1, 2))
    assert (torch.linalg.eigvalsh(fast) > -1e-9 * fast.abs().amax((1, 2), keepdim=True)[:, 0]).all()
    assert _relative_error(fast, exact) < tol
    assert torch.allclose(scores_from_blocks(fast), scores_from_blocks(exact), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("mode, keys", [("mip", (FILTER_KEY,)), ("matched", (DILATION_KEY,)),
                                        ("auto", (FILTER_KEY, DILATION_KEY)), ("classic", (FILTER_KEY,))])
def test_blocks_follow_the_anti_aliasing_mode(mode, keys):
    """With the 3D filter and the 2D Mip filter the opacity depends on position and scale, with the
    3D dilation the 2D dilation depends on depth: the blocks follow the renderer in every mode."""
    cloud = _cloud(n=6, seed=2)
    rng = np.random.default_rng(0)
    for key in keys:  # sizes around the views' sampling interval (~0.1): some clamp the 2D dilation
        cloud.extra[key] = rng.uniform(0.01, 0.3, 6).astype(np.float32)
    settings = RenderSettings(backward="autograd", dtype=torch.float64, tile_size=4, block=3, antialias=mode)
    exact = hessian_blocks_reference(cloud, _tiny_cameras(8), settings)
    assert _relative_error(hessian_blocks(cloud, _tiny_cameras(8), views=0, render_settings=settings), exact) < 1e-9


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
        s = hessian_scores(cloud, cams, score=score)
        assert s.shape == (12,) and torch.isfinite(s).all() and (s >= 0).all()
    s = hessian_scores(cloud, cams)
    assert s[7:].min() > 0  # ordinary visible Gaussians score
    assert s[3] == 0        # a transparent Gaussian has no influence on the image


def test_scores_without_cameras_and_edge_cases():
    cloud = _cloud(n=6, seed=3)
    s = hessian_scores(cloud, views=2, resolution=24)
    assert s.shape == (6,) and torch.isfinite(s).all() and (s > 0).all()
    assert hessian_scores(GaussianCloud.empty(), views=1).shape == (0,)
    everything_hidden = _cloud(n=3)
    everything_hidden.opacities[:] = -50
    assert (hessian_scores(everything_hidden, views=1, resolution=16) == 0).all()
    with pytest.raises(ValueError, match="score"):
        hessian_scores(cloud, score="det")


def test_scores_are_deterministic_and_follow_the_rows():
    """The same cloud gives the same scores; shuffled rows give the scores shuffled alike (the
    work is done in a spatial order of its own and put back)."""
    cloud = example_cloud(3000, seed=2)
    a = hessian_scores(cloud, views=2, resolution=48)
    assert torch.equal(a, hessian_scores(cloud, views=2, resolution=48))
    perm = np.random.default_rng(0).permutation(len(cloud))
    b = hessian_scores(cloud.select(perm), views=2, resolution=48)
    torch.testing.assert_close(b, a[perm], rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(compiled.numba_missing() is not None, reason="the compiled kernels need Numba")
def test_compiled_scores_are_the_same_whatever_the_threads():
    """The sweep's chunks add their moments stripe by stripe, each stripe taking the chunks in order:
    every Gaussian's sum is made in one order, so one thread and two give the same scores to the bit
    (on a cloud whose pairs fill several chunks)."""
    cloud = example_cloud(30_000, seed=2)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = hessian_scores(cloud, views=2, resolution=192)
        torch.set_num_threads(2)
        two = hessian_scores(cloud, views=2, resolution=192)
    finally:
        torch.set_num_threads(threads)
    view = default_views(cloud, 2, 192)[0]
    pairs = render(cloud, view, settings=RenderSettings(tile_size=4)).num_pairs
    assert pairs > 2 * (1 << 15)  # several of the sweep's chunks (`compiled`: about 32k pairs each)
    assert torch.equal(one, two) and (one > 0).sum() > 1000


def test_logdet_score_matches_the_eigenvalue_formula():
    h = torch.randn(500, 6, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    blocks = h @ h.transpose(1, 2)
    blocks[:10] = 0.0
    lam = 1e-2 * float(torch.diagonal(blocks, dim1=1, dim2=2).sum(-1).mean()) / 6
    want = torch.log1p(torch.linalg.eigvalsh(blocks / lam).clamp(min=0)).sum(-1)
    torch.testing.assert_close(scores_from_blocks(blocks).double(), want, rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(compiled.numba_missing() is not None, reason="the compiled kernels need Numba")
def test_compiled_log_determinants_are_the_torch_ones():
    h = torch.randn(3000, 6, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    blocks = (h @ h.transpose(1, 2)) * torch.logspace(-6, 3, 3000, dtype=torch.float64)[:, None, None]
    blocks[:10] = 0.0
    rows = blocks[:, _TRIU[0], _TRIU[1]].contiguous()
    rows[10, 3], rows[11, 0], rows[12, 20] = float("nan"), float("inf"), -float("inf")  # read as 0 by both
    torch_scores = scores_from_packed(rows.T, kernels="torch")
    fast = scores_from_packed(rows.T, kernels="auto")
    assert torch.isfinite(fast).all() and (fast >= 0).all() and (fast[:10] == 0).all()
    torch.testing.assert_close(fast, torch_scores, rtol=1e-6, atol=1e-6)
    assert not torch.equal(fast, scores_from_packed(rows.roll(1, 0).T, kernels="auto"))


def test_default_views_frame_an_object():
    cloud = _cloud(n=200, seed=4, spread=5.0)
    cloud.means += np.float32(100.0)
    assert surround_radius(cloud) is None
    for cam in default_views(cloud, views=5, resolution=40):
        uv, z = cam.project(cloud.means)
        assert (z > 0).all()
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= 40) & (uv[:, 1] >= 0) & (uv[:, 1] <= 40)
        assert inside.mean() > 0.95


def _shell(n, radius, seed=0) -> GaussianCloud:
    """A background around the origin: n coarse opaque Gaussians on a sphere."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * radius * (1 + 0.05 * rng.normal(size=(n, 1)))
    size = 0.8 * math.sqrt(4 * math.pi * radius ** 2 / n)
    return GaussianCloud(means=means.astype(np.float32), scales=np.full((n, 3), math.log(size), np.float32),
                         quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.full(n, 3.0, np.float32),
                         sh_dc=rgb_to_dc(rng.uniform(0.2, 0.8, (n, 3))).astype(np.float32),
                         sh_rest=np.zeros((n, 15, 3), np.float32))


def test_unbounded_scene_is_scored_from_inside():
    """An object inside a background shell (a capture of an object with its surroundings): the
    default views stand between the two, and the budget lands on the object's detail, not on the
    shell; views placed around the whole cloud, as for an object, see only the shell's outside
    (the selection is then all shell: the test can fail)."""
    n_obj = 3000
    obj = example_cloud(n_obj, seed=0)  # torus of radius 1 +- 0.35
    scene = GaussianCloud.concat([obj, _shell(6000, 10.0)])
    band = surround_radius(scene)
    assert band is not None and 1.2 < band[0] < 1.6 and 8.0 < band[1] < 10.0
    cams = default_views(scene, views=4, resolution=96)
    for cam in cams:
        assert 1.35 < np.linalg.norm(cam.center - scene.normalization()[0]) < 8.0
    selected = select_budget(hessian_scores(scene, views=4, resolution=96).numpy(), "auto")
    assert len(selected) > 0.3 * n_obj
    assert (selected < n_obj).mean() > 0.8  # the object is a third of the Gaussians

    outside = default_views(obj, views=4, resolution=96)  # framing the torus from outside the shell
    far = [Camera.look_at(c.center * 12.0, (0, 0, 0), width=96, height=96) for c in outside]
    selected_far = select_budget(hessian_scores(scene, far, views=0).numpy(), "auto")
    assert (selected_far < n_obj).mean() < 0.05


def test_scoring_views_pick_spread_cameras_that_see_the_cloud():
    cloud = example_cloud(500, seed=1)
    ring = [Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 1.0), (0, 0, 0), width=1600, height=1200)
            for a in np.linspace(0, 2 * math.pi, 24, endpoint=False)]
    away = [Camera.look_at((4, 0, 1.0), (8, 0, 1.0), width=1600, height=1200)]  # looks away from the cloud
    picked = scoring_views(ring + away, views=4, resolution=120, cloud=cloud)
    assert len(picked) == 4 and all(c.height == 120 and c.width == 160 for c in picked)
    azimuths = sorted(math.degrees(math.atan2(c.center[1], c.center[0])) % 360 for c in picked)
    gaps = np.diff(azimuths + [azimuths[0] + 360])
    assert gaps.min() >= 60  # spread around the ring, not bunched
    assert len(scoring_views(ring, views=0, resolution=2000)) == 24
    assert scoring_views(ring, views=0, resolution=2000)[0].height == 1200  # never scaled up
    with pytest.raises(ValueError, match="sees the cloud"):
        scoring_views(away, cloud=cloud)
