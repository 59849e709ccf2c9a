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

__all__ = ["example_cloud", "random_cloud", "write_example"]


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


def write_example(path, n: int = 4096, *, seed: int = 0) -> Path:
    """Write `example_cloud(n, seed=seed)` as a PLY file at `path` (folders created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_ply(example_cloud(n, seed=seed), path)


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "examples/example.ply"
    print(write_example(out))
