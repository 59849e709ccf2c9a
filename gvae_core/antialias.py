"""Anti-aliasing that follows the training resolution: per-Gaussian world-space sizes computed from
the cameras a cloud was trained with, stored with the cloud, honoured by the renderer. numpy only.

A camera with focal length f (pixels) samples the world at depth z every z / f world units; the
highest sampling rate at which the training cameras saw a Gaussian is

    nu = max over the cameras that see it of f / z        (pixels per world unit).

A camera sees a Gaussian when its centre is in front of the near plane and projects inside the
image widened by VIEW_MARGIN on each side. A Gaussian no training camera sees gets the largest
size of those that are seen (as Mip-Splatting does), and 0 when nothing is seen at all. Two
stored sizes, one per way a cloud can have been trained, each an extra PLY property (float32,
world units, one per Gaussian):

- FILTER_KEY = "filter_3D", sqrt(0.2) / nu: Mip-Splatting's 3D smoothing filter (Yu et al., CVPR
  2024), with the name and meaning of its own PLY files, for clouds trained with the filters
  (`TrainConfig(antialias="mip")`, Mip-Splatting): rendered with covariance Σ + filter_3D² I,
  opacity times sqrt(det Σ / det(Σ + filter_3D² I)), and the 2D Mip filter (mode "mip").
- DILATION_KEY = "gvae_dilation_3D", sqrt(0.3) / nu: the classic 0.3 px² dilation of the
  reference 3DGS expressed in world units at the finest training sampling, for clouds trained the
  classic way (the default trainer, most 3DGS tools): rendered with covariance Σ + d² I and the 2D
  dilation max(0, 0.3 - d² fx fy / z²) px², opacity unchanged (mode "matched"). At the training
  views this is the classic render; above the training resolution the blur the Gaussians were
  fitted with stays the same size in the world instead of shrinking with the pixels.

The two must not be swapped: the compensated Mip filters wipe out the thin, flat Gaussians a
classic training makes (measured: -3 to -7 dB at the training resolution, BENCHMARKS.md), and a
Mip-trained cloud rendered without compensation is too opaque.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .camera import Camera
from .cloud import GaussianCloud
from .conventions import NEAR_PLANE
from .parallel import in_threads

__all__ = ["FILTER_KEY", "DILATION_KEY", "FILTER_3D_VARIANCE", "CLASSIC_DILATION", "VIEW_MARGIN",
           "ANTIALIAS_MODES", "DEFAULT_ANTIALIAS", "resolve_antialias", "max_sampling_rate", "filter_3d",
           "dilation_3d", "filter_3d_reference", "with_filter_3d", "with_dilation_3d", "with_training_cameras",
           "cameras_at_height"]

#: Render modes (`gvae_core.rendering.RenderSettings.antialias`):
#: - "classic": the reference 3DGS, +CLASSIC_DILATION px² on every 2D covariance in the pixels of
#:   the image being rendered (a cloud trained at H px erodes when rendered at 2H);
#: - "mip": Mip-Splatting: the cloud's 3D filter (`extra[FILTER_KEY]`; without it that part is off)
#:   and the 2D Mip filter in place of the dilation, both with their opacity compensation;
#: - "matched": the classic dilation held in world units (`extra[DILATION_KEY]`; without it this
#:   is "classic");
#: - "auto": "mip" for a cloud with FILTER_KEY, else "matched" for one with DILATION_KEY, else
#:   "classic" (a PLY from another tool renders as it always did).
ANTIALIAS_MODES = ("auto", "classic", "mip", "matched")
#: The mode `render`, the metrics, the Hessian and `gvae render` use unless told otherwise: what
#: the cloud carries (the measurements behind this are in BENCHMARKS.md, "Anti-aliasing").
DEFAULT_ANTIALIAS = "auto"
#: Extra PLY property of Mip-Splatting's 3D filter (its standard deviation, world units).
FILTER_KEY = "filter_3D"
#: Extra PLY property of the classic dilation in world units (its standard deviation).
DILATION_KEY = "gvae_dilation_3D"
#: Variance of the 3D filter in units of the squared sampling interval (z / f)² (Mip-Splatting's 0.2).
FILTER_3D_VARIANCE = 0.2
#: The reference 3DGS's dilation of every 2D covariance (px²), and the variance of DILATION_KEY in
#: units of the squared sampling interval.
CLASSIC_DILATION = 0.3
#: A camera sees a centre that projects inside [-m W, (1 + m) W] x [-m H, (1 + m) H] (Mip-Splatting's 15%).
VIEW_MARGIN = 0.15


def resolve_antialias(mode: str, cloud: GaussianCloud) -> str:
    """The mode ("classic", "mip" or "matched") that `mode` means for `cloud`."""
    if mode not in ANTIALIAS_MODES:
        raise ValueError(f"antialias must be one of {', '.join(ANTIALIAS_MODES)}, got {mode!r}")
    if mode == "auto":
        return "mip" if FILTER_KEY in cloud.extra else "matched" if DILATION_KEY in cloud.extra else "classic"
    if mode == "matched" and DILATION_KEY not in cloud.extra:
        return "classic"
    return mode


def cameras_at_height(cameras: Sequence[Camera], height: int | None) -> list[Camera]:
    """`cameras` at image height `height` (None: as they are): the training cameras of a cloud
    whose training resolution is known but whose cameras are given at another size."""
    cams = list(cameras)
    if height is None:
        return cams
    if int(height) <= 0:
        raise ValueError(f"training resolution must be a positive image height, got {height}")
    return [c.scaled(int(height)) for c in cams]


def _camera_rate(means: np.ndarray, cam: Camera, near: float, margin: float) -> np.ndarray:
    """(N,) f / z of one camera where it sees the centre, else 0."""
    p = (means - cam.center) @ cam.rotation.T  # float64, relative to the camera before anything else
    z = p[:, 2]
    front = np.isfinite(z) & (z > near)
    zs = np.where(front, z, 1.0)  # never divide by a depth at or behind the near plane
    u = cam.fx * p[:, 0] / zs + cam.cx
    v = cam.fy * p[:, 1] / zs + cam.cy
    inside = (front & (u >= -margin * cam.width) & (u <= (1.0 + margin) * cam.width)
              & (v >= -margin * cam.height) & (v <= (1.0 + margin) * cam.height))
    return np.where(inside, max(cam.fx, cam.fy) / zs, 0.0)


def max_sampling_rate(means, cameras: Sequence[Camera], *, near: float = NEAR_PLANE,
                      margin: float = VIEW_MARGIN) -> np.ndarray:
    """(N,) float64: the largest f / z (pixels per world unit) over the cameras that see each
    centre; 0 where none does. One pass per camera, vectorised over the Gaussians, in ranges of
    them run in threads (`parallel.in_threads`; the same values)."""
    m = np.asarray(means, np.float64).reshape(-1, 3)
    rate = np.zeros(len(m))

    def part(a: int, b: int) -> None:
        for cam in cameras:
            np.maximum(rate[a:b], _camera_rate(m[a:b], cam, near, margin), out=rate[a:b])

    in_threads(len(m), part)
    return rate


def _filter_from_rate(rate: np.ndarray, variance: float) -> np.ndarray:
    seen = rate > 0.0
    out = np.zeros(len(rate))
    out[seen] = math.sqrt(variance) / rate[seen]
    if seen.any():
        out[~seen] = out[seen].max()
    return out.astype(np.float32)


def filter_3d(means, cameras: Sequence[Camera], *, variance: float = FILTER_3D_VARIANCE,
              near: float = NEAR_PLANE, margin: float = VIEW_MARGIN) -> np.ndarray:
    """(N,) float32 standard deviations sqrt(variance) / nu of Mip-Splatting's 3D filter of
    Gaussians centred at `means` (N,3) for training cameras `cameras` (module docstring)."""
    if not len(cameras):
        raise ValueError("filter_3d: needs at least one training camera")
    return _filter_from_rate(max_sampling_rate(means, cameras, near=near, margin=margin), variance)


def dilation_3d(means, cameras: Sequence[Camera], **options) -> np.ndarray:
    """(N,) float32 standard deviations sqrt(CLASSIC_DILATION) / nu of the classic dilation in
    world units (DILATION_KEY) for training cameras `cameras`."""
    return filter_3d(means, cameras, variance=CLASSIC_DILATION, **options)


def filter_3d_reference(means, cameras: Sequence[Camera], *, variance: float = FILTER_3D_VARIANCE,
                        near: float = NEAR_PLANE, margin: float = VIEW_MARGIN) -> np.ndarray:
    """The same, one Gaussian and one camera at a time through `Camera.project` (slow; for tests)."""
    m = np.asarray(means, np.float64).reshape(-1, 3)
    best = [0.0] * len(m)
    for cam in cameras:
        for i, point in enumerate(m):
            uv, z = cam.project(point[None])
            (u, v), depth = uv[0], float(z[0])
            if not depth > near:
                continue
            if (-margin * cam.width <= u <= (1 + margin) * cam.width
                    and -margin * cam.height <= v <= (1 + margin) * cam.height):
                best[i] = max(best[i], max(cam.fx, cam.fy) / depth)
    sizes = [math.sqrt(variance) / r for r in best if r > 0]
    fill = max(sizes) if sizes else 0.0
    return np.array([math.sqrt(variance) / r if r > 0 else fill for r in best], np.float32)


def _with_size(cloud: GaussianCloud, key: str, sizes: np.ndarray) -> GaussianCloud:
    if cloud.is_torch:
        import torch  # noqa: PLC0415 - only for torch clouds; this module is numpy-only otherwise

        sizes = torch.from_numpy(sizes).to(cloud.means.device)
    return cloud.replace(extra={**cloud.extra, key: sizes})


def _means(cloud: GaussianCloud) -> np.ndarray:
    return cloud.means.detach().cpu().numpy() if cloud.is_torch else np.asarray(cloud.means)


def with_filter_3d(cloud: GaussianCloud, cameras: Sequence[Camera], resolution: int | None = None,
                   **options) -> GaussianCloud:
    """`cloud` (numpy or torch) with Mip-Splatting's `extra[FILTER_KEY]` from its training cameras
    (at image height `resolution` when given): for a cloud trained with the filters. Other extras
    are kept; an existing value is replaced."""
    return _with_size(cloud, FILTER_KEY, filter_3d(_means(cloud), cameras_at_height(cameras, resolution), **options))


def with_dilation_3d(cloud: GaussianCloud, cameras: Sequence[Camera], resolution: int | None = None,
                     **options) -> GaussianCloud:
    """`cloud` with `extra[DILATION_KEY]` from its training cameras: for a cloud trained the
    classic way (the usual 3DGS PLY)."""
    return _with_size(cloud, DILATION_KEY,
                      dilation_3d(_means(cloud), cameras_at_height(cameras, resolution), **options))


def with_training_cameras(cloud: GaussianCloud, cameras: Sequence[Camera], resolution: int | None = None,
                          trained: str = "classic") -> GaussianCloud:
    """`cloud` with the size that its training (`trained`: "classic", the reference 3DGS and the
    default trainer, or "mip", trained with the filters) calls for, from its training cameras (at
    image height `resolution` when given); the other size is dropped. Render it with "auto"."""
    if trained not in ("classic", "mip"):
        raise ValueError(f"trained must be 'classic' or 'mip', got {trained!r}")
    other = DILATION_KEY if trained == "mip" else FILTER_KEY
    cloud = cloud.replace(extra={k: v for k, v in cloud.extra.items() if k != other})
    add = with_filter_3d if trained == "mip" else with_dilation_3d
    return add(cloud, cameras, resolution)
