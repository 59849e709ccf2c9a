"""The capture's cameras: COLMAP sparse models (binary and text, written here from the documented
format) and transforms*.json files, read as OpenCV cameras; bad files are refused by name."""

import json
import math
import struct

import numpy as np
import pytest
from PIL import Image

from gvae_core import Camera
from gvae_core.capture import load_cameras, load_capture_images
from gvae_core.datasets import DatasetError
from gvae_core.quaternions import from_rotmat

# COLMAP's camera models (src/colmap/sensor/models.h): name -> (model id, parameters)
MODELS = {"SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5), "OPENCV": (4, 8),
          "OPENCV_FISHEYE": (5, 8)}


def _cameras():
    """Four cameras around the origin, different sizes and focal lengths, off-centre principal points."""
    cams = []
    for k, a in enumerate(np.linspace(0.3, 5.0, 4)):
        c = Camera.look_at((3 * math.cos(a), 3 * math.sin(a), 1.0 + 0.3 * k), (0.1, -0.2, 0.0), width=640 + 16 * k,
                           height=480, fov_x=0.9 + 0.1 * k)
        cams.append(Camera(c.world_to_cam, c.fx, c.fx * (1.0 if k % 2 else 1.02), 317.5 + k, 241.0 - k,
                           c.width, c.height))
    return cams


def _params(cam, model):
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        p = [cam.fx, cam.cx, cam.cy]
    else:
        p = [cam.fx, cam.fy, cam.cx, cam.cy]
    return p + [0.01] * (MODELS[model][1] - len(p))  # distortion coefficients, ignored


def _write_binary(folder, cams, model="PINHOLE", points=2):
    """cameras.bin and images.bin as COLMAP writes them (little endian): cameras: uint64 count,
    then per camera int32 id, int32 model, uint64 width, uint64 height, double params[]; images:
    uint64 count, then per image uint32 id, double qw qx qy qz tx ty tz, int32 camera id, the name
    NUL-terminated, uint64 number of 2D points, then (double x, double y, int64 point id) each."""
    folder.mkdir(parents=True, exist_ok=True)
    model_id, n = MODELS[model]
    data = struct.pack("<Q", len(cams))
    for i, cam in enumerate(cams):
        data += struct.pack(f"<iiQQ{n}d", 10 + i, model_id, cam.width, cam.height, *_params(cam, model))
    (folder / "cameras.bin").write_bytes(data)
    data = struct.pack("<Q", len(cams))
    for i, cam in reversed(list(enumerate(cams))):  # stored out of order: read back by image id
        q = from_rotmat(cam.rotation) * (-1 if i == 2 else 1)  # q and -q are the same rotation
        data += struct.pack("<I4d3di", 1 + i, *q, *cam.translation, 10 + i) + f"img {i}.jpg".encode() + b"\0"
        data += struct.pack("<Q", points) + b"".join(struct.pack("<ddq", 1.5 * j, 2.5, j - 1) for j in range(points))
    (folder / "images.bin").write_bytes(data)
    return folder


def _write_text(folder, cams, model="PINHOLE", empty_points_line=True):
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cams)}"]
    lines += [f"{10 + i} {model} {c.width} {c.height} " + " ".join(repr(p) for p in _params(c, model))
              for i, c in enumerate(cams)]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, cam in enumerate(cams):
        q, t = from_rotmat(cam.rotation), cam.translation
        lines.append(" ".join([str(1 + i)] + [repr(float(v)) for v in (*q, *t)] + [str(10 + i), f"img_{i}.jpg"]))
        if i % 2 or not empty_points_line:
            lines.append("103.5 20.25 -1 104 21 7" if i % 2 else "")
        elif empty_points_line:
            lines.append("")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    return folder


def _same_cameras(got, want, check_intrinsics=True):
    assert len(got) == len(want)
    points = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    for g, w in zip(got, want):
        np.testing.assert_allclose(g.world_to_cam, w.world_to_cam, atol=1e-12)
        assert (g.width, g.height) == (w.width, w.height)
        if check_intrinsics:
            np.testing.assert_allclose([g.fx, g.fy, g.cx, g.cy], [w.fx, w.fy, w.cx, w.cy], rtol=1e-12)
            np.testing.assert_allclose(g.project(points)[0], w.project(points)[0], rtol=1e-9)


