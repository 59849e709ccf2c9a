"""The reference 3DGS's `cameras.json`: the cameras a splat was trained from, kept beside it.

The reference trainer (and the trainers that keep its output layout) writes `MODEL/cameras.json`
beside `MODEL/point_cloud/iteration_N/point_cloud.ply`: a list with, per camera, `img_name`,
`width` and `height` (of its training image), `position` (the camera's centre, world frame),
`rotation` (camera-to-world 3x3 in COLMAP's axes: x right, y down, z forward), `fx` and `fy`
(pixels; the principal point at the centre). Run with `--eval`, its held-out cameras are listed
too. Cameras only: the photos are not named by path. Files that cannot be read raise
`DatasetError` naming the file and the problem.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_text
from ..camera import Camera
from ..datasets import DatasetError
from .lens import Lens

__all__ = ["GsCameras", "read_gs_cameras", "write_gs_cameras", "is_gs_cameras", "GS_CAMERAS"]

#: The file's name in the reference trainer's model folder.
GS_CAMERAS = "cameras.json"
_KEYS = ("width", "height", "position", "rotation", "fx", "fy")


@dataclass
class GsCameras:
    """The cameras of a `cameras.json` (pinhole, OpenCV convention), their names (`img_name`) and,
    as every reader gives them, their lenses (pinhole), image files (none) and points (none)."""

    cameras: list[Camera]
    names: list[str]
    lenses: list[Lens] = field(default_factory=list)
    points: None = None
    stated_size: bool = True

    def __post_init__(self):
        self.lenses = self.lenses or [Lens() for _ in self.cameras]


def _load(path: Path):
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: malformed JSON: {exc}") from None


def is_gs_cameras(path: Path) -> bool:
    """Whether the JSON file `path` is a reference 3DGS `cameras.json` (a list of cameras with a
    position and a rotation), not a transforms file."""
    try:
        data = _load(path)
    except (OSError, DatasetError):
        return False
    return isinstance(data, list) and bool(data) and isinstance(data[0], dict) \
        and "position" in data[0] and "rotation" in data[0]


def read_gs_cameras(path: Path) -> GsCameras:
    """Every camera of the `cameras.json` at `path` (module docstring)."""
    path = Path(path)
    data = _load(path)
    if not isinstance(data, list) or not data:
        raise DatasetError(f"{path}: malformed: expected a non-empty list of cameras (the reference 3DGS's "
                           f"cameras.json)")
    cams, names = [], []
    for i, entry in enumerate(data):
        missing = [k for k in _KEYS if not isinstance(entry, dict) or k not in entry]
        if missing:
            raise DatasetError(f"{path}: camera {i}: missing {', '.join(missing)}")
        try:
            centre = np.asarray(entry["position"], np.float64).reshape(3)
            c2w = np.asarray(entry["rotation"], np.float64).reshape(3, 3)
            w, h, fx, fy = (float(entry[k]) for k in ("width", "height", "fx", "fy"))
        except (TypeError, ValueError):
            raise DatasetError(f"{path}: camera {i}: position, rotation, size and focal lengths must be "
                               f"numbers (3, 3x3, 1 each)") from None
        if not (np.isfinite(centre).all() and np.isfinite(c2w).all()):
            raise DatasetError(f"{path}: camera {i}: position and rotation must be finite")
        if not np.allclose(c2w.T @ c2w, np.eye(3), atol=1e-4) or np.linalg.det(c2w) <= 0:
            raise DatasetError(f"{path}: camera {i}: rotation is not a rotation matrix")
        w2c = np.eye(4)
        w2c[:3, :3] = c2w.T
        w2c[:3, 3] = -c2w.T @ centre
        try:
            cams.append(Camera(w2c, fx, fy, w / 2.0, h / 2.0, int(round(w)), int(round(h))))
        except ValueError as exc:
            raise DatasetError(f"{path}: camera {i}: {exc}") from None
        names.append(str(entry.get("img_name", f"camera_{i:04d}")))
    return GsCameras(cams, names)


def write_gs_cameras(cameras, names, path) -> None:
    """`cameras` (with their image `names`) as the reference 3DGS writes them (module docstring;
    a principal point off the centre is not kept), atomically."""
    entries = [{"id": i, "img_name": str(name), "width": cam.width, "height": cam.height,
                "position": cam.center.tolist(), "rotation": cam.rotation.T.tolist(), "fx": cam.fx, "fy": cam.fy}
               for i, (cam, name) in enumerate(zip(cameras, names))]
    atomic_write_text(path, json.dumps(entries))
