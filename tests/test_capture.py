"""Captures: COLMAP sparse models (binary and text, written here from the documented format),
transforms*.json files and NeRF-Synthetic folders, read as OpenCV pinhole cameras with their lens
distortion undone (to within 0.05 px), their images, held-out views and SfM points; missing images
counted; bad files refused by name."""

import json
import math
import struct

import numpy as np
import pytest
from PIL import Image

from gvae_core import Camera
from gvae_core.capture import Lens, load_cameras, load_capture_images, read_capture, undistorted_camera
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


def _params(cam, model, distortion=0.01):
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        p = [cam.fx, cam.cx, cam.cy]
    else:
        p = [cam.fx, cam.fy, cam.cx, cam.cy]
    return p + [distortion] * (MODELS[model][1] - len(p))  # distortion coefficients


#: The lens each model's parameters above describe (COLMAP's parameter order).
LENSES = {"SIMPLE_PINHOLE": Lens(), "PINHOLE": Lens(), "SIMPLE_RADIAL": Lens(k1=0.01), "RADIAL": Lens(k1=0.01, k2=0.01),
          "OPENCV": Lens(k1=0.01, k2=0.01, p1=0.01, p2=0.01)}


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


def _write_text(folder, cams, model="PINHOLE", empty_points_line=True, params=None):
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cams)}"]
    lines += [f"{10 + i} {model} {c.width} {c.height} " + " ".join(repr(p) for p in (params or _params)(c, model))
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
    """Pinhole models read as they are; radial and OpenCV ones as the pinhole COLMAP's undistorter
    makes of them (never silently as their pinhole part); fisheye refused with how to undistort."""
    cams = _cameras()
    simple = [Camera(c.world_to_cam, c.fx, c.fx, c.cx, c.cy, c.width, c.height) for c in cams]
    _same_cameras(load_cameras(writer(tmp_path / "simple", simple, "SIMPLE_PINHOLE")), simple)
    for model, part in (("SIMPLE_RADIAL", simple), ("RADIAL", simple), ("OPENCV", cams)):
        capture = read_capture(writer(tmp_path / model, cams, model), images=False)
        assert capture.lenses == [LENSES[model]] * len(cams) and capture.distorted == len(cams)
        _same_cameras(capture.photo_cameras, part)
        want = [undistorted_camera(c, LENSES[model]) for c in part]
        _same_cameras(load_cameras(tmp_path / model), want)
        assert all(w.fx > 1.001 * c.fx for w, c in zip(want, part))  # pincushion: the view narrows
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE model, which is not supported.*image_undistorter"):
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
    # nerfstudio: intrinsics in pixels, per file or per frame, with distortion (undone: the pinhole
    # COLMAP's undistorter makes of each frame)
    odd = Camera(cams[1].world_to_cam, 70.0, 71.0, 30.5, 25.0, 64, 48)
    frames[1] = {**frames[1], "fl_x": 70.0, "fl_y": 71.0, "cx": 30.5, "cy": 25.0, "k2": -0.01}
    meta = {"fl_x": cams[0].fx, "fl_y": cams[0].fy, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "k1": 0.02,
            "camera_model": "OPENCV", "frames": frames}
    (tmp_path / "ns").mkdir()
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    capture = read_capture(tmp_path / "ns", images=False)
    assert capture.lenses == [Lens(k1=0.02), Lens(k1=0.02, k2=-0.01), Lens(k1=0.02)]
    _same_cameras(capture.photo_cameras, [cams[0], odd, cams[2]])
    _same_cameras(load_cameras(tmp_path / "ns"), [undistorted_camera(c, lens) for c, lens in
                                                  zip([cams[0], odd, cams[2]], capture.lenses)])
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
    assert read_capture(tmp_path / "cap").points is None  # no points3D file
    np.testing.assert_allclose(views.images[1], pixels[1] / 255.0, atol=1e-6)
    assert (views.alphas == 1).all()
    _same_cameras(views.cameras, cams)
    small = load_capture_images(tmp_path / "cap" / "sparse" / "0", resolution=15)
    assert small.images.shape == (3, 15, 20, 3) and small.cameras[0].fx == pytest.approx(cams[0].fx / 2)
    assert load_capture_images(tmp_path / "cap", resolution=60).images.shape[1] == 30  # never up
    (tmp_path / "cap" / "images" / "img_2.jpg").unlink()
    with pytest.warns(UserWarning, match=r"1 of 3 frames skipped: image missing \(.*img_2.jpg"):
        capture = read_capture(tmp_path / "cap")
    assert capture.skipped == ["img_2.jpg"] and capture.names == ["img_0", "img_1"]
    assert "1 frame(s) skipped" in capture.summary()
    for name in ("img_0.jpg", "img_1.jpg"):
        (tmp_path / "cap" / "images" / name).unlink()
    with pytest.raises(DatasetError, match="img_0.jpg: image not found; none of the 3 frames"):
        read_capture(tmp_path / "cap")
    nerf = tmp_path / "nerf"
    nerf.mkdir()
    Image.fromarray(pixels[0]).save(nerf / "r_0.png")
    (nerf / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": [
        {"file_path": "r_0", "transform_matrix": cams[0].to_blender_c2w().tolist()}]}))
    got = load_capture_images(nerf, resolution=15)
    assert got.images.shape == (1, 15, 20, 3)


