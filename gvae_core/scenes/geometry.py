"""Procedural mesh generators in numpy (no bpy): each returns `(verts (V,3) float64, faces list)`
with faces as vertex-index tuples (quads or triangles), ready for `Mesh.from_pydata`. Keeping
the shapes here makes them deterministic and testable without Blender."""

from __future__ import annotations

import numpy as np

Mesh = tuple[np.ndarray, list[tuple[int, ...]]]


def _frames(path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-minimising normal/binormal along a polyline (double reflection would be overkill
    for these short, smooth paths: parallel transport of one normal is enough)."""
    tang = np.gradient(path, axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
    ref = np.array([1.0, 0.0, 0.0]) if abs(tang[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(tang[0], ref)
    n /= np.linalg.norm(n)
    normals = np.empty_like(path)
    for i, t in enumerate(tang):
        n = n - np.dot(n, t) * t
        norm = np.linalg.norm(n)
        if norm < 1e-9:  # tangent turned onto the previous normal: pick any perpendicular
            n = np.cross(t, ref)
            norm = np.linalg.norm(n)
        n = n / norm
        normals[i] = n
    return normals, np.cross(tang, normals)


def tube(path, radius, segments: int = 8, caps: bool = True) -> Mesh:
    """A tube of `segments` sides swept along the polyline `path` (P,3); `radius` is a scalar or
    one radius per path point (a taper)."""
    path = np.asarray(path, np.float64)
    radii = np.broadcast_to(np.asarray(radius, np.float64), (len(path),))
    normals, binormals = _frames(path)
    ang = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.cos(ang)[None, :, None] * normals[:, None] + np.sin(ang)[None, :, None] * binormals[:, None]
    verts = (path[:, None] + radii[:, None, None] * ring).reshape(-1, 3)
    faces: list[tuple[int, ...]] = []
    for i in range(len(path) - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            faces.append((a, b, b + segments, a + segments))
    if caps:
        verts = np.vstack([verts, path[0], path[-1]])
        c0, c1 = len(verts) - 2, len(verts) - 1
        last = (len(path) - 1) * segments
        for j in range(segments):
            faces.append((c0, (j + 1) % segments, j))
            faces.append((c1, last + j, last + (j + 1) % segments))
    return verts, faces


def lathe(profile, segments: int = 48) -> Mesh:
    """Revolve a profile of (radius, z) points around the z axis. Points with radius 0 become
    single pole vertices, so closed solids (spheres, bowls with a bottom) have no holes. Faces
    point outwards when the profile runs from bottom to top on the outside."""
    prof = np.asarray(profile, np.float64)
    ang = 2.0 * np.pi * np.arange(segments) / segments
    verts: list[np.ndarray] = []
    rings: list[list[int] | int] = []
    for r, z in prof:
        if r <= 1e-9:
            rings.append(len(verts))
            verts.append(np.array([0.0, 0.0, z]))
        else:
            start = len(verts)
            verts.extend(np.stack([r * np.cos(ang), r * np.sin(ang), np.full(segments, z)], 1))
            rings.append(list(range(start, start + segments)))
    faces: list[tuple[int, ...]] = []
    for lo, hi in zip(rings[:-1], rings[1:]):
        for j in range(segments):
            k = (j + 1) % segments
            if isinstance(lo, int) and isinstance(hi, int):
                continue
            if isinstance(lo, int):
                faces.append((lo, hi[k], hi[j]))
            elif isinstance(hi, int):
                faces.append((lo[j], lo[k], hi))
            else:
                faces.append((lo[j], lo[k], hi[k], hi[j]))
    return np.asarray(verts), faces


def box(size, center=(0.0, 0.0, 0.0)) -> Mesh:
    """An axis-aligned box with full extents `size` (3,) centred at `center`."""
    half = np.asarray(size, np.float64) / 2.0
    corners = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], np.float64)
    verts = corners * half + np.asarray(center, np.float64)
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return verts, faces


def uv_sphere(radius: float, center=(0.0, 0.0, 0.0), rings: int = 16, segments: int = 32, squash=(1, 1, 1)) -> Mesh:
    """A UV sphere (optionally an ellipsoid through `squash`)."""
    t = np.linspace(0.0, np.pi, rings + 1)
    verts, faces = lathe(np.stack([radius * np.sin(t), -radius * np.cos(t)], 1), segments)
    return verts * np.asarray(squash, np.float64) + np.asarray(center, np.float64), faces


def cylinder(radius: float, z0: float, z1: float, center_xy=(0.0, 0.0), segments: int = 16) -> Mesh:
    """A closed cylinder along z from z0 to z1."""
    verts, faces = lathe([(0.0, z0), (radius, z0), (radius, z1), (0.0, z1)], segments)
    verts[:, :2] += np.asarray(center_xy, np.float64)
    return verts, faces


def leaf(length: float, width: float, fold: float = 0.25, curl: float = 0.3, nu: int = 8, nv: int = 4) -> Mesh:
    """An open leaf blade in its own frame: base at the origin, pointing along +x, lying near
    the xy plane, folded along the midrib and curled downwards towards the tip."""
    u = np.linspace(0.0, 1.0, nu + 1)
    v = np.linspace(-1.0, 1.0, 2 * nv + 1)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    half_width = width / 2.0 * np.sin(np.pi * np.clip(uu, 0.0, 1.0)) ** 0.8
    x = length * uu
    y = vv * half_width
    z = fold * np.abs(y) - curl * length * uu**2
    verts = np.stack([x, y, z], -1).reshape(-1, 3)
    cols = 2 * nv + 1
    faces = [(i * cols + j, i * cols + j + 1, (i + 1) * cols + j + 1, (i + 1) * cols + j)
             for i in range(nu) for j in range(cols - 1)]
    return verts, faces


def transform(mesh: Mesh, matrix) -> Mesh:
    """Apply a 4x4 affine matrix to a mesh's vertices."""
    verts, faces = mesh
    m = np.asarray(matrix, np.float64)
    return verts @ m[:3, :3].T + m[:3, 3], faces


def merge(*meshes: Mesh) -> Mesh:
    """Concatenate meshes into one (faces re-indexed)."""
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(np.asarray(v, np.float64))
        faces.extend(tuple(i + offset for i in face) for face in f)
        offset += len(v)
    return np.vstack(verts), faces


def rotation(axis, angle: float) -> np.ndarray:
    """4x4 rotation about a unit axis through the origin (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
    return m


def translation(offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = offset
    return m


def triangulate(faces) -> np.ndarray:
    """Fan-triangulate polygons into an (F,3) int array."""
    tris = [(f[0], f[i], f[i + 1]) for f in faces for i in range(1, len(f) - 1)]
    return np.asarray(tris, np.int64).reshape(-1, 3)


def sample_surface(verts, tris, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`n` points uniformly distributed by area on a triangle mesh; returns points and the index
    of the triangle each lies on."""
    v = np.asarray(verts, np.float64)[np.asarray(tris)]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    if area.sum() <= 0:
        raise ValueError("sample_surface: the mesh has no area")
    idx = rng.choice(len(v), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("nk,nkd->nd", w, v[idx]), idx
