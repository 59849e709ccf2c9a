"""A texture-rich scene drawn by the project's renderer from known cameras: a photo set for
structure from motion whose true cameras and surface are known.

The scene: a box (1.2 x 0.8 x 0.6) standing on a 3.2 x 3.2 floor, every face covered by small flat
Gaussians coloured by smooth random noise at four scales (SIFT finds blobs and corners at each).
`photo_set(folder)` writes PNG photos taken from a ring of cameras around it and returns the
cameras; `on_surface(points)` is each point's distance to the scene's surfaces; `similarity` the
best similarity between two sets of camera centres, `relative_rotation_errors` how far recovered
cameras turn from true ones."""

from __future__ import annotations

import math

import numpy as np
from PIL import Image

from gvae_core import Camera, GaussianCloud
from gvae_core.conventions import rgb_to_dc
from gvae_core.rendering import render

#: Half-sizes of the box (centred above the origin, standing on z = 0) and the floor's half-width.
BOX = np.array([0.6, 0.4, 0.3])
FLOOR = 1.6
#: The scene's size (its bounding box's diagonal), what "1% of the scene" is measured against.
SCENE_SIZE = float(np.linalg.norm([2 * FLOOR, 2 * FLOOR, 2 * BOX[2]]))


def _noise(uv: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Colours of smooth random noise at cells of 0.6, 0.3, 0.15 and 0.08 (uv in scene units; value
    noise, bilinear between random values at the cells' corners), contrast stretched: blobs and
    edges at every scale, nothing repeated."""
    rgb = np.zeros((len(uv), 3))
    for cell, weight in ((0.6, 1.0), (0.3, 0.8), (0.15, 0.6), (0.08, 0.5)):
        x = uv / cell + 1000.0
        i = np.floor(x).astype(np.int64)
        f = x - i
        f = f * f * (3 - 2 * f)  # smoothstep: no creases at the cell edges
        table = rng.random((263, 257, 3))
        c00, c10 = table[i[:, 0] % 263, i[:, 1] % 257], table[(i[:, 0] + 1) % 263, i[:, 1] % 257]
        c01, c11 = table[i[:, 0] % 263, (i[:, 1] + 1) % 257], table[(i[:, 0] + 1) % 263, (i[:, 1] + 1) % 257]
        rgb += weight * ((c00 * (1 - f[:, :1]) + c10 * f[:, :1]) * (1 - f[:, 1:])
                         + (c01 * (1 - f[:, :1]) + c11 * f[:, :1]) * f[:, 1:])
    lo, hi = np.percentile(rgb, [2, 98], axis=0)
    return np.clip((rgb - lo) / (hi - lo), 0.0, 1.0)


def _face(center, axis_u, axis_v, half_u, half_v, spacing, rng):
    """Flat Gaussians on a rectangle (centre, two in-plane unit axes), jittered grid."""
    nu, nv = int(2 * half_u / spacing), int(2 * half_v / spacing)
    gu, gv = np.meshgrid((np.arange(nu) + 0.5) / nu * 2 - 1, (np.arange(nv) + 0.5) / nv * 2 - 1, indexing="ij")
    u = (gu.ravel() + rng.uniform(-0.3, 0.3, gu.size) / nu) * half_u
    v = (gv.ravel() + rng.uniform(-0.3, 0.3, gv.size) / nv) * half_v
    pts = np.asarray(center) + u[:, None] * np.asarray(axis_u) + v[:, None] * np.asarray(axis_v)
    return pts, np.stack([u, v], 1) + np.asarray(center)[:2] * 7.0


def scene_cloud(seed: int = 0, spacing: float = 0.025) -> GaussianCloud:
    """The box on its floor as a cloud of flat, opaque, noise-coloured Gaussians."""
    rng = np.random.default_rng(seed)
    faces = [((0, 0, 0), (1, 0, 0), (0, 1, 0), FLOOR, FLOOR, 2)]  # floor, normal z
    bx, by, bz = BOX
    faces += [((0, 0, 2 * bz), (1, 0, 0), (0, 1, 0), bx, by, 2),
              ((bx, 0, bz), (0, 1, 0), (0, 0, 1), by, bz, 0), ((-bx, 0, bz), (0, 1, 0), (0, 0, 1), by, bz, 0),
              ((0, by, bz), (1, 0, 0), (0, 0, 1), bx, bz, 1), ((0, -by, bz), (1, 0, 0), (0, 0, 1), bx, bz, 1)]
    means, colours, scales = [], [], []
    for center, au, av, hu, hv, normal in faces:
        pts, uv = _face(center, au, av, hu, hv, spacing, rng)
        s = np.full((len(pts), 3), math.log(0.5 * spacing))
        s[:, normal] = math.log(0.05 * spacing)
        means.append(pts)
        colours.append(_noise(uv, rng))
        scales.append(s)
    means = np.concatenate(means)
    n = len(means)
    return GaussianCloud(means=means.astype(np.float32), scales=np.concatenate(scales).astype(np.float32),
                         quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)), opacities=np.full(n, 4.0, np.float32),
                         sh_dc=rgb_to_dc(np.concatenate(colours)).astype(np.float32),
                         sh_rest=np.zeros((n, 0, 3), np.float32))


def ring_cameras(count: int = 20, width: int = 400, height: int = 300, *, roll: float = 0.0,
                 principal_point: tuple[float, float] = (0.0, 0.0)) -> list[Camera]:
    """`count` cameras on a ring around the box at two heights, each looking near its centre, turned
    about its axis by up to `roll` degrees (a hand-held camera's tilt), its principal point moved by
    `principal_point` times the image's width and height from the centre (a phone's lens)."""
    cams = []
    for k in range(count):
        a = 2 * math.pi * k / count
        r, z = (3.2, 1.8) if k % 2 == 0 else (3.0, 1.3)
        target = (0.15 * math.cos(3 * a), 0.15 * math.sin(2 * a), 0.2)
        cam = Camera.look_at((r * math.cos(a), r * math.sin(a), z), target, width=width, height=height,
                             fov_x=math.radians(62))
        t = math.radians(roll) * math.sin(1.7 * k)
        turn = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
        w2c = cam.world_to_cam.copy()
        w2c[:3] = turn @ w2c[:3]
        cams.append(Camera(w2c, cam.fx, cam.fy, cam.cx + principal_point[0] * width,
                           cam.cy + principal_point[1] * height, width, height))
    return cams


def photo_set(folder, cameras: list[Camera] | None = None, seed: int = 0) -> list[Camera]:
    """Photos of the scene through `cameras` (default `ring_cameras()`) as PNGs in `folder`
    (view_00.png, ...); returns the cameras."""
    cameras = cameras or ring_cameras()
    cloud = scene_cloud(seed).to_torch()
    folder.mkdir(parents=True, exist_ok=True)
    for k, cam in enumerate(cameras):
        image = render(cloud, cam, background=(0.55, 0.6, 0.7)).image.clamp(0, 1).numpy()
        Image.fromarray((image * 255 + 0.5).astype(np.uint8)).save(folder / f"view_{k:02d}.png")
    return cameras


def on_surface(points: np.ndarray) -> np.ndarray:
    """Each point's distance to the scene's surfaces (the floor and the box's faces)."""
    p = np.asarray(points, np.float64)
    outside = np.abs(p[:, :2]).max(1) > FLOOR
    floor = np.where(outside, np.inf, np.abs(p[:, 2]))
    q = np.abs(p - [0, 0, BOX[2]]) - BOX  # signed distance to the box
    box = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)
    return np.minimum(floor, np.abs(box))


def similarity(a: np.ndarray, b: np.ndarray):
    """s, R, t with b ≈ s R a + t (Umeyama's least squares)."""
    ma, mb = a.mean(0), b.mean(0)
    u, sv, vt = np.linalg.svd((b - mb).T @ (a - ma) / len(a))
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt))
    r = u @ d @ vt
    s = np.trace(np.diag(sv) @ d) / ((a - ma) ** 2).sum(1).mean()
    return s, r, mb - s * r @ ma


def relative_rotation_errors(capture, true: dict) -> np.ndarray:
    """Degrees between the recovered and the true relative rotation of every pair of the capture's
    cameras that `true` (name -> Camera) holds."""
    rot = {n: c.rotation for n, c in zip(capture.names, capture.cameras)}
    names = [n for n in capture.names if n in true]
    out = []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            d = (true[names[j]].rotation @ true[names[i]].rotation.T) @ (rot[names[j]] @ rot[names[i]].T).T
            out.append(math.degrees(math.acos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return np.array(out)
