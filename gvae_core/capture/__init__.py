"""Captures: the cameras and photos a splat is trained from, read through one door.

`open_capture(path, test_every)` reads a capture in one call (`door`): a folder of photos gets
its cameras by structure from motion first (`sfm`), then `read_capture` reads a COLMAP capture
(binary or text; `colmap`), a `transforms*.json` of instant-ngp or nerfstudio, a NeRF-Synthetic
folder (`transforms`) or the reference 3DGS's `cameras.json` (cameras only, `gs_cameras`) into
one `Capture` (`dataset`): per frame a pinhole camera in the OpenCV convention of DESIGN.md with
lens distortion undone (`lens`, as COLMAP's undistorter), its image, name and split (held-out
views every `test_every`-th by name), and the SfM points when there are any. Every command that
takes a capture (`train`, `render`, `refine --images/--cameras`, `compact --cameras/--images`)
reads it here: `load_cameras` (the training cameras), `load_capture_images` (the training images),
`load_nerf_synthetic` (a NeRF-Synthetic split). `views` places the views a cloud is scored from;
`beside` finds the cameras a splat file's training left beside it.
Files that cannot be read raise `DatasetError` (a ValueError) naming the file and the problem.
"""

from __future__ import annotations

from ..camera import Camera
from ..datasets import DatasetError, Views
from .colmap import COLMAP_MODELS, SfMPoints, read_colmap_cameras, read_colmap_points
from .beside import FoundCameras, cameras_beside, training_cameras
from .dataset import SPLITS, TEST_EVERY, Capture, find_capture, read_capture
from .door import open_capture
from .lens import Lens, undistort_image, undistorted_camera
from .views import (DEFAULT_RESOLUTION, DEFAULT_VIEWS, PlacedViews, Surround, default_views, in_view, inside_views,
                    outside_views, placed_views, scoring_views, surround, surround_radius)

__all__ = ["Capture", "open_capture", "read_capture", "find_capture", "load_cameras", "load_capture_images",
           "load_nerf_synthetic",
           "SfMPoints", "Lens", "undistort_image", "undistorted_camera", "read_colmap_cameras", "read_colmap_points",
           "COLMAP_MODELS", "SPLITS", "TEST_EVERY", "DatasetError", "scoring_views", "default_views", "placed_views",
           "PlacedViews", "outside_views", "inside_views", "surround", "surround_radius", "Surround", "DEFAULT_VIEWS",
           "DEFAULT_RESOLUTION", "cameras_beside", "training_cameras", "FoundCameras", "in_view"]


def load_cameras(path, test_every: int | None = None) -> list[Camera]:
    """The cameras a cloud was trained from: the training views of the capture at `path` (every
    frame of one transforms file or COLMAP model, but the held-out ones), without their images."""
    return open_capture(path, test_every, images=False).split_cameras("train")


def load_capture_images(path, resolution: int | None = None, test_every: int | None = None) -> Views:
    """The capture's training images with their cameras (for fitting a cloud trained from them),
    scaled to `resolution` pixels high (None: as stored; never up)."""
    capture = open_capture(path, test_every)
    height = capture.cameras[capture.indices("train")[0]].height if len(capture.indices("train")) else None
    return capture.load("train", None if resolution is None or height is None else min(int(resolution), height))


def load_nerf_synthetic(root, split: str = "train", resolution: int | None = None) -> Views:
    """`root/transforms_{split}.json` of a NeRF-Synthetic folder and its images, at `resolution`
    pixels high (None: as stored; the width keeps the aspect ratio, rounded like `Camera.scaled`)."""
    if resolution is not None and int(resolution) <= 0:
        raise ValueError(f"load_nerf_synthetic: resolution must be a positive height, got {resolution}")
    return read_capture(root, splits=(split,), kind="nerf-synthetic").load(split, resolution)
