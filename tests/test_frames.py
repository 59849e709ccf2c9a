"""Frames: redrawing a view after some Gaussians changed draws what `render` draws of the changed
cloud; the Hessian's frames are the views it composited."""

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import DILATION_KEY, with_dilation_3d
from gvae_core.hessian import hessian_scores, scoring_settings
from gvae_core.rendering import RenderSettings, render
from gvae_core.rendering.frames import make_frame, redraw

WHITE = (1.0, 1.0, 1.0)


def _cloud(n: int, seed: int, degree: int = 1) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 3: 15}[degree]
    scales = rng.uniform(-3.5, -1.5, (n, 3))
    scales[: n // 8] += 1.5
    return GaussianCloud(means=rng.normal(0, 0.5, (n, 3)).astype(np.float32), scales=scales.astype(np.float32),
                         quats=rng.normal(size=(n, 4)).astype(np.float32),
                         opacities=rng.normal(1.0, 2.0, n).astype(np.float32),
                         sh_dc=rng.normal(0, 1, (n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.3, (n, k, 3)).astype(np.float32))


def _camera(w=37, h=29) -> Camera:
    return Camera.look_at((3.0, 1.0, 1.5), (0, 0, 0), width=w, height=h, fov_x=math.radians(45))


def _changed(cloud: GaussianCloud, seed: int) -> tuple[GaussianCloud, np.ndarray]:
    """`cloud` with some rows moved, recoloured, made faint or put behind the camera, and new
    rows appended; and the rows that differ."""
    rng = np.random.default_rng(seed)
    n = len(cloud)
    after = cloud.select(np.arange(n))
    moved = rng.choice(n, n // 5, replace=False)
    after.means[moved] += rng.normal(0, 0.1, (len(moved), 3)).astype(np.float32)
    after.sh_dc[moved[:5]] = 3.0
    after.opacities[moved[5:8]] = -20.0                     # no longer drawn
    after.means[moved[8]] = np.float32([3.0, 1.0, 1.5])     # at the camera's centre
    kids = cloud.select(rng.choice(n, n // 4))
    kids.means += rng.normal(0, 0.05, kids.means.shape).astype(np.float32)
    return GaussianCloud.concat([after, kids]), np.concatenate([moved, np.arange(n, n + len(kids))])


@pytest.mark.parametrize("tile_size", [4, 8])
def test_redraw_draws_what_render_draws_of_the_changed_cloud(tile_size):
    cloud = _cloud(300, seed=1)
    cam = _camera()
    s = RenderSettings(tile_size=tile_size)
    frame = make_frame(cloud, cam, s)
    assert torch.equal(frame.image(WHITE), render(cloud, cam, background=WHITE, settings=s).image)
    after, rows = _changed(cloud, seed=2)
    want = render(after, cam, background=WHITE, settings=s).image
    assert (frame.image(WHITE) - want).abs().max() > 0.05  # the change shows
    again = redraw(frame, after, rows)
    assert (again.image(WHITE) - want).abs().max() < 1e-5
    # a redraw of a redraw, and rows given that did not change (drawn again, the same)
    later, more = _changed(after, seed=3)
    both = redraw(again, later, np.concatenate([more, rows[:10]]))
    assert (both.image(WHITE) - render(later, cam, background=WHITE, settings=s).image).abs().max() < 1e-5
    # nothing changed: the same picture; every row changed: the changed cloud's
    assert (redraw(frame, cloud, []).image(WHITE) - frame.image(WHITE)).abs().max() == 0.0
    assert torch.equal(redraw(frame, after, np.arange(len(after))).image(WHITE), want)


def test_redraw_uses_the_changed_clouds_anti_aliasing_and_refuses_unknown_rows():
    cloud = with_dilation_3d(_cloud(200, seed=4), [_camera(60, 48)])
    assert DILATION_KEY in cloud.extra
    cam = _camera()
    s = RenderSettings(tile_size=4, antialias="matched")
    after, rows = _changed(cloud, seed=5)
    after.extra[DILATION_KEY][rows[:20]] *= 3.0
    got = redraw(make_frame(cloud, cam, s), after, rows).image(WHITE)
    assert (got - render(after, cam, background=WHITE, settings=s).image).abs().max() < 1e-5
    with pytest.raises(ValueError, match="rows"):
        redraw(make_frame(cloud, cam, s), after, [len(after)])


def test_redraw_of_an_empty_view():
    cloud = _cloud(60, seed=6)
    away = Camera.look_at((3.0, 1.0, 1.5), (6.0, 2.0, 3.0), width=16, height=12)  # looks away from the cloud
    frame = make_frame(cloud, away)
    assert frame.binning.num_pairs == 0 and torch.equal(frame.image(WHITE), torch.ones(12, 16, 3))
    after, rows = _changed(cloud, seed=7)
    assert torch.equal(redraw(frame, after, rows).image(WHITE), render(after, away, background=WHITE).image)


def test_the_hessians_frames_are_the_views_it_composited():
    cloud = _cloud(400, seed=8, degree=3)
    frames: list = []
    scores = hessian_scores(cloud, views=3, resolution=24, frames=frames)
    assert len(frames) == 3 and np.isfinite(scores.numpy()).all()
    s = scoring_settings()
    after, rows = _changed(cloud, seed=9)
    for frame in frames:  # table rows in the Hessian's (Morton) order, which the frame maps back
        assert frame.settings == s and (frame.camera.height, frame.camera.width) == (24, 24)
        want = render(cloud, frame.camera, background=WHITE, settings=s).image
        assert (frame.image(WHITE) - want).abs().max() < 1e-5
        got = redraw(frame, after, rows).image(WHITE)
        assert (got - render(after, frame.camera, background=WHITE, settings=s).image).abs().max() < 1e-5
