"""`transforms*.json` captures: NeRF-Synthetic, instant-ngp and nerfstudio.

Camera-to-world matrices in the Blender/OpenGL convention (y up, looking along -z), flipped to
OpenCV. Intrinsics per frame or for the file: `fl_x`/`fl_y`/`cx`/`cy` in pixels with `w`/`h`, or
`camera_angle_x` (and `camera_angle_y`, else fy = fx) with the principal point at the centre,
the image size from the file or else from the frame's image. Lens distortion `k1..k4, p1, p2`
(nerfstudio's OPENCV model: k4 is the r⁸ term) is kept as the frame's `Lens`, undone when the
images are read; fisheye and equirectangular cameras are refused with how to undistort. SfM
points from nerfstudio's `ply_file_path` (a PLY of x, y, z and red, green, blue) when named.
Files that cannot be read raise `DatasetError` naming the file and the problem.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..camera import Camera
from ..datasets import DatasetError
from .colmap import SfMPoints
from .lens import Lens

__all__ = ["TransformsFrames", "read_transforms", "read_transforms_file", "find_image", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".webp", ".JPG", ".PNG", ".JPEG")
_LENS_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_FISHEYE_HINT = ("undistort the images first (nerfstudio: ns-process-data with --camera-type perspective; COLMAP: "
                 "colmap image_undistorter) and give the undistorted capture")


@dataclass
class TransformsFrames:
    """The frames of one transforms file: cameras (pinhole part, at the size the file states or
    the first image has), lenses, image files (where they should be; None for a frame that names
    none), names (what the frames' file_path name), the SfM points the file names (None without), and
    whether the file states the image size (`w`, `h`) rather than the first image giving it."""

    cameras: list[Camera]
    lenses: list[Lens]
    files: list[Path | None]
    names: list[str]
    points: SfMPoints | None
    stated_size: bool


def read_transforms_file(path: Path) -> tuple[dict, list]:
    """A transforms JSON and its non-empty 'frames' list; DatasetError naming the file when it is
    not one."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: malformed JSON: {exc}") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: malformed: expected an object with a non-empty 'frames' list")
    return meta, frames


def read_transforms(path: Path) -> TransformsFrames:
    """Every frame of the transforms file `path` (module docstring)."""
    meta, frames = read_transforms_file(path)
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if "FISHEYE" in model or "EQUIRECTANGULAR" in model or meta.get("is_fisheye"):
        raise DatasetError(f"{path}: camera_model {model if 'FISHEYE' in model or 'EQUI' in model else 'fisheye'} "
                           f"is not supported (pinhole cameras with OpenCV distortion only): {_FISHEYE_HINT}")
    size = None
    cams, lenses, files, names = [], [], [], []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{path}: malformed frame {i}: not an object")
        try:
            c2w = np.asarray(frame["transform_matrix"], np.float64)
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{path}: malformed frame {i}: needs a numeric 'transform_matrix'") from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise DatasetError(f"{path}: frame {i}: transform_matrix must be a finite 4x4 matrix")
        rel = frame.get("file_path")
        if rel is not None and not isinstance(rel, str):
            raise DatasetError(f"{path}: malformed frame {i}: 'file_path' is not text")
        image = find_image(path.parent, rel) if rel else None

        def get(key, default=None, frame=frame, i=i):
            return _number(path, meta, frame, i, key, default)

        fx, fy, angle = get("fl_x"), get("fl_y"), get("camera_angle_x")
        if fx is None and angle is None:
            raise DatasetError(f"{path}: frame {i}: no focal length ('fl_x' or 'camera_angle_x')")
        if fx is None and not 0.0 < angle < math.pi:
            raise DatasetError(f"{path}: camera_angle_x {angle} is not in (0, pi)")
        w, h = get("w"), get("h")
        if w is None or h is None:
            if size is None:
                size = _first_image_size(path, frames)
            w, h = size
        if fx is None:
            fx = 0.5 * w / math.tan(0.5 * angle)
        if fy is None:
            angle_y = get("camera_angle_y")
            fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None and 0 < angle_y < math.pi else fx
        cx, cy = get("cx", w / 2.0), get("cy", h / 2.0)
        base = Camera.from_blender_c2w(c2w, 2.0 * math.atan(0.5 * w / fx), int(round(w)), int(round(h)))
        try:
            cams.append(Camera(base.world_to_cam, fx, fy, cx, cy, int(round(w)), int(round(h))))
        except ValueError as exc:
            raise DatasetError(f"{path}: frame {i}: {exc}") from None
        lenses.append(Lens(**{k: get(k, 0.0) for k in _LENS_KEYS}))
        files.append(image)
        names.append(Path(rel).stem if rel else f"frame_{i:04d}")
    points = _ply_points(path, meta["ply_file_path"]) if isinstance(meta.get("ply_file_path"), str) else None
    return TransformsFrames(cams, lenses, files, names, points, stated_size=size is None)


def find_image(folder: Path, rel: str) -> Path:
    """The image a frame's file_path names (NeRF-Synthetic omits the suffix): the file that exists,
    else the name it would have (for the message that it is missing)."""
    base = folder / rel
    candidates = [base] if base.suffix.lower() in {s.lower() for s in IMAGE_SUFFIXES} else []
    candidates += [base.with_name(base.name + s) for s in IMAGE_SUFFIXES]
    return next((c for c in candidates if c.is_file()), candidates[0])


def _number(path: Path, meta: dict, frame: dict, index: int, key: str, default=None) -> float | None:
    """A frame's numeric field, else the file's, else `default`; non-numbers are refused."""
    value = frame.get(key, meta.get(key, default))
    if value is None:
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: frame {index}: {key!r} is not a number") from None
    if not math.isfinite(value):
        raise DatasetError(f"{path}: frame {index}: {key!r} is not finite")
    return value


def _first_image_size(path: Path, frames: list) -> tuple[int, int]:
    """(width, height) of the first frame's image that exists (only its header is read)."""
    wanted = None
    for frame in frames:
        rel = frame.get("file_path") if isinstance(frame, dict) else None
        image = find_image(path.parent, rel) if isinstance(rel, str) and rel else None
        wanted = wanted or image
        if image is not None and image.is_file():
            try:
                with Image.open(image) as im:
                    return im.size
            except (UnidentifiedImageError, OSError) as exc:
                raise DatasetError(f"{image}: cannot read image: {exc}") from None
    raise DatasetError(f"{wanted or path}: image not found; {path.name} gives no image size ('w' and 'h') and none "
                       f"of its frames' images was found")


def _ply_points(path: Path, rel: str) -> SfMPoints:
    """nerfstudio's SfM point cloud (x, y, z, red, green, blue), in the frames' world frame."""
    from plyfile import PlyData  # noqa: PLC0415 - only for captures that name one

    file = path.parent / rel
    try:
        vertex = PlyData.read(str(file))["vertex"]
        xyz = np.stack([np.asarray(vertex[k], np.float64) for k in "xyz"], 1)
        names = vertex.data.dtype.names
        rgb = (np.stack([np.asarray(vertex[k], np.float64) for k in ("red", "green", "blue")], 1) / 255.0
               if {"red", "green", "blue"} <= set(names) else np.full((len(xyz), 3), 0.5))
    except (OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{file}: cannot read the SfM points named by {path.name} ({exc})") from None
    if not np.isfinite(xyz).all():
        raise DatasetError(f"{file}: non-finite point positions")
    return SfMPoints(xyz, rgb.astype(np.float32), np.full(len(xyz), np.nan))