@pytest.mark.parametrize("writer", [_write_binary, _write_text])
def test_colmap_models_read_as_the_cameras_they_hold(tmp_path, writer):
    cams = _cameras()
    folder = writer(tmp_path / "sparse" / "0", cams)
    _same_cameras(load_cameras(folder), cams)
    _same_cameras(load_cameras(tmp_path), cams)  # the capture folder: sparse/0 is found
    _same_cameras(load_cameras(folder / f"images{'.bin' if writer is _write_binary else '.txt'}"), cams)


@pytest.mark.parametrize("writer", [_write_binary, _write_text])
def test_colmap_camera_models(tmp_path, writer):
    cams = _cameras()
    simple = [Camera(c.world_to_cam, c.fx, c.fx, c.cx, c.cy, c.width, c.height) for c in cams]
    _same_cameras(load_cameras(writer(tmp_path / "simple", simple, "SIMPLE_PINHOLE")), simple)
    for model, want in (("SIMPLE_RADIAL", simple), ("RADIAL", simple), ("OPENCV", cams)):
        with pytest.warns(UserWarning, match=f"{model} cameras are read as pinholes"):
            _same_cameras(load_cameras(writer(tmp_path / model, cams, model)), want)
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE model, which is not supported"):
        load_cameras(writer(tmp_path / "fisheye", cams, "OPENCV_FISHEYE"))


def test_colmap_text_without_the_empty_points_lines(tmp_path):
    cams = _cameras()
    _same_cameras(load_cameras(_write_text(tmp_path, cams, empty_points_line=False)), cams)


def test_bad_colmap_files_are_refused_by_name(tmp_path):
    cams = _cameras()
    good = _write_binary(tmp_path / "good", cams)
    cases = {}
    for name, cut in (("cameras.bin", 30), ("images.bin", 100), ("images.bin", 8)):
        folder = _write_binary(tmp_path / f"cut_{name}_{cut}", cams)
        data = (good / name).read_bytes()
        (folder / name).write_bytes(data[:cut])
        cases[folder / name] = "truncated"
    folder = _write_binary(tmp_path / "huge_count", cams)
    (folder / "images.bin").write_bytes(struct.pack("<Q", 10 ** 12) + (good / "images.bin").read_bytes()[8:])
    cases[folder / "images.bin"] = "corrupt"
    folder = _write_binary(tmp_path / "trailing", cams)
    (folder / "cameras.bin").write_bytes((good / "cameras.bin").read_bytes() + b"\x00" * 5)
    cases[folder / "cameras.bin"] = "corrupt"
    folder = _write_binary(tmp_path / "bad_model", cams)
    data = bytearray((good / "cameras.bin").read_bytes())
    data[12:16] = struct.pack("<i", 99)
    (folder / "cameras.bin").write_bytes(bytes(data))
    cases[folder / "cameras.bin"] = "unknown model id 99"
    folder = _write_text(tmp_path / "text_bad_params", cams)
    (folder / "cameras.txt").write_text("1 PINHOLE 640 480 500 500 320\n")
    cases[folder / "cameras.txt"] = "4 parameters, got 3"
    folder = _write_text(tmp_path / "text_garbage", cams)
    (folder / "images.txt").write_text("1 0.5 0.5 hello\n")
    cases[folder / "images.txt"] = "line 1: expected IMAGE_ID"
    folder = _write_text(tmp_path / "text_unknown_camera", cams)
    (folder / "cameras.txt").write_text("77 PINHOLE 640 480 500 500 320 240\n")
    cases[folder / "cameras.txt"] = "camera 10, which the cameras file lacks"
    folder = _write_binary(tmp_path / "binary_text", cams)
    (folder / "images.bin").write_bytes(b"\xff" * 3)
    cases[folder / "images.bin"] = "truncated"
    for path, reason in cases.items():
        with pytest.raises(DatasetError, match=reason) as err:
            load_cameras(path.parent)
        assert str(path.parent) in str(err.value), (path, str(err.value))
    with pytest.raises(DatasetError, match="no such file"):
        load_cameras(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no cameras found"):
        load_cameras(tmp_path / "empty")


def test_transforms_json_nerf_synthetic_and_nerfstudio(tmp_path):
    cams = [Camera.look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0), width=64, height=48, fov_x=0.8)
            for a in (0.0, 1.0, 2.0)]
    # NeRF-Synthetic: camera_angle_x, image size from the images (read here from the first)
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": c.to_blender_c2w().tolist()}
              for i, c in enumerate(cams)]
    (tmp_path / "train").mkdir()
    Image.new("RGBA", (64, 48)).save(tmp_path / "train" / "r_0.png")
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    _same_cameras(load_cameras(tmp_path / "transforms_train.json"), cams)
    _same_cameras(load_cameras(tmp_path), cams)  # the only transforms*.json in the folder
    # nerfstudio: intrinsics in pixels, per file or per frame, with distortion (ignored, warned)
    odd = Camera(cams[1].world_to_cam, 70.0, 71.0, 30.5, 25.0, 64, 48)
    frames[1] = {**frames[1], "fl_x": 70.0, "fl_y": 71.0, "cx": 30.5, "cy": 25.0}
    meta = {"fl_x": cams[0].fx, "fl_y": cams[0].fy, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "k1": 0.02,
            "camera_model": "OPENCV", "frames": frames}
    (tmp_path / "ns").mkdir()
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match="distortion is ignored"):
        got = load_cameras(tmp_path / "ns")
    _same_cameras(got, [cams[0], odd, cams[2]])
    plain = {k: v for k, v in meta.items() if k != "k1"}
    for bad, reason in (({"frames": []}, "non-empty 'frames'"),
                        ({**plain, "camera_model": "OPENCV_FISHEYE"}, "not supported"),
                        ({"w": 64, "h": 48, "frames": frames[:1]}, "no focal length"),
                        ({**plain, "frames": [{"transform_matrix": [[1, 2], [3, 4]]}]}, "4x4")):
        path = tmp_path / "bad.json"
        path.write_text(json.dumps(bad))
        with pytest.raises(DatasetError, match=reason) as err:
            load_cameras(path)
        assert "bad.json" in str(err.value)
    path.write_text("{not json")
    with pytest.raises(DatasetError, match="malformed JSON"):
        load_cameras(path)
    (tmp_path / "nosize").mkdir()
    (tmp_path / "nosize" / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames[:1]}))
    with pytest.raises(DatasetError, match="no image size"):
        load_cameras(tmp_path / "nosize")


