"""NeRF-Synthetic loading: cameras, images, area downsampling, clear errors."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from gvae_core import DatasetError, load_nerf_synthetic
from gvae_core.datasets import resize_area, resize_area_reference

# Blender camera at (0, -4, 0) looking along +y at the origin, z up (columns: camera x, y, z axes).
FRONT = [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0], [0, 0, 0, 1]]
# Blender camera at (0, 0, 5) looking straight down, image up = world +y.
TOP = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]
ANGLE_X = 2 * math.atan(0.5)  # fx = width


def draw_dot(path, size, row, col, colour=(255, 0, 0)):
    """An RGBA PNG, transparent except one opaque pixel."""
    h, w = size
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[row, col] = (*colour, 255)
    Image.fromarray(rgba, "RGBA").save(path)


def make_dataset(root, frames, size=(48, 64), split="train"):
    (root / split).mkdir(parents=True, exist_ok=True)
    meta = {"camera_angle_x": ANGLE_X, "frames": []}
    for i, (c2w, row, col) in enumerate(frames):
        draw_dot(root / split / f"r_{i}.png", size, row, col)
        meta["frames"].append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w})
    (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def test_known_point_projects_to_the_pixel_it_was_drawn_at(tmp_path):
    h, w = 48, 64
    f = w  # from ANGLE_X
    x, y, z = point = np.array([0.53, 0.3, 0.41])
    # Pinhole projection worked out by hand for each camera: FRONT sees depth 4 + y, image right
    # = +x, image up = +z; TOP sees depth 5 - z, image right = +x, image up = +y.
    front = (32 + f * x / (4 + y), 24 - f * z / (4 + y))  # (column, row) = (39.89, 17.90)
    top = (32 + f * x / (5 - z), 24 - f * y / (5 - z))    # (39.39, 19.82)
    frames = [(FRONT, int(front[1]), int(front[0])), (TOP, int(top[1]), int(top[0]))]
    views = load_nerf_synthetic(make_dataset(tmp_path, frames, (h, w)))
    assert len(views) == 2 and views.names == ["r_0", "r_1"]
    assert views.images.shape == (2, h, w, 3) and views.alphas.shape == (2, h, w)
    assert views.images.dtype == np.float32 and views.alphas.dtype == np.float32
    for cam, alpha, image in zip(views.cameras, views.alphas, views.images):
        (u, v), = cam.project(point[None])[0]
        row, col = np.unravel_index(np.argmax(alpha), alpha.shape)
        assert (int(v), int(u)) == (row, col)
        assert alpha.sum() == 1.0
        np.testing.assert_array_equal(image[row, col], [1, 0, 0])
    np.testing.assert_allclose(views.cameras[0].center, [0, -4, 0], atol=1e-12)
    np.testing.assert_allclose(views.cameras[1].center, [0, 0, 5], atol=1e-12)
    # Half resolution: the point falls in the pixel whose area holds the dot.
    half = load_nerf_synthetic(tmp_path, resolution=24)
    assert half.images.shape == (2, 24, 32, 3)
    (u, v), = half.cameras[0].project(point[None])[0]
    assert (u, v) == pytest.approx((front[0] / 2, front[1] / 2))
    assert half.alphas[0, int(v), int(u)] == pytest.approx(0.25)
    assert half.alphas[0].sum() == pytest.approx(0.25)
    np.testing.assert_allclose(half.images[0, int(v), int(u)], [1, 0, 0], atol=1e-6)  # not darkened


def test_composite(tmp_path):
    views = load_nerf_synthetic(make_dataset(tmp_path, [(FRONT, 1, 2)], (4, 5)))
    out = views.composite((0.0, 1.0, 0.0))
    assert out.shape == (1, 4, 5, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0, 1, 2], [1, 0, 0])
    np.testing.assert_array_equal(out[0, 0, 0], [0, 1, 0])
    expected = views.images * views.alphas[..., None] + np.array([0, 1, 0]) * (1 - views.alphas[..., None])
    np.testing.assert_allclose(out, expected)


@pytest.mark.parametrize("shape,out", [((7, 5, 4), (3, 2)), ((10, 10, 1), (4, 4)), ((3, 4, 2), (5, 6)),
                                       ((9, 6, 3), (9, 2))])
def test_area_resize_matches_the_reference(shape, out):
    img = np.random.default_rng(0).random(shape)
    fast = resize_area(img, *out)
    np.testing.assert_allclose(fast, resize_area_reference(img, *out), atol=1e-6)
    # Area averaging keeps the mean.
    np.testing.assert_allclose(fast.mean((0, 1)), img.mean((0, 1)), atol=1e-6)


def test_integer_factor_is_a_block_mean():
    img = np.random.default_rng(1).random((8, 12, 3))
    blocks = img.reshape(4, 2, 4, 3, 3).mean((1, 3))
    np.testing.assert_allclose(resize_area(img, 4, 4), blocks, atol=1e-6)


def test_downsampling_is_premultiplied(tmp_path):
    (tmp_path / "train").mkdir()
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = (0, 0, 255, 255)     # opaque blue
    rgba[0, 1] = (255, 0, 0, 0)       # fully transparent red: must not tint the result
    rgba[1, 0] = (0, 0, 255, 255)
    rgba[1, 1] = (255, 255, 0, 0)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "train" / "a.png")
    meta = {"camera_angle_x": 0.7, "frames": [{"file_path": "train/a.png", "transform_matrix": FRONT}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    views = load_nerf_synthetic(tmp_path, resolution=1)
    assert views.alphas[0, 0, 0] == pytest.approx(0.5)
    np.testing.assert_allclose(views.images[0, 0, 0], [0, 0, 1], atol=1e-6)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match="transforms_train.json: missing"):
        load_nerf_synthetic(tmp_path)
    meta = tmp_path / "transforms_test.json"
    meta.write_text("{not json")
    with pytest.raises(DatasetError, match="transforms_test.json: malformed JSON"):
        load_nerf_synthetic(tmp_path, "test")
    meta.write_text(json.dumps({"frames": [{"file_path": "x", "transform_matrix": FRONT}]}))
    with pytest.raises(DatasetError, match="camera_angle_x"):
        load_nerf_synthetic(tmp_path, "test")
    meta.write_text(json.dumps({"camera_angle_x": 0.7, "frames": [{"file_path": "test/x"}]}))
    with pytest.raises(DatasetError, match="frame 0"):
        load_nerf_synthetic(tmp_path, "test")
    meta.write_text(json.dumps({"camera_angle_x": 0.7,
                                "frames": [{"file_path": "./test/r_9", "transform_matrix": FRONT}]}))
    with pytest.raises(DatasetError, match=r"test/r_9\.png: image not found"):
        load_nerf_synthetic(tmp_path, "test")
    (tmp_path / "test").mkdir()
    (tmp_path / "test" / "r_9.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"r_9\.png: cannot read image"):
        load_nerf_synthetic(tmp_path, "test")
    make_dataset(tmp_path / "sizes", [(FRONT, 0, 0), (TOP, 0, 0)], (4, 4))
    draw_dot(tmp_path / "sizes" / "train" / "r_1.png", (5, 4), 0, 0)
    with pytest.raises(DatasetError, match="r_1.png: size 4x5 differs"):
        load_nerf_synthetic(tmp_path / "sizes")
