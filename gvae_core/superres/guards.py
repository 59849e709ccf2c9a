"""What a real capture's images do that a render does not, fitted per image beside the changes per
octave: a small pose error (`PoseCorrection`) and an exposure or white-balance change
(`ExposureCorrection`). Each is a set of torch parameters, one row per image, that starts at "no
change", is pulled back towards it by a penalty, and has its mean over the images held at zero (the
cloud was trained on all of them: their average is what it already shows).
"""

from __future__ import annotations

import numpy as np
import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from ..quaternions import multiply

__all__ = ["PoseCorrection", "ExposureCorrection", "POSE_WEIGHT", "EXPOSURE_WEIGHT"]

#: The guards' penalty weights when on (`SuperResConfig.pose`, `.exposure`).
POSE_WEIGHT = 0.01
EXPOSURE_WEIGHT = 0.1


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


class PoseCorrection:
    """A rigid change of each image's camera, in that camera's frame: a rotation vector (radians)
    and a translation (in pixels at the image's depth scale, `depth`), applied as the inverse change
    of the cloud so the renderer's cameras stay as they are. `weight`: the penalty on the squared
    change, in pixels of image motion (a rotation by 1/f radians moves the image by one pixel)."""

    def __init__(self, cameras: list[Camera], depth: np.ndarray, weight: float):
        self.cameras = cameras
        self.focal = torch.tensor([max(c.fx, c.fy) for c in cameras], dtype=torch.float64)
        self.depth = torch.as_tensor(np.asarray(depth, np.float64))
        self.weight = float(weight)
        # six numbers per image, in pixels of image motion: rotation (3), translation (3)
        self.params = torch.zeros((len(cameras), 6), dtype=torch.float64, requires_grad=True)

    def centred(self) -> torch.Tensor:
        return self.params - self.params.mean(0, keepdim=True)

    def penalty(self) -> torch.Tensor:
        return self.weight * self.centred().pow(2).sum(1).mean()

    def pixels(self) -> np.ndarray:
        """(V,) how far each correction moves its image, pixels (rotation and translation)."""
        return self.centred().detach().norm(dim=1).numpy()

    def apply(self, cloud: GaussianCloud, view: int) -> GaussianCloud:
        """`cloud` (torch) moved so that the camera of image `view` sees it as the corrected camera
        would see the cloud as it is (SH directions are not rotated: the change is a fraction of a
        pixel)."""
        p = self.centred()[view]
        cam = self.cameras[view]
        f = self.focal[view]
        omega = p[:3] / f                       # radians
        tau = p[3:] / f * self.depth[view]      # world units (pixels at the view's depth)
        rot_delta = torch.linalg.matrix_exp(_skew(omega))
        rc = torch.as_tensor(cam.rotation, dtype=torch.float64)
        center = torch.as_tensor(cam.center, dtype=torch.float64)
        a = rc.T @ rot_delta @ rc                # the change as a world rotation about the camera centre
        shift = rc.T @ tau
        means = cloud.means.to(torch.float64)
        moved = (means - center) @ a.T + center + shift
        q = _quaternion(a).to(cloud.quats.dtype)
        return cloud.replace(means=moved.to(cloud.means.dtype), quats=multiply(q, cloud.quats))


def _quaternion(m: torch.Tensor) -> torch.Tensor:
    """A rotation matrix near the identity as a (w, x, y, z) quaternion, differentiable."""
    w = 0.5 * torch.sqrt(torch.clamp(1.0 + m[0, 0] + m[1, 1] + m[2, 2], min=1e-12))
    return torch.stack([w, (m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w)])


class ExposureCorrection:
    """A colour gain and offset per image and channel, applied to what the cloud draws (not the
    background): drawn = gain * colour + offset * alpha. `weight`: the penalty on the squared
    log-gain and offset."""

    def __init__(self, count: int, weight: float):
        self.weight = float(weight)
        self.params = torch.zeros((count, 6), dtype=torch.float32, requires_grad=True)  # log-gain 3, offset 3

    def centred(self) -> torch.Tensor:
        return self.params - self.params.mean(0, keepdim=True)

    def penalty(self) -> torch.Tensor:
        return self.weight * self.centred().pow(2).sum(1).mean()

    def gains(self) -> np.ndarray:
        return self.centred()[:, :3].detach().exp().numpy()

    def apply(self, image: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor, view: int) -> torch.Tensor:
        p = self.centred()[view]
        colour = image - (1.0 - alpha)[..., None] * background
        return p[:3].exp() * colour + p[3:] * alpha[..., None] + (1.0 - alpha)[..., None] * background

