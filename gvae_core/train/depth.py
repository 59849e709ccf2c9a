"""The SfM points' depths as a training signal: a sparse depth prior.

Each training view gets the SfM points it sees, at the pixel each falls in, with its camera depth
(`depth_targets`): the points its own features matched (the model's tracks), or, for a model
stored without tracks, the points a coarse z-buffer of the points keeps (the nearest in each cell
of a grid over the photo, and those within a few percent behind it). A step then adds
`depth_loss`, the mean relative error |D - z| / z of the rendered depth D (sum of w z over alpha)
at those pixels, weighted by `TrainConfig.depth_weight`. Where few photos see a region, colour
alone lets content sit at any depth that reproduces them (floaters in front of the cameras that
did not train); the points hold it at the depth the photos' matches agree on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..camera import Camera
from ..capture import SfMPoints
from ..datasets import Views

__all__ = ["DepthTargets", "depth_targets", "depth_loss", "visible_points"]

#: Points with a mean reprojection error above this (pixels at the model's size) give no target.
MAX_ERROR = 2.0
#: The z-buffer of a model without tracks: grid rows over the photo's height, and how far behind
#: the nearest point of its cell (relative depth) a point may lie and still be kept.
GRID_ROWS, BEHIND = 64, 0.05


@dataclass
class DepthTargets:
    """Per training view: the flat pixel indices (row * width + column, at the views' size) where
    the points it sees fall, and their camera depths (float32, on the training device)."""

    pixels: list[torch.Tensor]
    depths: list[torch.Tensor]

    def __len__(self) -> int:
        return len(self.pixels)

    def count(self) -> int:
        return sum(len(p) for p in self.pixels)


def depth_targets(points: SfMPoints | None, views: Views, device=None) -> DepthTargets | None:
    """The depth targets of `views` (their names find their tracks) from `points`; None without
    points or when no view sees one."""
    if points is None or len(points) == 0:
        return None
    reliable = ~(points.error > MAX_ERROR)  # (NaN: unknown, kept)
    kept = points.xyz[reliable]
    pixels, depths = [], []
    for camera, name in zip(views.cameras, views.names):
        seen = points.observed_by(name)
        xyz = kept[visible_points(kept, camera)] if seen is None else points.xyz[seen[reliable[seen]]]
        flat, z = _pixels(camera, xyz)
        pixels.append(torch.from_numpy(flat).to(device))
        depths.append(torch.from_numpy(z.astype(np.float32)).to(device))
    targets = DepthTargets(pixels, depths)
    return targets if targets.count() else None


def visible_points(xyz: np.ndarray, camera: Camera) -> np.ndarray:
    """Indices of the points of `xyz` a coarse z-buffer of them keeps in `camera` (module docstring)."""
    inside, uv, z = _in_image(camera, xyz)
    if len(inside) == 0:
        return inside
    cell = camera.height / GRID_ROWS
    cols = int(np.ceil(camera.width / cell))
    key = np.floor(uv[inside, 1] / cell).astype(np.int64) * cols + np.floor(uv[inside, 0] / cell).astype(np.int64)
    nearest = np.full(GRID_ROWS * cols + cols, np.inf)
    np.minimum.at(nearest, key, z[inside])
    return inside[z[inside] <= nearest[key] * (1.0 + BEHIND)]


def _pixels(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flat pixel indices, camera depths) of the points of `xyz` that fall inside `camera`'s image."""
    inside, uv, z = _in_image(camera, xyz)
    col, row = np.floor(uv[inside, 0]).astype(np.int64), np.floor(uv[inside, 1]).astype(np.int64)
    return row * camera.width + col, z[inside]


def _in_image(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices of the points in front of `camera` and inside its image, pixel coordinates, depths)."""
    uv, z = camera.project(xyz)
    with np.errstate(invalid="ignore"):  # (NaN pixels behind the camera)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    return np.flatnonzero(ok), uv, z


def depth_loss(depth: torch.Tensor, targets: DepthTargets, view: int) -> torch.Tensor:
    """Mean relative error |D - z| / z of the rendered depth `depth` (H, W) at view `view`'s target
    pixels (zero without any)."""
    pixels, z = targets.pixels[view], targets.depths[view]
    if len(pixels) == 0:
        return depth.new_zeros(())
    drawn = depth.reshape(-1)[pixels]
    return ((drawn - z).abs() / z).mean()
