"""Camera placement for the benchmark scenes (numpy only): views on the upper hemisphere looking
at the origin, z up, as Blender camera-to-world matrices (the NeRF-Synthetic convention)."""

from __future__ import annotations

import math

import numpy as np

from ..camera import Camera

# NeRF-Synthetic's horizontal field of view and camera distance.
CAMERA_ANGLE_X = 0.6911112070083618
RADIUS = 4.0311289
# Anything within this distance of the origin is inside every view: asin(1.3 / RADIUS) is below
# half the field of view.
OBJECT_RADIUS = 1.3


def _look(eye: np.ndarray) -> np.ndarray:
    return Camera.look_at(eye, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width=2, height=2,
                          fov_x=CAMERA_ANGLE_X).to_blender_c2w()


def _direction(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.sin(elevation)], 1)


def train_views(n: int, seed: int, radius: float = RADIUS, min_elevation: float = math.radians(6.0),
                max_elevation: float = math.radians(80.0)) -> np.ndarray:
    """`n` (n,4,4) camera-to-world matrices spread evenly over a band of the upper hemisphere:
    a Fibonacci spiral (equal area per view) with a seed-dependent azimuth offset and jitter."""
    rng = np.random.default_rng([seed, 1])
    k = np.arange(n) + 0.5
    lo, hi = math.sin(min_elevation), math.sin(max_elevation)
    s = lo + (hi - lo) * (k + rng.uniform(-0.3, 0.3, n)) / n  # sin(elevation), uniform in area
    elevation = np.arcsin(np.clip(s, lo, hi))
    azimuth = rng.uniform(0, 2 * math.pi) + math.pi * (3.0 - math.sqrt(5.0)) * np.arange(n)
    eyes = radius * _direction(azimuth, elevation)
    return np.stack([_look(e) for e in eyes]) if n else np.zeros((0, 4, 4))


def test_views(n: int, seed: int, radius: float = RADIUS) -> np.ndarray:
    """`n` camera-to-world matrices on a closed spiral path around the object (elevation 15..45
    degrees, two oscillations per turn), like NeRF-Synthetic's test trajectory."""
    rng = np.random.default_rng([seed, 2])
    t = np.arange(n) / max(n, 1)
    azimuth = rng.uniform(0, 2 * math.pi) + 2 * math.pi * t
    elevation = math.radians(30.0) + math.radians(15.0) * np.sin(4 * math.pi * t)
    eyes = radius * _direction(azimuth, elevation)
    return np.stack([_look(e) for e in eyes]) if n else np.zeros((0, 4, 4))
