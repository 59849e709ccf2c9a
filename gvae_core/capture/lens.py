"""Lens distortion of the OpenCV family, and undoing it the way COLMAP's undistorter does.

A photo taken through a distorting lens is not a pinhole image: read as one, its pixels land up
to a few pixels away from where the cloud's projection puts them. `Lens` holds the distortion
of normalised image coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy):

    r² = x² + y²,  R = (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) / (1 + d1 r² + d2 r⁴ + d3 r⁶)
    x' = x R + 2 p1 x y + p2 (r² + 2 x²),  y' = y R + p1 (r² + 2 y²) + 2 p2 x y

which covers COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV (k4..k6 of FULL_OPENCV are
the denominator d1..d3) and the `k1..k4, p1, p2` of instant-ngp's and nerfstudio's transforms.json
(nerfstudio's k4 is the r⁸ term). Fisheye models are not of this family and are refused by the
readers.

`undistorted_camera` is COLMAP's `UndistortCamera` with its defaults (blank_pixels 0, scale
clipped to [0.2, 2]): the pinhole whose view the distorted photo covers entirely, found from the
undistorted image border; the photo's size is kept and the focal lengths scaled instead of
cropping the image, so every frame of a capture keeps one size. `undistort_image` resamples a
photo into that pinhole (bilinear, pixel centres at +0.5). numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera

__all__ = ["Lens", "undistorted_camera", "undistort_image", "MIN_SCALE", "MAX_SCALE"]

#: COLMAP's undistorter clips the scale of the undistorted view to this range.
MIN_SCALE, MAX_SCALE = 0.2, 2.0


@dataclass(frozen=True)
class Lens:
    """Distortion coefficients (module docstring): radial numerator k1..k4, denominator d1..d3,
    tangential p1, p2. All zero: a pinhole."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    d1: float = 0.0
    d2: float = 0.0
    d3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def is_pinhole(self) -> bool:
        return not any(getattr(self, f) for f in self.__dataclass_fields__)

    def distort(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates of undistorted ones (the lens's forward model)."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        r2 = x * x + y * y
        radial = (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)))) \
            / (1.0 + r2 * (self.d1 + r2 * (self.d2 + r2 * self.d3)))
        xy = x * y
        return (x * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x * x),
                y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * xy)

    def undistort(self, xd, yd, iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates of distorted ones: Newton's method on `distort`
        with a numerical Jacobian (as COLMAP's `IterativeUndistortion`), from the distorted point."""
        xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
        x, y = xd.copy(), yd.copy()
        eps = 1e-7
        for _ in range(iterations):
            fx, fy = self.distort(x, y)
            rx, ry = fx - xd, fy - yd
            ax, ay = self.distort(x + eps, y)
            bx, by = self.distort(x, y + eps)
            j00, j10 = (ax - fx) / eps, (ay - fy) / eps
            j01, j11 = (bx - fx) / eps, (by - fy) / eps
            det = j00 * j11 - j01 * j10
            det = np.where(np.abs(det) < 1e-12, 1e-12, det)
            dx, dy = (j11 * rx - j01 * ry) / det, (j00 * ry - j10 * rx) / det
            x, y = x - dx, y - dy
            if max(float(np.abs(dx).max(initial=0.0)), float(np.abs(dy).max(initial=0.0))) < 1e-12:
                break
        return x, y


def _border(width: int, height: int) -> tuple[np.ndarray, ...]:
    """Pixel centres along the four image borders: left, right (x fixed), top, bottom (y fixed)."""
    ys, xs = np.arange(height) + 0.5, np.arange(width) + 0.5
    return (np.stack([np.full(height, 0.5), ys], 1), np.stack([np.full(height, width - 0.5), ys], 1),
            np.stack([xs, np.full(width, 0.5)], 1), np.stack([xs, np.full(width, height - 0.5)], 1))


def undistorted_camera(camera: Camera, lens: Lens) -> Camera:
    """The pinhole camera a photo taken by `camera` (its pinhole part) through `lens` is undistorted
    into: COLMAP's choice of view (module docstring) at the photo's size."""
    if lens.is_pinhole:
        return camera
    w, h, cx, cy = camera.width, camera.height, camera.cx, camera.cy
    inner = []
    for pts in _border(w, h):
        x, y = lens.undistort((pts[:, 0] - cx) / camera.fx, (pts[:, 1] - cy) / camera.fy)
        inner.append((camera.fx * x + cx, camera.fy * y + cy))
    (left, _), (right, _), (_, top), (_, bottom) = inner
    # The largest scale with no blank pixels: the innermost point of each undistorted border.
    scale_x = min((cx - left.max()) / cx, (right.min() - cx) / (w - cx))
    scale_y = min((cy - top.max()) / cy, (bottom.min() - cy) / (h - cy))
    scale_x, scale_y = (float(np.clip(s, MIN_SCALE, MAX_SCALE)) for s in (scale_x, scale_y))
    return Camera(camera.world_to_cam.copy(), camera.fx / scale_x, camera.fy / scale_y, cx, cy, w, h)


def source_pixels(distorted: Camera, lens: Lens, target: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of the pinhole `target`, where its centre lies in the photo taken by `distorted`
    through `lens` (continuous pixel coordinates, centres at +0.5): (H, W) x and y."""
    xs = (np.arange(target.width) + 0.5 - target.cx) / target.fx
    ys = (np.arange(target.height) + 0.5 - target.cy) / target.fy
    x, y = lens.distort(*np.meshgrid(xs, ys))
    return distorted.fx * x + distorted.cx, distorted.fy * y + distorted.cy


def undistort_image(image: np.ndarray, distorted: Camera, lens: Lens, target: Camera) -> np.ndarray:
    """`image` (H, W, C) taken by `distorted` through `lens`, resampled bilinearly into the pinhole
    `target` (`undistorted_camera`); samples beyond the photo take its nearest edge pixel."""
    img = np.asarray(image, np.float32)
    sx, sy = source_pixels(distorted, lens, target)
    fx, fy = sx - 0.5, sy - 0.5  # pixel-index coordinates
    x0 = np.clip(np.floor(fx), 0, img.shape[1] - 1).astype(np.int64)
    y0 = np.clip(np.floor(fy), 0, img.shape[0] - 1).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, img.shape[1] - 1), np.minimum(y0 + 1, img.shape[0] - 1)
    ax = np.clip(fx - x0, 0.0, 1.0).astype(np.float32)[..., None]
    ay = np.clip(fy - y0, 0.0, 1.0).astype(np.float32)[..., None]
    top = img[y0, x0] * (1 - ax) + img[y0, x1] * ax
    bottom = img[y1, x0] * (1 - ax) + img[y1, x1] * ax
    return (top * (1 - ay) + bottom * ay).astype(np.float32)