# ------------------------------------------------------------------ real captures: lenses, points, splits

def _dot_photo(cam, lens, dots, sigma=1.6):
    """The photo `cam` takes through `lens` of small round dots at world points `dots` (float RGB):
    each photo pixel shows what its undistorted ray sees, a Gaussian blob of `sigma` pixels of the
    pinhole around each dot's projection."""
    v, u = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    x, y = lens.undistort((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
    px, py = cam.fx * x + cam.cx, cam.fy * y + cam.cy
    image = np.zeros((cam.height, cam.width))
    uv, _ = cam.project(dots)
    for du, dv in uv:
        image += np.exp(-((px - du) ** 2 + (py - dv) ** 2) / (2 * sigma * sigma))
    return np.repeat(np.clip(image, 0, 1)[..., None], 3, 2)


def _centroids(image, guesses, radius=5):
    """Intensity-weighted centres (x, y) of the blobs of `image` nearest `guesses` (pixel centres +0.5)."""
    out = []
    h, w = image.shape[:2]
    for gx, gy in guesses:
        c0, r0 = int(gx), int(gy)
        rows = slice(max(r0 - radius, 0), min(r0 + radius + 1, h))
        cols = slice(max(c0 - radius, 0), min(c0 + radius + 1, w))
        patch = image[rows, cols, 0].astype(np.float64)
        yy, xx = np.mgrid[rows, cols] + 0.5
        out.append((float((patch * xx).sum() / patch.sum()), float((patch * yy).sum() / patch.sum())))
    return np.array(out)


def _dots_in_view(cam, margin=14, spacing=26, seed=0):
    """World points at random depths whose projections lie on a grid of `spacing` px inside `cam`'s
    image, `margin` px from its border (blobs far enough apart to be measured one by one)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(margin, cam.width - margin + 1, spacing), np.arange(margin, cam.height - margin + 1,
                                                                                      spacing))
    uv = np.stack([u.ravel(), v.ravel()], 1) + rng.uniform(-3, 3, (u.size, 2))
    depth = rng.uniform(2.5, 3.5, len(uv))
    local = np.stack([(uv[:, 0] - cam.cx) / cam.fx * depth, (uv[:, 1] - cam.cy) / cam.fy * depth, depth], 1)
    return (local - cam.translation) @ cam.rotation


@pytest.mark.parametrize("kind", ["colmap_opencv", "colmap_radial", "transforms"])
def test_distortion_is_undone_to_a_twentieth_of_a_pixel(tmp_path, kind):
    """Photos taken through a distorting lens (up to several pixels at the corners), written as a
    COLMAP OPENCV / RADIAL model or a nerfstudio transforms.json: read back, each dot of the photo
    lies where the undistorted pinhole camera projects its world point, within 0.05 px."""
    base = Camera.look_at((3.0, 0.5, 1.0), (0.0, 0.0, 0.2), width=160, height=120, fov_x=1.0)
    cams = [Camera(base.world_to_cam, base.fx, base.fx * 1.01, 81.3, 58.6, 160, 120)]
    cams.append(Camera(Camera.look_at((-2.5, 1.5, 1.2), (0, 0, 0), width=160, height=120).world_to_cam,
                       *cams[0].K[[0, 1, 0, 1], [0, 1, 2, 2]], 160, 120))
    if kind == "colmap_opencv":
        lens = Lens(k1=-0.08, k2=0.03, p1=0.004, p2=-0.003)
        params = lambda c, model: [c.fx, c.fy, c.cx, c.cy, lens.k1, lens.k2, lens.p1, lens.p2]  # noqa: E731
    elif kind == "colmap_radial":
        cams = [Camera(c.world_to_cam, c.fx, c.fx, c.cx, c.cy, 160, 120) for c in cams]
        lens = Lens(k1=0.06, k2=-0.02)
        params = lambda c, model: [c.fx, c.cx, c.cy, lens.k1, lens.k2]  # noqa: E731
    else:
        lens = Lens(k1=-0.05, k2=0.01, p1=0.002, p2=0.001)
    folder = tmp_path / "cap"
    (folder / "images").mkdir(parents=True)
    dots = [_dots_in_view(c, seed=i) for i, c in enumerate(cams)]
    for i, (c, d) in enumerate(zip(cams, dots)):
        Image.fromarray(np.round(_dot_photo(c, lens, d) * 255).astype(np.uint8)).save(folder / "images" / f"p{i}.png")
    if kind == "transforms":
        frames = [{"file_path": f"images/p{i}.png", "transform_matrix": c.to_blender_c2w().tolist(), "fl_x": c.fx,
                   "fl_y": c.fy, "cx": c.cx, "cy": c.cy} for i, c in enumerate(cams)]
        (folder / "transforms.json").write_text(json.dumps({"w": 160, "h": 120, "k1": lens.k1, "k2": lens.k2,
                                                            "p1": lens.p1, "p2": lens.p2, "frames": frames}))
    else:
        _write_text(folder / "sparse" / "0", cams, "OPENCV" if kind == "colmap_opencv" else "RADIAL", params=params)
        for i in range(len(cams)):
            (folder / "images" / f"p{i}.png").rename(folder / "images" / f"img_{i}.jpg")
    capture = read_capture(folder)
    assert capture.distorted == len(cams)
    views = capture.load()
    for cam, image, photo, lens_read, d in zip(views.cameras, views.images, capture.photo_cameras, capture.lenses,
                                               dots):
        want, _ = cam.project(d)
        assert np.linalg.norm(_centroids(image, want) - want, axis=1).max() < 0.05, kind
        # what reading the photo as its pinhole would have got wrong: pixels, not a twentieth of one
        pin, _ = photo.project(d)
        x, y = lens_read.distort((pin[:, 0] - photo.cx) / photo.fx, (pin[:, 1] - photo.cy) / photo.fy)
        assert np.abs(np.stack([photo.fx * x + photo.cx, photo.fy * y + photo.cy], 1) - pin).max() > 0.5


def _write_points(folder, xyz, rgb, err, binary):
    """points3D as COLMAP writes it: text (ID X Y Z R G B ERROR TRACK[]) or binary (uint64 count, then
    per point uint64 id, double xyz, uint8 rgb, double error, uint64 track length, (uint32 image id,
    uint32 feature)s). Each point's track: image 1 and image 2 (even points) or 3 (odd ones)."""
    if binary:
        data = struct.pack("<Q", len(xyz))
        for i, (p, c, e) in enumerate(zip(xyz, rgb, err)):
            data += struct.pack("<Q3d3BdQ", 100 + i, *p, *c, e, 2) + struct.pack("<4I", 1, 0, 2 + i % 2, 5)
        (folder / "points3D.bin").write_bytes(data)
    else:
        lines = ["# 3D point list with one line of data per point:"]
        lines += [f"{100 + i} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} {e!r} 1 0 {2 + i % 2} 5"
                  for i, (p, c, e) in enumerate(zip(xyz, rgb, err))]
        (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("writer", [_write_binary, _write_text])
def test_sfm_points_held_out_views_and_scaled_copies(tmp_path, writer):
    """A COLMAP capture's SfM points read exactly, with the photos that observe each; --test-every
    holds out every n-th image by name; images stored at a fraction of the model's size are read
    with the cameras scaled to them."""
    cams = _cameras()[:1] * 9  # nine frames of one camera size
    model = writer(tmp_path / "sparse" / "0", cams)
    rng = np.random.default_rng(1)
    xyz, rgb, err = rng.normal(size=(7, 3)), rng.integers(0, 256, (7, 3)), rng.uniform(0.1, 2, 7)
    _write_points(model, xyz, rgb, err, writer is _write_binary)
    (tmp_path / "images").mkdir()
    names = [f"img {i}.jpg" if writer is _write_binary else f"img_{i}.jpg" for i in range(len(cams))]
    for name, cam in zip(names, cams):  # stored at half the model's size
        Image.new("RGB", (cam.width // 2, cam.height // 2), (10, 20, 30)).save(tmp_path / "images" / name, "PNG")
    capture = read_capture(tmp_path, test_every=4)
    np.testing.assert_array_equal(capture.points.xyz, xyz)
    np.testing.assert_allclose(capture.points.rgb, rgb / 255.0, atol=1e-7)
    np.testing.assert_array_equal(capture.points.error, err)
    # the tracks: which photos observe each point (image id 1 + i is names[i])
    np.testing.assert_array_equal(capture.points.observed_by(names[0]), np.arange(7))
    np.testing.assert_array_equal(capture.points.observed_by(names[1]), [0, 2, 4, 6])
    np.testing.assert_array_equal(capture.points.observed_by(names[2]), [1, 3, 5])
    assert len(capture.points.observed_by(names[3])) == 0
    order = sorted(range(len(names)), key=lambda i: names[i])
    assert [capture.splits[i] for i in order] == ["test", "train", "train", "train"] * 2 + ["test"]
    assert len(load_cameras(tmp_path, test_every=4)) == 6
    views = capture.load("test")
    assert len(views) == 3 and views.images.shape[1:3] == (240, cams[0].width // 2)
    half = views.cameras[0]
    assert (half.fx, half.cx) == pytest.approx((cams[0].fx / 2, cams[0].cx / 2))


def test_bad_captures_are_refused_by_name(tmp_path):
    """A model with no images, an image that is not (a scaled copy of) its camera's size, an unknown
    camera model, a hold-out that leaves nothing to train on: a clear error naming the file."""
    cams = _cameras()[:2]
    folder = _write_text(tmp_path / "empty", cams)
    (folder / "images.txt").write_text("# no images\n")
    with pytest.raises(DatasetError, match=r"images.txt: no images"):
        read_capture(folder)
    folder = _write_text(tmp_path / "sized" / "sparse" / "0", cams)
    (tmp_path / "sized" / "images").mkdir()
    Image.new("RGB", (cams[0].width, cams[0].height)).save(tmp_path / "sized" / "images" / "img_0.jpg", "PNG")
    Image.new("RGB", (cams[1].width, cams[1].height - 40)).save(tmp_path / "sized" / "images" / "img_1.jpg", "PNG")
    with pytest.raises(DatasetError, match=r"img_1.jpg: size \d+x440 differs from the \d+x480 of the model .*cameras"):
        read_capture(tmp_path / "sized")
    folder = _write_text(tmp_path / "unknown", cams)
    (folder / "cameras.txt").write_text("10 EQUIDISTANT 640 480 500 320 240\n")
    with pytest.raises(DatasetError, match=r"cameras.txt: line 1: unknown camera model 'EQUIDISTANT'"):
        read_capture(folder, images=False)
    with pytest.raises(ValueError, match="leaves none to train on"):
        read_capture(_write_text(tmp_path / "two", cams[:1]), test_every=2, images=False)


def test_reference_3dgs_cameras_json_reads_as_the_cameras_it_holds(tmp_path):
    """The reference 3DGS's `cameras.json` (camera-to-world rotation and centre, focal lengths,
    principal point at the centre): read as a file or as its model folder, held out by name like
    any capture; it holds no photos, and asking for them or giving a broken file says so by name."""
    from gvae_core.capture.gs_cameras import write_gs_cameras  # noqa: PLC0415

    cams = [Camera(c.world_to_cam, c.fx, c.fy, c.width / 2.0, c.height / 2.0, c.width, c.height) for c in _cameras()]
    model = tmp_path / "model"
    model.mkdir()
    write_gs_cameras(cams, [f"img_{i}" for i in range(4)], model / "cameras.json")
    entry = json.loads((model / "cameras.json").read_text())[1]  # the reference's fields, its conventions
    assert set(entry) == {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
    np.testing.assert_allclose(entry["position"], cams[1].center, atol=1e-12)
    np.testing.assert_allclose(np.asarray(entry["rotation"]) @ [0, 0, 1], cams[1].rotation[2], atol=1e-12)  # z forward
    for path in (model / "cameras.json", model):
        capture = read_capture(path, images=False)
        assert capture.kind == "3dgs-cameras" and capture.points is None
        _same_cameras(capture.cameras, cams)
    assert [c.width for c in load_cameras(model, test_every=2)] == [cams[1].width, cams[3].width]
    with pytest.raises(DatasetError, match=r"cameras.json: the reference 3DGS's cameras.json holds cameras without "
                                           r"photos"):
        read_capture(model)
    broken = json.loads((model / "cameras.json").read_text())
    del broken[2]["fy"]
    (tmp_path / "b.json").write_text(json.dumps(broken))
    with pytest.raises(DatasetError, match=r"b.json: camera 2: missing fy"):
        read_capture(tmp_path / "b.json", images=False)
    broken[2]["fy"], broken[3]["rotation"] = 500.0, [[2, 0, 0], [0, 1, 0], [0, 0, 1]]
    (tmp_path / "b.json").write_text(json.dumps(broken))
    with pytest.raises(DatasetError, match=r"b.json: camera 3: rotation is not a rotation matrix"):
        read_capture(tmp_path / "b.json", images=False)


def test_the_cameras_a_splats_training_left_beside_it_are_found(tmp_path):
    """`cameras_beside`: the reference 3DGS's MODEL/cameras.json two folders above its
    point_cloud.ply, a `gvae train` run's capture (its training cameras, held out as the run did);
    nothing for a lone file; a run whose capture is gone is passed over with why."""
    from gvae_core.capture import cameras_beside  # noqa: PLC0415
    from gvae_core.capture.gs_cameras import write_gs_cameras  # noqa: PLC0415

    cams = [Camera(c.world_to_cam, c.fx, c.fy, c.width / 2.0, c.height / 2.0, c.width, c.height) for c in _cameras()]
    model = tmp_path / "model"
    (model / "point_cloud" / "iteration_7000").mkdir(parents=True)
    write_gs_cameras(cams, [f"img_{i}" for i in range(4)], model / "cameras.json")
    found, passed = cameras_beside(model / "point_cloud" / "iteration_7000" / "point_cloud.ply")
    assert passed == [] and found.source == model / "cameras.json" and "4 training cameras" in found.how
    _same_cameras(found.cameras, cams)
    capture = _write_text(tmp_path / "capture" / "sparse" / "0", cams)
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"data": str(capture), "config": {"test_every": 2}}))
    found, passed = cameras_beside(run / "stage_2.ply")
    assert passed == [] and "1 in 2 held out" in found.how
    _same_cameras(found.cameras, [cams[1], cams[3]])
    (run / "run.json").write_text(json.dumps({"data": str(tmp_path / "gone"), "config": {}}))
    found, passed = cameras_beside(run / "stage_2.ply")
    assert found is None and len(passed) == 1 and "gone cannot be read" in passed[0]
    assert cameras_beside(tmp_path / "lone" / "splat.ply") == (None, [])
