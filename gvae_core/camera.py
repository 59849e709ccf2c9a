"""Pinhole cameras in the OpenCV convention (DESIGN.md): world-to-camera 4x4, the camera looks
along +z with x right and y down; intrinsics in pixels; pixel (row i, column j) has its centre at
(j + 0.5, i + 0.5). numpy only (float64), so Blender-side code can use it without torch."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Blender/OpenGL cameras look along -z with y up; OpenCV along +z with y down.
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    """A pinhole camera: world_to_cam (4,4), focal lengths and principal point in pixels, size."""

    world_to_cam: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        w2c = np.asarray(self.world_to_cam, dtype=np.float64)
        if w2c.shape == (3, 4):
            w2c = np.vstack([w2c, [0.0, 0.0, 0.0, 1.0]])
        if w2c.shape != (4, 4) or not np.isfinite(w2c).all():
            raise ValueError(f"Camera.world_to_cam must be a finite 4x4 matrix, got {w2c.shape}")
        self.world_to_cam = w2c
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx, self.cy))
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera needs positive size and focal lengths, got {self.width}x{self.height}, "
                             f"fx={self.fx}, fy={self.fy}")

    # ----------------------------------------------------------------- views
    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation R (3,3)."""
        return self.world_to_cam[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        """World-to-camera translation t (3,): x_cam = R x_world + t."""
        return self.world_to_cam[:3, 3]

    @property
    def cam_to_world(self) -> np.ndarray:
        r, t = self.rotation, self.translation
        out = np.eye(4)
        out[:3, :3] = r.T
        out[:3, 3] = -r.T @ t
        return out

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def fov_x(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fx))

    @property
    def fov_y(self) -> float:
        return 2.0 * math.atan(self.height / (2.0 * self.fy))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    # -------------------------------------------------------------- helpers
    def scaled(self, height: int) -> Camera:
        """The same view at another image height (width keeps the aspect ratio)."""
        height = int(height)
        sy = height / self.height
        width = max(1, int(round(self.width * sy)))
        sx = width / self.width
        return Camera(self.world_to_cam.copy(), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      width, height)

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) to pixel coordinates (N,2) as (x, y) = (column, row) continuous
        coordinates, and camera depths (N,). Points at z <= 0 get NaN pixels."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        cam = p @ self.rotation.T + self.translation
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            safe = np.where(z > 0, z, np.nan)
            uv = np.stack([self.fx * cam[:, 0] / safe + self.cx, self.fy * cam[:, 1] / safe + self.cy], 1)
        return uv, z

    # ---------------------------------------------------------- Blender I/O
    @classmethod
    def from_blender_c2w(cls, c2w, camera_angle_x: float, width: int, height: int) -> Camera:
        """From a NeRF-Synthetic / Blender camera-to-world matrix (y up, looking along -z)."""
        c2w = np.asarray(c2w, np.float64) @ _FLIP_YZ
        fx = 0.5 * width / math.tan(0.5 * float(camera_angle_x))
        return cls(np.linalg.inv(c2w), fx, fx, width / 2.0, height / 2.0, width, height)

    def to_blender_c2w(self) -> np.ndarray:
        """Camera-to-world in the Blender/OpenGL convention (inverse of `from_blender_c2w`)."""
        return self.cam_to_world @ _FLIP_YZ

    # ------------------------------------------------------------ builders
    @classmethod
    def look_at(cls, eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), *, width: int = 400,
                height: int = 400, fov_x: float = math.radians(50.0)) -> Camera:
        """A camera at `eye` looking at `target`, with `up` pointing up in the image."""
        eye = np.asarray(eye, np.float64)
        forward = np.asarray(target, np.float64) - eye
        norm = np.linalg.norm(forward)
        if norm < 1e-12:
            raise ValueError("Camera.look_at: eye and target coincide")
        forward /= norm
        up = np.asarray(up, np.float64)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
            right = np.cross(forward, [1.0, 0.0, 0.0] if abs(forward[0]) < 0.9 else [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        r = np.stack([right, down, forward])  # rows: camera x, y, z axes in world
        w2c = np.eye(4)
        w2c[:3, :3] = r
        w2c[:3, 3] = -r @ eye
        fx = 0.5 * width / math.tan(0.5 * fov_x)
        return cls(w2c, fx, fx, width / 2.0, height / 2.0, width, height)


def orbit(n: int, radius: float, elevation: float = math.radians(30.0), *, target=(0.0, 0.0, 0.0),
          up=(0.0, 0.0, 1.0), width: int = 400, height: int = 400, fov_x: float = math.radians(50.0),
          start_azimuth: float = 0.0) -> list[Camera]:
    """`n` cameras evenly spaced in azimuth on a circle at `elevation` (radians) above the target,
    all looking at it; z is up unless `up` says otherwise."""
    target = np.asarray(target, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    # Two unit vectors spanning the plane perpendicular to `up`.
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    cams = []
    for k in range(n):
        az = start_azimuth + 2.0 * math.pi * k / n
        d = math.cos(elevation) * (math.cos(az) * a + math.sin(az) * b) + math.sin(elevation) * up
        cams.append(Camera.look_at(target + radius * d, target, up, width=width, height=height, fov_x=fov_x))
    return cams


def look_target(cameras) -> np.ndarray:
    """Least-squares point nearest to every optical axis (where the cameras look); a point in front
    of them when the axes are all parallel."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c in cameras:
        d = c.rotation[2]  # camera +z axis in world coordinates
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c.center
    if np.linalg.cond(a) > 1e8:
        return np.mean([c.center + 3.0 * c.rotation[2] for c in cameras], 0)
    return np.linalg.solve(a, b)


def scene_extent(cameras) -> tuple[np.ndarray, float]:
    """The reference 3DGS's camera normalisation: the centre of the camera centres and 1.1 x the
    largest distance from it (the scale of positional learning rates and of densification)."""
    centers = np.stack([c.center for c in cameras])
    mid = centers.mean(0)
    radius = 1.1 * float(np.linalg.norm(centers - mid, axis=1).max())
    if radius < 1e-9:  # one camera: its distance to the point it looks at
        radius = 1.1 * float(np.linalg.norm(look_target(cameras) - centers[0])) or 1.0
    return mid, radius