def test_capture_images_from_colmap_and_nerf_synthetic(tmp_path):
    """A COLMAP capture's images come with their cameras, scaled to the height asked for (never up);
    a missing image is refused by name; a NeRF-Synthetic folder reads its training split."""
    cams = [Camera.look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0), width=40, height=30, fov_x=0.9)
            for a in (0.2, 1.9, 3.7)]
    _write_text(tmp_path / "cap" / "sparse" / "0", cams)
    (tmp_path / "cap" / "images").mkdir()
    rng = np.random.default_rng(0)
    pixels = [rng.integers(0, 255, (30, 40, 3), dtype=np.uint8) for _ in cams]
    for i, px in enumerate(pixels):
        Image.fromarray(px).save(tmp_path / "cap" / "images" / f"img_{i}.jpg", format="PNG")
    views = load_capture_images(tmp_path / "cap")
    assert views.images.shape == (3, 30, 40, 3) and views.names == ["img_0", "img_1", "img_2"]
    np.testing.assert_allclose(views.images[1], pixels[1] / 255.0, atol=1e-6)
    assert (views.alphas == 1).all()
    _same_cameras(views.cameras, cams)
    small = load_capture_images(tmp_path / "cap" / "sparse" / "0", resolution=15)
    assert small.images.shape == (3, 15, 20, 3) and small.cameras[0].fx == pytest.approx(cams[0].fx / 2)
    assert load_capture_images(tmp_path / "cap", resolution=60).images.shape[1] == 30  # never up
    (tmp_path / "cap" / "images" / "img_2.jpg").unlink()
    with pytest.raises(DatasetError, match="img_2.jpg"):
        load_capture_images(tmp_path / "cap")
    nerf = tmp_path / "nerf"
    nerf.mkdir()
    Image.fromarray(pixels[0]).save(nerf / "r_0.png")
    (nerf / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": [
        {"file_path": "r_0", "transform_matrix": cams[0].to_blender_c2w().tolist()}]}))
    got = load_capture_images(nerf, resolution=15)
    assert got.images.shape == (1, 15, 20, 3)
