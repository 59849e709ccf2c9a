"""Camera: OpenCV convention, Blender conversion, look_at/orbit, scaling, projection."""

import math

import numpy as np
import pytest

from gvae_core import Camera, orbit

# A Blender camera at (0, -4, 0) looking along +y (at the origin), z up: its local axes in world
# coordinates are x -> +x, y (up) -> +z, z (backwards) -> -y.
C2W = np.array([[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]], float)


def test_blender_camera_projects_like_a_pinhole():
    cam = Camera.from_blender_c2w(C2W, 2 * math.atan(0.5), 64, 48)
    assert cam.fx == pytest.approx(64.0) and cam.fy == pytest.approx(64.0)
    assert (cam.cx, cam.cy) == (32.0, 24.0)
    np.testing.assert_allclose(cam.center, [0, -4, 0])
    uv, z = cam.project([[0, 0, 0], [0.5, 0, 0.25], [0, -5, 0]])
    np.testing.assert_allclose(z[:2], [4, 4])
    np.testing.assert_allclose(uv[0], [32, 24])
    np.testing.assert_allclose(uv[1], [32 + 64 * 0.5 / 4, 24 - 64 * 0.25 / 4])  # right and up
    assert z[2] < 0 and np.isnan(uv[2]).all()  # behind the camera
    np.testing.assert_allclose(cam.to_blender_c2w(), C2W, atol=1e-12)


def test_construction_from_lists_and_validation():
    cam = Camera(world_to_cam=np.eye(4)[:3].tolist(), fx=10, fy=12, cx=5, cy=6, width=10, height=12)
    assert cam.world_to_cam.shape == (4, 4) and cam.world_to_cam.dtype == np.float64
    np.testing.assert_allclose(cam.K, [[10, 0, 5], [0, 12, 6], [0, 0, 1]])
    with pytest.raises(ValueError):
        Camera(np.full((4, 4), np.nan), 1, 1, 0, 0, 1, 1)
    with pytest.raises(ValueError):
        Camera(np.eye(4), 0, 1, 0, 0, 1, 1)


def test_look_at_and_orbit():
    cam = Camera.look_at([3, 1, 2], [0.5, 0, 0], width=80, height=60)
    uv, z = cam.project([[0.5, 0, 0], [0.5, 0, 1]])
    np.testing.assert_allclose(uv[0], [40, 30], atol=1e-9)
    assert z[0] == pytest.approx(np.linalg.norm([2.5, 1, 2]))
    assert uv[1][1] < 30  # world up is image up
    np.testing.assert_allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-12)
    cams = orbit(6, radius=2.5, elevation=math.radians(40), target=(1, 0, 0), width=32, height=32)
    assert len(cams) == 6
    for c in cams:
        offset = c.center - [1, 0, 0]
        assert np.linalg.norm(offset) == pytest.approx(2.5)
        assert math.asin(offset[2] / 2.5) == pytest.approx(math.radians(40))
        np.testing.assert_allclose(c.project([[1, 0, 0]])[0][0], [16, 16], atol=1e-9)
    assert len({tuple(np.round(c.center, 6)) for c in cams}) == 6
    # Straight down: still a valid camera.
    down = Camera.look_at([0, 0, 5], [0, 0, 0])
    np.testing.assert_allclose(down.project([[0, 0, 0]])[0][0], [200, 200], atol=1e-9)


def test_scaled_keeps_the_view():
    cam = Camera.from_blender_c2w(C2W, 0.8, 100, 80)
    half = cam.scaled(40)
    assert (half.width, half.height) == (50, 40)
    pts = np.array([[0.3, 0.2, -0.1], [-0.4, 1.0, 0.3]])
    np.testing.assert_allclose(half.project(pts)[0], cam.project(pts)[0] / 2, atol=1e-9)
    np.testing.assert_allclose(half.center, cam.center)
