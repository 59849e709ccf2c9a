"""The SfM points' depths as a training signal (`gvae_core.train.depth`): which points each view
sees (its tracks, or a coarse z-buffer without them), where they fall, and that the loss pulls
content misplaced in depth to the depth the points give."""

import math

import numpy as np
import torch

from gvae_core.camera import Camera, orbit
from gvae_core.capture import SfMPoints
from gvae_core.cloud import GaussianCloud
from gvae_core.datasets import Views
from gvae_core.rendering import render
from gvae_core.train.depth import depth_loss, depth_targets, visible_points


def _views(cams):
    n, h, w = len(cams), cams[0].height, cams[0].width
    return Views(cams, np.zeros((n, h, w, 3), np.float32), np.ones((n, h, w), np.float32),
                 [f"v{i}.jpg" for i in range(n)])


def test_a_view_sees_its_tracks_or_what_a_z_buffer_of_the_points_keeps():
    """With tracks a view gets exactly the points it observes; without, a point hidden right behind
    a nearer one in its cell is dropped and one in a cell of its own is kept; points outside the
    photo, behind the camera or with a large reprojection error give no target."""
    cam = Camera.look_at((0.0, -4.0, 0.0), (0.0, 0.0, 0.0), width=64, height=48, fov_x=1.0)
    ahead = np.zeros(3)  # the target, 4 units ahead
    xyz = np.array([ahead, ahead + [0, 2.0, 0],  # a point, and one behind it in the same pixel
                    ahead + [1.0, 0, 0.5],  # in a cell of its own
                    ahead + [50.0, 0, 0],  # outside the photo
                    cam.center - [0, 3.0, 0],  # behind the camera
                    ahead + [-1.0, 0, -0.5]])  # unreliable
    error = np.array([0.5, 0.5, 0.5, 0.5, 0.5, 9.0])
    untracked = SfMPoints(xyz, np.zeros((6, 3), np.float32), error)
    assert sorted(visible_points(xyz[:5], cam)) == [0, 2]
    got = depth_targets(untracked, _views([cam]))
    np.testing.assert_allclose(sorted(got.depths[0].numpy()), [4.0, 4.0], rtol=1e-5)
    uv, _ = cam.project(xyz[:1])
    assert int(got.pixels[0][0]) in {int(uv[0, 1]) * 64 + int(uv[0, 0])}
    tracked = SfMPoints(xyz, untracked.rgb, error, observers={"v0": np.array([1, 5])})  # (occluded in truth: 1)
    got = depth_targets(tracked, _views([cam]))
    np.testing.assert_allclose(got.depths[0].numpy(), [6.0], rtol=1e-5)
    assert depth_targets(SfMPoints(xyz, untracked.rgb, error, observers={}), _views([cam])) is None


def test_the_depth_loss_moves_a_misplaced_gaussian_to_the_points_depth():
    """A blob drawn 1.5 units in front of where the points of the surface lie: descending the depth
    loss alone (its gradient through the compositing of depth) moves it back among them (within 0.1
    across the ground, which the near-level cameras' depths fix; the height they barely see), and
    its loss falls to a fraction of what it was."""
    cams = orbit(4, 4.0, math.radians(10), width=40, height=40, fov_x=math.radians(50))
    rng = np.random.default_rng(0)
    surface = rng.normal(scale=0.15, size=(200, 3))  # the points, round the origin
    points = SfMPoints(surface, np.zeros((200, 3), np.float32), np.full(200, 0.3))
    targets = depth_targets(points, _views(cams))
    start = cams[0].center * (1.5 / 4.0)  # 1.5 units out from the origin towards camera 0
    means = torch.tensor(start[None], dtype=torch.float32, requires_grad=True)
    fixed = dict(scales=torch.full((1, 3), math.log(0.3)), quats=torch.tensor([[1.0, 0, 0, 0]]),
                 opacities=torch.tensor([4.0]), sh_dc=torch.full((1, 3), 0.5), sh_rest=torch.zeros((1, 0, 3)))
    optimizer = torch.optim.Adam([means], lr=0.02)
    first = None
    for step in range(300):
        v = step % len(cams)
        loss = depth_loss(render(GaussianCloud(means=means, **fixed), cams[v]).depth, targets, v)
        first = float(loss.detach()) if first is None else first
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert np.linalg.norm(means.detach().numpy()[0, :2]) < 0.1
    total = sum(float(depth_loss(render(GaussianCloud(means=means.detach(), **fixed), c).depth, targets, v))
                for v, c in enumerate(cams))
    assert total / len(cams) < 0.3 * first
