"""COLMAP sparse models, binary (`cameras.bin`, `images.bin`, `points3D.bin`) or text (`.txt`).

Images: world-to-camera rotation (quaternion w, x, y, z) and translation, OpenCV convention
already, pixel centres at +0.5 like ours, in image-id order. Cameras: SIMPLE_PINHOLE and PINHOLE
as they are; SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV as their pinhole part with their
`Lens` (undone when the images are read, `capture.lens`); fisheye and other models are refused
with how to undistort the capture first. Points: position, colour, reprojection error and which
images observe each (its track). Files that cannot be read raise `DatasetError` naming the file and the problem.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..datasets import DatasetError
from .lens import Lens

__all__ = ["COLMAP_MODELS", "ColmapModel", "SfMPoints", "read_colmap", "read_colmap_cameras", "read_colmap_points",
           "colmap_files", "UNDISTORT_HINT"]

#: COLMAP camera models: id -> (name, number of parameters).
COLMAP_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
                 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
_MODEL_IDS = {name: (i, count) for i, (name, count) in COLMAP_MODELS.items()}
#: How to turn a capture this project cannot undistort into one it reads as it is.
UNDISTORT_HINT = ("undistort the capture first (colmap image_undistorter --image_path IMAGES --input_path SPARSE "
                  "--output_path OUT, then use OUT), as the reference 3DGS's convert.py does")


@dataclass
class SfMPoints:
    """A capture's structure-from-motion points: positions (M, 3) in its world frame, colours (M, 3)
    in [0, 1] and mean reprojection errors in pixels (M,; NaN where unknown); `source` says where
    they came from (the capture's SfM, or triangulated with its poses)."""

    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    source: str = "SfM points"
    observers: dict[str, np.ndarray] | None = None  # image name stem -> the points it observes (tracks)

    def __len__(self) -> int:
        return len(self.xyz)

    def observed_by(self, name: str) -> np.ndarray | None:
        """Indices of the points the image `name` observes (matched features of its own: visible
        there), or None where the tracks are unknown."""
        if self.observers is None:
            return None
        return self.observers.get(Path(name).stem, np.zeros(0, np.int64))


@dataclass
class ColmapModel:
    """What a sparse model holds, per image in image-id order: the pinhole part of its camera (at the
    model's image size, which a model always states), its lens distortion, its file name; and the SfM
    points (None without a points3D file)."""

    cameras: list[Camera]
    lenses: list[Lens]
    names: list[str]
    points: SfMPoints | None
    images_file: Path
    stated_size: bool = True


def colmap_files(folder: Path) -> tuple[Path, Path] | None:
    """(cameras, images) files of a sparse model in `folder`, binary first, else None."""
    for ext in (".bin", ".txt"):
        c, i = folder / f"cameras{ext}", folder / f"images{ext}"
        if c.is_file() and i.is_file():
            return c, i
    return None


def read_colmap(cameras_file: Path, images_file: Path) -> ColmapModel:
    """A sparse model from its cameras and images files, with points3D beside them when present."""
    intrinsics = read_colmap_cameras(cameras_file)
    poses, names, cam_ids, image_ids = _read_images(images_file)
    cams, lenses = [], []
    for (what, q, t), cam_id in zip(poses, cam_ids):
        fx, fy, cx, cy, width, height, lens = _intrinsics(cameras_file, cam_id, intrinsics)
        cams.append(_camera(images_file, what, q, t, (fx, fy, cx, cy, width, height)))
        lenses.append(lens)
    points_file = images_file.with_name("points3D" + images_file.suffix)
    points = read_colmap_points(points_file, dict(zip(image_ids, names))) if points_file.is_file() else None
    return ColmapModel(cams, lenses, names, points, images_file)


class _Reader:
    """Little-endian binary reads that name the file when it ends too early."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what} (byte {self.pos} of "
                               f"{len(self.data)})")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def count(self, what: str) -> int:
        """A uint64 count of records (`what`: "cameras", "images") that the file could hold."""
        (n,) = self.read("Q", f"the {what[:-1]} count")
        if n > len(self.data):
            raise DatasetError(f"{self.path}: corrupt: {n} {what} in a {len(self.data)}-byte file")
        return n

    def string(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what}")
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{self.path}: corrupt: {what} is not text") from None

    def skip(self, size: int, what: str) -> None:
        if size < 0 or self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what}")
        self.pos += size

    def finish(self, count: int, what: str) -> None:
        if self.pos != len(self.data):
            raise DatasetError(f"{self.path}: corrupt: {len(self.data) - self.pos} bytes after the last of {count} "
                               f"{what}")


def read_colmap_cameras(path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    """COLMAP `cameras.bin` or `cameras.txt`: camera id -> (model name, width, height, parameters)."""
    path = Path(path)
    out: dict[int, tuple[str, int, int, np.ndarray]] = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        count = r.count("cameras")
        for k in range(count):
            cam_id, model_id, width, height = r.read("iiQQ", f"camera {k}")
            if model_id not in COLMAP_MODELS:
                raise DatasetError(f"{path}: corrupt: camera {cam_id} has unknown model id {model_id}")
            name, n = COLMAP_MODELS[model_id]
            params = np.array(r.read(f"{n}d", f"the parameters of camera {cam_id}"), np.float64)
            out[cam_id] = (name, int(width), int(height), params)
        r.finish(count, "cameras")
    else:
        for lineno, line in _text_lines(path):
            parts = line.split()
            try:
                cam_id, name, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
                params = np.array([float(v) for v in parts[4:]], np.float64)
            except (IndexError, ValueError):
                raise DatasetError(f"{path}: line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got "
                                   f"{line[:80]!r}") from None
            if name not in _MODEL_IDS:
                raise DatasetError(f"{path}: line {lineno}: unknown camera model {name!r}")
            if len(params) != _MODEL_IDS[name][1]:
                raise DatasetError(f"{path}: line {lineno}: a {name} camera has {_MODEL_IDS[name][1]} parameters, "
                                   f"got {len(params)}")
            out[cam_id] = (name, width, height, params)
    if not out:
        raise DatasetError(f"{path}: no cameras")
    return out


def read_colmap_points(path, image_names: dict[int, str] | None = None) -> SfMPoints:
    """COLMAP `points3D.bin` or `points3D.txt`: positions, colours, errors and, given the model's
    image names by image id, which images observe each point (`SfMPoints.observers`; None for a
    model stored without tracks)."""
    path = Path(path)
    xyz, rgb, err, tracks = [], [], [], []
    if path.suffix == ".bin":
        r = _Reader(path)
        count = r.count("points")
        for _ in range(count):
            values = r.read("Q3d3Bd", "a point")
            xyz.append(values[1:4])
            rgb.append(values[4:7])
            err.append(values[7])
            (track,) = r.read("Q", "a point's track length")
            if track > len(r.data):
                raise DatasetError(f"{path}: corrupt: a track of {track} observations")
            tracks.append(r.read(f"{2 * track}I", "a point's track")[0::2])
        r.finish(count, "points")
    else:
        for lineno, line in _text_lines(path):
            parts = line.split()
            try:
                xyz.append([float(v) for v in parts[1:4]])
                rgb.append([int(v) for v in parts[4:7]])
                err.append(float(parts[7]) if len(parts) > 7 else float("nan"))
                tracks.append([int(v) for v in parts[8::2]])
            except (IndexError, ValueError):
                raise DatasetError(f"{path}: line {lineno}: expected POINT3D_ID X Y Z R G B ERROR TRACK..., got "
                                   f"{line[:80]!r}") from None
            if len(xyz[-1]) != 3 or len(rgb[-1]) != 3:
                raise DatasetError(f"{path}: line {lineno}: expected POINT3D_ID X Y Z R G B ERROR TRACK..., got "
                                   f"{line[:80]!r}")
    xyz_a = np.asarray(xyz, np.float64).reshape(-1, 3)
    rgb_a = np.asarray(rgb, np.float64).reshape(-1, 3)
    if not np.isfinite(xyz_a).all():
        raise DatasetError(f"{path}: non-finite point positions")
    if ((rgb_a < 0) | (rgb_a > 255)).any():
        raise DatasetError(f"{path}: point colours outside 0..255")
    observers = None if image_names is None or not any(len(t) for t in tracks) else _observers(tracks, image_names)
    return SfMPoints(xyz_a, (rgb_a / 255.0).astype(np.float32), np.asarray(err, np.float64), observers=observers)


def _observers(tracks: list, image_names: dict[int, str]) -> dict[str, np.ndarray]:
    """Image name stem -> the indices of the points whose tracks name that image (ids the model
    has no image for are ignored)."""
    lengths = np.array([len(t) for t in tracks], np.int64)
    point = np.repeat(np.arange(len(tracks), dtype=np.int64), lengths)
    image = np.fromiter((i for t in tracks for i in t), np.int64, int(lengths.sum()))
    order = np.lexsort((point, image))
    point, image = point[order], image[order]
    bounds = np.flatnonzero(np.diff(image)) + 1
    out = {}
    for ids, pts in zip(np.split(image, bounds), np.split(point, bounds)):
        if len(ids) and int(ids[0]) in image_names:
            out[Path(image_names[int(ids[0])]).stem] = np.unique(pts)
    return out


def _text_lines(path: Path):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: corrupt: not a text file") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield lineno, line


def _intrinsics(cam_file: Path, cam_id: int, intrinsics: dict):
    """(fx, fy, cx, cy, width, height, Lens) of camera `cam_id` (COLMAP's parameter order per model)."""
    if cam_id not in intrinsics:
        raise DatasetError(f"{cam_file}: an image refers to camera {cam_id}, which the cameras file lacks")
    name, width, height, p = intrinsics[cam_id]
    if name == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2], width, height, Lens()
    if name == "PINHOLE":
        return p[0], p[1], p[2], p[3], width, height, Lens()
    if name == "SIMPLE_RADIAL":
        return p[0], p[0], p[1], p[2], width, height, Lens(k1=p[3])
    if name == "RADIAL":
        return p[0], p[0], p[1], p[2], width, height, Lens(k1=p[3], k2=p[4])
    if name == "OPENCV":
        return p[0], p[1], p[2], p[3], width, height, Lens(k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    if name == "FULL_OPENCV":
        return p[0], p[1], p[2], p[3], width, height, Lens(k1=p[4], k2=p[5], p1=p[6], p2=p[7], k3=p[8], d1=p[9],
                                                            d2=p[10], d3=p[11])
    raise DatasetError(f"{cam_file}: camera {cam_id} uses the {name} model, which is not supported (pinhole, radial "
                       f"and OpenCV models only): {UNDISTORT_HINT}")


def _camera(path: Path, what: str, q, t, intr) -> Camera:
    q = np.asarray(q, np.float64)
    t = np.asarray(t, np.float64)
    norm = np.linalg.norm(q)
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or norm < 1e-12:
        raise DatasetError(f"{path}: {what}: non-finite or zero pose")
    w, x, y, z = q / norm
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = t
    fx, fy, cx, cy, width, height = intr
    try:
        return Camera(w2c, fx, fy, cx, cy, width, height)
    except ValueError as exc:
        raise DatasetError(f"{path}: {what}: {exc}") from None


def _read_images(path: Path) -> tuple[list[tuple[str, list, list]], list[str], list[int], list[int]]:
    """COLMAP `images.bin` or `images.txt`: per image in image-id order, (what to call it in an error,
    quaternion, translation), its name, its camera id and its image id."""
    found: list[tuple[int, tuple, str, int]] = []
    if path.suffix == ".bin":
        r = _Reader(path)
        count = r.count("images")
        for k in range(count):
            image_id, *pose, cam_id = r.read("I7di", f"image {k}")
            name = r.string(f"the name of image {image_id}")
            (points,) = r.read("Q", f"the point count of image {image_id}")
            r.skip(24 * points, f"the points of image {image_id}")
            found.append((image_id, (f"image {image_id} ({name})", pose[:4], pose[4:]), name, cam_id))
        r.finish(count, "images")
    else:
        # Two lines an image: the pose, then its 2D points (possibly an empty line). A line that
        # parses as a pose where points are expected is taken as the next pose (some writers drop
        # the empty lines).
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{path}: corrupt: not a text file") from None
        lines = [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if not line.startswith("#")]
        i = 0
        while i < len(lines):
            lineno, line = lines[i]
            i += 1
            if not line:
                continue
            parsed = _pose_line(line)
            if parsed is None:
                raise DatasetError(f"{path}: line {lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got "
                                   f"{line[:80]!r}")
            image_id, pose, cam_id, name = parsed
            if i < len(lines) and _pose_line(lines[i][1]) is None:
                i += 1  # its points line
            found.append((image_id, (f"line {lineno}", pose[:4], pose[4:]), name, cam_id))
    if not found:
        raise DatasetError(f"{path}: no images")
    found.sort(key=lambda item: item[0])
    return [f[1] for f in found], [f[2] for f in found], [f[3] for f in found], [f[0] for f in found]


def _pose_line(line: str):
    """(image id, 7 pose numbers, camera id, image name) of an images.txt pose line, else None."""
    parts = line.split()
    if len(parts) < 10:
        return None
    try:
        image_id, cam_id = int(parts[0]), int(parts[8])
        pose = [float(v) for v in parts[1:8]]
    except ValueError:
        return None
    name = " ".join(parts[9:])
    try:
        float(name)
        return None  # all numbers: a points line
    except ValueError:
        return image_id, pose, cam_id, name
