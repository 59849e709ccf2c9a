"""Where training starts: the Gaussians of the first stage, from the capture's points or its images.

- `sfm`: the capture's structure-from-motion points, position and colour (the reference 3DGS's
  start for a COLMAP capture), with random points along the training rays where they leave pixels
  uncovered (a white wall has no SfM points, and a pixel no Gaussian reaches is a pixel no
  gradient can fix);
- `hull`: random points inside the visual hull of the training images' alpha masks, coloured
  from the images (an object on a transparent background, NeRF-Synthetic);
- `random`: random points over what the cameras see: along the rays of random training pixels
  (opaque ones), each with its pixel's colour, half of them where the cameras look (within the
  sphere every camera sees there, the reference's cube for NeRF-Synthetic) and half at depths
  uniform in inverse depth between a near and a far distance, so every training pixel's ray meets
  the start (not a cube around the object alone: a room around it is not inside one);
- `auto` (the default): `sfm` when the capture has points, else `hull` when the images have
  transparent pixels, else `random`.

Every start is a cloud of isotropic Gaussians with the reference's scales (the mean squared
distance to the three nearest neighbours), identity rotations and opacity `init_opacity`.
`coverage` says how many of the training pixels it reaches. numpy (and the renderer, for
`coverage` and the fill).
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera, look_target
from .cloud import GaussianCloud
from .conventions import SH_REST_COUNTS, opacity_logit, rgb_to_dc
from .datasets import Views

__all__ = ["INIT_MODES", "initial_bounds", "hull_points", "ray_points", "initial_cloud", "start_points", "coverage",
           "has_masks", "NEAR", "FAR", "COVERED_ALPHA"]

INIT_MODES = ("auto", "sfm", "hull", "random")
#: Random points lie between NEAR and FAR times each camera's distance to where the cameras look.
NEAR, FAR = 0.2, 4.0
#: A pixel is covered where the start's accumulated opacity reaches this (one Gaussian at a tenth
#: of its peak, with the reference's initial opacity 0.1).
COVERED_ALPHA = 0.01


def initial_bounds(cameras: list[Camera]) -> tuple[np.ndarray, float]:
    """Centre and half-size of a cube every camera sees: around where the optical axes meet,
    as large as the sphere that fits in the narrowest view (1.3 for NeRF-Synthetic, whose
    random initialisation the reference draws from [-1.3, 1.3]^3)."""
    target = look_target(cameras)
    half = min(float(np.linalg.norm(c.center - target)) * math.sin(0.5 * min(c.fov_x, c.fov_y))
               for c in cameras)
    return target, max(half, 1e-6)


def has_masks(views: Views, threshold: float = 0.999) -> bool:
    """Whether the images have transparent pixels (an object on a transparent background)."""
    return bool((views.alphas < threshold).any())


def hull_points(views: Views, count: int, rng: np.random.Generator, threshold: float = 0.1,
                max_rounds: int = 8) -> np.ndarray:
    """Up to `count` random points of `initial_bounds` inside the visual hull of the views'
    alpha masks (a point is carved away when a view that sees it has alpha <= threshold there),
    with the mean colour of the pixels they project to: (M,6) xyz + RGB."""
    center, half = initial_bounds(views.cameras)
    found, total, rate = [], 0, 0.05
    for _ in range(max_rounds):
        m = int(min(max(1.3 * (count - total) / rate, 1000), 2_000_000))
        cand = center + (rng.random((m, 3)) * 2.0 - 1.0) * half
        rgb_sum = np.zeros((m, 3))
        seen = np.zeros(m)
        alive = np.arange(m)
        for cam, img, alpha in zip(views.cameras, views.images, views.alphas):
            uv, z = cam.project(cand[alive])
            with np.errstate(invalid="ignore"):
                col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
                inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
            r, c = row[inside].astype(np.int64), col[inside].astype(np.int64)
            idx = alive[inside]
            rgb_sum[idx] += img[r, c]
            seen[idx] += 1
            carved = np.zeros(len(alive), bool)
            carved[np.flatnonzero(inside)[alpha[r, c] <= threshold]] = True
            alive = alive[~carved]
        alive = alive[seen[alive] > 0]
        rate = max(len(alive) / m, 1e-4)
        found.append(np.concatenate([cand[alive], rgb_sum[alive] / seen[alive, None]], 1))
        total += len(alive)
        if total >= count:
            break
    return np.concatenate(found)[:count]


def _depth_range(views: Views) -> np.ndarray:
    """(N, 4) per view: near and far depths (NEAR and FAR times its distance d to where the cameras
    look), d, and the half-depth of the sphere every camera sees there (`initial_bounds`)."""
    target, half = initial_bounds(views.cameras)
    d = np.array([max(float(np.linalg.norm(c.center - target)), 1e-6) for c in views.cameras])
    return np.stack([NEAR * d, FAR * d, d, np.minimum(half, (1.0 - NEAR) * d)], 1)


def ray_points(views: Views, count: int, rng: np.random.Generator, depths: np.ndarray | None = None,
               weights: np.ndarray | None = None) -> np.ndarray:
    """`count` points along the rays of random training pixels, at depths uniform in inverse depth
    between each view's near and far (`depths` (N, 2)), or by default (`_depth_range`, (N, 4)) half
    of them so and half within the sphere every camera sees where they look, each with its
    pixel's colour: (count, 6) xyz + RGB. `weights` (N, H, W): where to draw pixels from (default
    the images' alpha: every pixel of a photo alike, none where a transparent image shows nothing)."""
    n, h, w = views.images.shape[:3]
    depths = _depth_range(views) if depths is None else np.asarray(depths, np.float64)
    p = np.asarray(views.alphas if weights is None else weights, np.float64).reshape(-1)
    flat = rng.choice(n * h * w, count, p=p / p.sum()) if p.sum() > 0 else rng.integers(0, n * h * w, count)
    v, rest = np.divmod(flat, h * w)
    row, col = np.divmod(rest, w)
    near, far = depths[v, 0], depths[v, 1]
    z = 1.0 / (1.0 / far + rng.random(count) * (1.0 / near - 1.0 / far))
    if depths.shape[1] == 4:  # half of them where the cameras look, within the sphere they all see
        there = rng.random(count) < 0.5
        z[there] = depths[v[there], 2] + (2.0 * rng.random(int(there.sum())) - 1.0) * depths[v[there], 3]
    xyz = np.empty((count, 3))
    for k in np.unique(v):
        sel = v == k
        cam = views.cameras[k]
        x = (col[sel] + rng.random(sel.sum()) - cam.cx) / cam.fx * z[sel]
        y = (row[sel] + rng.random(sel.sum()) - cam.cy) / cam.fy * z[sel]
        xyz[sel] = (np.stack([x, y, z[sel]], 1) - cam.translation) @ cam.rotation
    return np.concatenate([xyz, views.images[v, row, col]], 1)


