"""A small deterministic example cloud: a rainbow torus of flat Gaussians with SH degree 3.

`python -m gvae_core.examples OUT.ply` writes it; `gvae demo` uses it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .cloud import GaussianCloud
from .conventions import rgb_to_dc
from .ply import write_ply
from .quaternions import from_rotmat

__all__ = ["example_cloud", "random_cloud", "write_example", "shape_cloud", "SHAPES"]


def example_cloud(n: int = 4096, *, seed: int = 0, radius: float = 1.0, tube: float = 0.35) -> GaussianCloud:
    """`n` Gaussians on a torus around the z axis (numpy, float32, SH degree 3).

    Each Gaussian is a flat disc tangent to the surface; the base colour cycles through the hues
    around the ring and the degree-1 SH terms make surfaces facing the viewer brighter."""
    rng = np.random.default_rng(seed)
    # Even coverage: a Fibonacci-like lattice on the (u, v) torus angles, jittered slightly.
    k = np.arange(n)
    u = 2 * np.pi * (k / n + rng.uniform(-0.1, 0.1, n) / n)
    v = 2 * np.pi * ((k * 0.6180339887498949) % 1.0)
    ring = radius + tube * np.cos(v)
    means = np.stack([ring * np.cos(u), ring * np.sin(u), tube * np.sin(v)], 1)
    normal = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    t_u = np.stack([-np.sin(u), np.cos(u), np.zeros(n)], 1)
    t_v = np.cross(normal, t_u)
    rot = np.stack([t_u, t_v, normal], 2)  # columns: local axes (flat along the normal)
    area = 4 * np.pi ** 2 * radius * tube / n
    spacing = np.sqrt(area)
    scales = np.log(spacing * np.array([0.6, 0.6, 0.05])) + rng.normal(0.0, 0.15, (n, 3))
    hue = u / (2 * np.pi)
    rgb = np.clip(np.abs((hue[:, None] * 6 + np.array([0.0, 4.0, 2.0])) % 6 - 3) - 1, 0, 1)
    rgb = 0.15 + 0.7 * rgb
    sh_dc = rgb_to_dc(rgb)
    sh_rest = np.zeros((n, 15, 3))
    # Degree-1 basis functions are -y, z, -x (times a constant) of the direction d from the camera
    # to the Gaussian: these coefficients add -0.3*C1*(d . normal), brighter where it faces the camera.
    sh_rest[:, 0, :] = 0.3 * normal[:, 1:2]
    sh_rest[:, 1, :] = -0.3 * normal[:, 2:3]
    sh_rest[:, 2, :] = 0.3 * normal[:, 0:1]
    sh_rest[:, 3:, :] = rng.normal(0.0, 0.02, (n, 12, 3))
    opacities = np.full(n, 2.0) + rng.normal(0.0, 0.2, n)
    return GaussianCloud(
        means=means.astype(np.float32), scales=scales.astype(np.float32),
        quats=from_rotmat(rot).astype(np.float32), opacities=opacities.astype(np.float32),
        sh_dc=sh_dc.astype(np.float32), sh_rest=sh_rest.astype(np.float32))


def random_cloud(n: int, seed: int = 0) -> GaussianCloud:
    """`n` random SH-3 Gaussians (standard-normal parameters, log-scales around -4): the
    cloud the speed benchmarks read, write, import and export."""
    rng = np.random.default_rng(seed)

    def f(*shape):
        return rng.standard_normal(shape, dtype=np.float32)

    return GaussianCloud(means=f(n, 3), scales=f(n, 3) - 4, quats=f(n, 4), opacities=f(n),
                         sh_dc=f(n, 3), sh_rest=f(n, 15, 3) * 0.1)


# ------------------------------------------------------------------ shapes that fool placed views

#: The clouds `shape_cloud` makes: closed shells (views inside them see nothing of their surface),
#: objects whose detail is only underneath or on one side (views from above or one side miss it),
#: a room seen from inside and an object inside a distant background (views outside them see
#: only the outside of their walls).
SHAPES = ("sphere", "head", "box", "underside", "one-sided", "room", "unbounded")


def _discs(points, normals, size, rng, opacity: float = 5.0, jitter: float = 0.3) -> dict:
    """Flat discs of `size` (standard deviation along the surface) tangent to the surface at
    `points`, jittered by `jitter` sizes along the normal, as 3DGS lays a surface down (a layer
    a Gaussian or two thick); random colours."""
    n = len(points)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    size = np.broadcast_to(np.asarray(size, np.float64), (n,))
    means = points + normals * (jitter * size * rng.normal(size=n))[:, None]
    scales = np.log(size[:, None] * np.array([1.0, 1.0, 0.1])) + rng.normal(0.0, 0.1, (n, 3))
    return {"means": means, "scales": scales, "quats": from_rotmat(np.stack([t1, t2, normals], 2)),
            "opacities": opacity + rng.normal(0.0, 0.3, n), "rgb": rng.uniform(0.1, 0.9, (n, 3))}


def _blobs(centres, size, rng, opacity: float = -1.0) -> dict:
    """Round, faint Gaussians (a trained cloud's floaters)."""
    n = len(centres)
    return {"means": centres, "scales": np.full((n, 3), np.log(size)) + rng.normal(0.0, 0.2, (n, 3)),
            "quats": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), "opacities": opacity + rng.normal(0.0, 0.5, n),
            "rgb": rng.uniform(0.1, 0.9, (n, 3))}


