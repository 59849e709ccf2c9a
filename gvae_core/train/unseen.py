"""Gaussians no training photo sees: the renderer's projection of each training camera marks a
Gaussian visible when it lies in front of the camera and its footprint touches the image; one that
no training camera marks gets no gradient from any photo, so its place, size and opacity are
whatever it had when it left their view (a clone or a split child pushed past the cameras, an SfM
point behind them). From a viewpoint the photos do not cover it can stand right in front of the
camera (such Gaussians drew a held-out photo of the plush at 6 dB).
A stage's result keeps only the Gaussians some training photo sees.
"""

from __future__ import annotations

import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from ..rendering import RenderSettings, project_view

__all__ = ["seen_by_any"]


def seen_by_any(cloud: GaussianCloud, cameras: list[Camera], settings: RenderSettings) -> torch.Tensor:
    """(N,) bool: whether any of `cameras` draws each Gaussian of `cloud` (as `render` with
    `settings` would project it: `rendering.project_view`, no tile lists)."""
    seen = torch.zeros(len(cloud), dtype=torch.bool)
    with torch.no_grad():
        for camera in cameras:
            seen |= project_view(cloud, camera, settings)[0].visible.cpu()
    return seen