def initial_cloud(config, points, rng: np.random.Generator | None = None) -> GaussianCloud:
    """The start from `points` ((N,3), or (N,6) with RGB in [0,1]): isotropic scales from the
    mean squared distance to the 3 nearest neighbours, identity rotations, opacity
    `config.init_opacity`, SH degree `config.sh_degree` (only the DC term set)."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (3, 6) or len(pts) == 0 or not np.isfinite(pts).all():
        raise ValueError(f"initial points must be a finite (N,3) or (N,6) array, got shape {pts.shape}")
    xyz = pts[:, :3]
    dc = rgb_to_dc(pts[:, 3:6]) if pts.shape[1] == 6 else np.zeros((len(pts), 3))
    n = len(xyz)
    k = min(4, n)
    if k > 1:
        from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import; only this step needs it

        dist, _ = cKDTree(xyz).query(xyz, k=k)
        d2 = np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), 1e-7)
    else:
        d2 = np.full(n, 1e-2)
    return GaussianCloud(
        means=xyz.astype(np.float32),
        scales=np.repeat(0.5 * np.log(d2)[:, None], 3, 1).astype(np.float32),
        quats=np.tile(np.array([1.0, 0, 0, 0], np.float32), (n, 1)),
        opacities=np.full(n, opacity_logit(config.init_opacity), np.float32),
        sh_dc=dc.astype(np.float32),
        sh_rest=np.zeros((n, SH_REST_COUNTS[config.sh_degree], 3), np.float32),
    )


def coverage(cloud: GaussianCloud, views: Views) -> np.ndarray:
    """(N, H, W) bool: the training pixels `cloud` reaches (accumulated opacity >= COVERED_ALPHA)."""
    from .rendering import RenderSettings, render  # noqa: PLC0415 - torch only for this

    import torch  # noqa: PLC0415

    dev = cloud.to_torch()
    with torch.no_grad():
        return np.stack([render(dev, cam, settings=RenderSettings()).alpha.numpy() >= COVERED_ALPHA
                         for cam in views.cameras])


def start_points(views: Views, config, rng: np.random.Generator, sfm=None) -> tuple[np.ndarray, str]:
    """The points training starts from (module docstring) for `config.init` and what was used: (M, 6)
    xyz + RGB and a one-line description. `views`: the first stage's training views; `sfm`: the
    capture's SfM points (`capture.SfMPoints`) or None."""
    mode, why = config.init, " (asked for)"
    if mode == "auto":
        if sfm is not None and len(sfm):
            mode, why = "sfm", ""
        elif has_masks(views):
            mode, why = "hull", " (no SfM points; the images have transparent pixels)"
        else:
            mode, why = "random", " (no SfM points and no masks: a fallback, far behind an SfM start on photos)"
    if mode == "sfm":
        if sfm is None or not len(sfm):
            raise ValueError("--init sfm: the capture has no SfM points (a COLMAP model's points3D, or nerfstudio's "
                             "ply_file_path)")
        pts = np.concatenate([sfm.xyz, sfm.rgb], 1)
        return _fill(pts, views, config, rng, f"{len(pts)} {getattr(sfm, 'source', 'SfM points')}")
    if mode == "hull":
        pts = hull_points(views, config.init_count, rng)
        if len(pts):
            return pts, f"{len(pts)} random points in the visual hull of the masks{why}"
        mode, why = "random", " (the masks' hull is empty)"
    return ray_points(views, config.init_count, rng), f"{config.init_count} random points along the training " \
        f"rays{why}"


def _fill(points: np.ndarray, views: Views, config, rng: np.random.Generator, what: str) -> tuple[np.ndarray, str]:
    """`points` and, where their start leaves training pixels uncovered, random points along those
    pixels' rays (one per uncovered pixel up to `config.init_count`), between the depths at which
    the points lie in each view."""
    covered = coverage(initial_cloud(config, points), views)
    missing = ~covered
    if not missing.any():
        return points, what
    depths = np.empty((len(views), 2))
    default = _depth_range(views)
    for k, cam in enumerate(views.cameras):
        _, z = cam.project(points[:, :3])
        z = z[z > 0.01]
        depths[k] = np.percentile(z, [5.0, 95.0]) if len(z) >= 10 else default[k]
    count = int(min(missing.sum(), config.init_count))
    extra = ray_points(views, count, rng, depths, weights=missing)
    return np.concatenate([points, extra]), f"{what} and {count} random points along the rays of the " \
        f"{missing.mean():.1%} of training pixels they leave uncovered"