def _ellipsoid(n, axes, centre, rng):
    """`n` points on an ellipsoid's surface (about evenly by area) and its normals."""
    axes = np.asarray(axes, np.float64)
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    normal = d / axes  # the gradient of |x / axes|^2 at x = axes * d
    weight = np.linalg.norm(normal * np.prod(axes), axis=1)  # area element relative to the sphere's
    pick = rng.choice(len(d), n, replace=False, p=weight / weight.sum())
    return centre + d[pick] * axes, normal[pick]


def _box(n, lo, hi, rng, faces=(0, 1, 2, 3, 4, 5)):
    """`n` points on the `faces` (-x, +x, -y, +y, -z, +z) of an axis-aligned box, evenly by area,
    and their outward normals."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = hi - lo
    areas = np.array([size[(f // 2 + 1) % 3] * size[(f // 2 + 2) % 3] for f in faces])
    face = np.asarray(faces)[rng.choice(len(faces), n, p=areas / areas.sum())]
    p = lo + rng.random((n, 3)) * size
    axis = face // 2
    p[np.arange(n), axis] = np.where(face % 2 == 1, hi[axis], lo[axis])
    normal = np.zeros((n, 3))
    normal[np.arange(n), axis] = np.where(face % 2 == 1, 1.0, -1.0)
    return p, normal


def _spacing(area: float, n: int) -> float:
    return float(np.sqrt(area / max(n, 1)))


def shape_cloud(kind: str, n: int = 6000, *, seed: int = 0) -> GaussianCloud:
    """About `n` Gaussians (SH degree 0) laid on one of SHAPES, in a frame where the object
    spans about [-1, 1] (the room and the background are larger):

    - "sphere", "head" (an ellipsoid with a nose, ears and a neck), "box": closed shells with a
      few faint floaters inside (8%), as training leaves them;
    - "underside": a plate on a stem whose fine detail (small bumps) is all on its underside;
    - "one-sided": an upright plaque with fine relief on one face only;
    - "room": floor, walls and ceiling (two layers: opaque) of a 6 x 6 x 3 room around a table,
      chairs, a lamp and a shelf standing on the floor (we are inside: the walls' Gaussians are
      coarser, as a capture made from inside trains them);
    - "unbounded": an object (the torus of `example_cloud`) inside a coarse background shell
      ten times its size (a capture of an object with its surroundings)."""
    if kind not in SHAPES:
        raise ValueError(f"shape_cloud: kind must be one of {', '.join(SHAPES)}, got {kind!r}")
    rng = np.random.default_rng(seed)
    if kind in ("sphere", "head", "box"):
        parts = _shell_parts(kind, n, rng)
    elif kind == "underside":
        parts = _underside_parts(n, rng)
    elif kind == "one-sided":
        parts = _one_sided_parts(n, rng)
    elif kind == "room":
        parts = _room_parts(n, rng)
    else:
        parts = _unbounded_parts(n, rng, seed)
    cat = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
    m = len(cat["means"])
    return GaussianCloud(means=cat["means"].astype(np.float32), scales=cat["scales"].astype(np.float32),
                         quats=cat["quats"].astype(np.float32), opacities=cat["opacities"].astype(np.float32),
                         sh_dc=rgb_to_dc(cat["rgb"]).astype(np.float32), sh_rest=np.zeros((m, 0, 3), np.float32))


def _shell_parts(kind: str, n: int, rng) -> list[dict]:
    """A closed shell (sphere, box or head) and the faint floaters inside it."""
    shell = int(0.92 * n)
    if kind == "sphere":
        p, nrm = _ellipsoid(shell, (1.0, 1.0, 1.0), np.zeros(3), rng)
        area = 4 * np.pi
    elif kind == "box":
        p, nrm = _box(shell, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), rng)
        area = 24.0
    else:  # a head: skull, nose, two ears and a neck below
        counts = (np.array([0.72, 0.06, 0.06, 0.06, 0.10]) * shell).astype(int)
        parts_of_head = (((0.75, 0.85, 1.0), (0.0, 0.0, 0.15)), ((0.12, 0.15, 0.25), (0.0, -0.85, 0.05)),
                         ((0.1, 0.18, 0.28), (-0.78, 0.05, 0.1)), ((0.1, 0.18, 0.28), (0.78, 0.05, 0.1)),
                         ((0.35, 0.35, 0.45), (0.0, 0.1, -0.85)))
        ps, ns = [], []
        for (axes, centre), k in zip(parts_of_head, counts):
            a, b = _ellipsoid(k, axes, np.array(centre), rng)
            ps.append(a)
            ns.append(b)
        p, nrm = np.concatenate(ps), np.concatenate(ns)
        area = 10.0
    parts = [_discs(p, nrm, _spacing(area, shell), rng)]
    inner = rng.normal(size=(n - shell, 3))
    parts.append(_blobs(0.35 * inner / np.maximum(np.linalg.norm(inner, axis=1, keepdims=True), 1.0), 0.08, rng))
    return parts


def _underside_parts(n: int, rng) -> list[dict]:
    """A plate on a stem, its fine detail (small bumps) all on its underside."""
    top, detail, stem = int(0.25 * n), int(0.6 * n), n - int(0.25 * n) - int(0.6 * n)
    p, nrm = _box(top, (-1.0, -1.0, 0.25), (1.0, 1.0, 0.3), rng)  # an opaque slab: light passes no face
    parts = [_discs(p, nrm, _spacing(8.2, top), rng)]
    bumps = 40
    rb = 0.85 * np.sqrt(rng.random(bumps))
    tb = rng.random(bumps) * 2 * np.pi
    centres = np.stack([rb * np.cos(tb), rb * np.sin(tb), np.full(bumps, 0.25)], 1)
    d = rng.normal(size=(detail, 3))
    d[:, 2] = -np.abs(d[:, 2])  # the lower half of each bump
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    which = rng.integers(0, bumps, detail)
    parts.append(_discs(centres[which] + 0.08 * d, d, _spacing(bumps * 2 * np.pi * 0.08 ** 2, detail), rng))
    h = rng.random(stem) * 1.2 - 1.0
    a = rng.random(stem) * 2 * np.pi
    nrm = np.stack([np.cos(a), np.sin(a), np.zeros(stem)], 1)
    parts.append(_discs(nrm * 0.12 + np.stack([np.zeros(stem), np.zeros(stem), h], 1), nrm,
                        _spacing(2 * np.pi * 0.12 * 1.2, stem), rng))
    return parts


def _one_sided_parts(n: int, rng) -> list[dict]:
    """An upright plaque with fine relief on its -y face only."""
    back, relief = int(0.3 * n), n - int(0.3 * n)
    p, nrm = _box(back, (-1.0, -0.05, -1.0), (1.0, 0.05, 1.0), rng)
    parts = [_discs(p, nrm, _spacing(8.4, back), rng)]
    cells = rng.random((relief, 2)) * 2 - 1
    bump = 0.06 * np.sin(9 * cells[:, 0]) * np.cos(7 * cells[:, 1])  # fine relief on the -y face
    p = np.stack([cells[:, 0], -0.05 - 0.06 - bump, cells[:, 1]], 1)
    nrm = np.stack([-0.06 * 9 * np.cos(9 * cells[:, 0]) * np.cos(7 * cells[:, 1]), -np.ones(relief),
                    0.06 * 7 * np.sin(9 * cells[:, 0]) * np.sin(7 * cells[:, 1])], 1)
    parts.append(_discs(p, nrm, _spacing(4.0, relief), rng))
    return parts


def _room_parts(n: int, rng) -> list[dict]:
    """A room's two-layer walls, floor and ceiling, facing in, and the furniture standing on its floor."""
    walls, things = int(0.45 * n), n - int(0.45 * n)
    parts = []
    for grow in (0.0, 0.1):  # two layers: no light passes the walls
        p, nrm = _box(walls // 2, (-3.0 - grow, -3.0 - grow, -grow), (3.0 + grow, 3.0 + grow, 3.0 + grow), rng)
        parts.append(_discs(p, -nrm, _spacing(108.0, walls // 2), rng))  # coarser than the things, facing in
    pieces = [((-0.8, -0.5, 0.0), (0.8, 0.5, 0.75)), ((-0.4, 0.8, 0.0), (0.1, 1.3, 0.9)),
              ((0.3, -1.4, 0.0), (0.8, -0.9, 0.9)), ((1.8, 1.6, 0.0), (2.1, 1.9, 1.7)),
              ((-2.6, -1.0, 0.0), (-2.0, 1.0, 0.8))]
    per = things // len(pieces)
    for lo, hi in pieces:
        p, nrm = _box(per, lo, hi, rng, faces=(0, 1, 2, 3, 5))
        parts.append(_discs(p, nrm, _spacing(4.0, per), rng))
    return parts


def _unbounded_parts(n: int, rng, seed: int) -> list[dict]:
    """The torus of `example_cloud` inside a coarse background shell ten times its size."""
    obj = example_cloud(int(0.4 * n), seed=seed).with_sh_degree(0)
    parts = [{"means": obj.means.astype(np.float64), "scales": obj.scales.astype(np.float64),
              "quats": obj.quats.astype(np.float64), "opacities": obj.opacities.astype(np.float64),
              "rgb": np.clip(0.28209479177387814 * obj.sh_dc + 0.5, 0, 1)}]
    k = n - len(obj)
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radius = 12.0 * (1.0 + 0.3 * rng.random(k))[:, None]
    parts.append(_discs(d * radius, -d, _spacing(4 * np.pi * 144.0, k), rng, jitter=3.0))
    return parts


def write_example(path, n: int = 4096, *, seed: int = 0) -> Path:
    """Write `example_cloud(n, seed=seed)` as a PLY file at `path` (folders created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_ply(example_cloud(n, seed=seed), path)


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "examples/example.ply"
    print(write_example(out))
