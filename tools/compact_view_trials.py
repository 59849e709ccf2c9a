"""Which views close the no-photos gap of compaction on a real capture: a trained cloud compacted
(`gvae_core.compaction.compact`, the default otherwise) from views placed around it (the default),
from the capture's training cameras, or from views placed on a sphere or its upper half around the
point the capture's cameras look at (least squares over their optical axes), at their median
distance; each scored on the capture's held-out photos (every 8th by name) as the capture benchmark
scores (`python -m gvae_core.benchmarks.compact --capture`). One thread.

    python tools/compact_view_trials.py CLOUD.ply --capture ../shared/captures/plush placed capture upper-focus
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import torch

from gvae_core.antialias import DILATION_KEY, with_training_cameras
from gvae_core.camera import Camera
from gvae_core.capture import load_cameras, read_capture
from gvae_core.capture.views import fibonacci_lattice
from gvae_core.compaction import compact, fine_tune_height
from gvae_core.ply import read_ply
from gvae_core.rendering import RenderSettings
from gvae_core.train import evaluate_views

TRIALS = ("placed", "capture", "upper-focus", "sphere-focus", "upper-centre")


def focus_of(cams) -> tuple[np.ndarray, np.ndarray, float]:
    """(the point nearest every camera's optical axis, the cameras' mean up direction, their median
    distance from that point)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        d = c.rotation[2]
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ c.center
    focus = np.linalg.solve(a, b)
    up = -np.mean([c.rotation[1] for c in cams], 0)
    return focus, up / np.linalg.norm(up), float(np.median([np.linalg.norm(c.center - focus) for c in cams]))


def sphere(center, radius: float, count: int, upper: bool, fov_deg: float, up) -> list[Camera]:
    """`count` views on a sphere (its upper half, about `up`, when `upper`) looking at `center`."""
    lat = fibonacci_lattice(4 * count if upper else count)
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, up), float(z @ up)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot = np.eye(3) + k + k @ k * ((1 - c) / max(float(v @ v), 1e-12))
    dirs = lat @ rot.T
    if upper:
        dirs = dirs[dirs @ up > 0.15]
    return [Camera.look_at(center + radius * d, center, up, width=256, height=256, fov_x=math.radians(fov_deg))
            for d in dirs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cloud")
    parser.add_argument("--capture", required=True)
    parser.add_argument("--keep", type=float, default=0.5)
    parser.add_argument("trials", nargs="+", choices=TRIALS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    base = read_ply(args.cloud)
    cams = load_cameras(args.capture, 8)
    test = read_capture(args.capture).held_out(8).load("test", fine_tune_height(base, cams))

    def score(c) -> float:
        if DILATION_KEY not in c.extra:
            c = with_training_cameras(c, cams)
        return evaluate_views(c.to_torch(), test, (1.0, 1.0, 1.0), c.sh_degree, None,
                              RenderSettings(antialias="classic"), with_ssim=False)[0]

    before = score(base)
    focus, up, dist = focus_of(cams)
    print(f"input {before:.3f} dB; the cameras look at {focus.round(2)}, median distance {dist:.2f}", flush=True)
    views = {"placed": None, "capture": cams, "upper-focus": sphere(focus, dist, 16, True, 62, up),
             "sphere-focus": sphere(focus, dist, 16, False, 62, up),
             "upper-centre": sphere(base.normalization()[0], dist, 16, True, 62, up)}
    for name in args.trials:
        t, c0 = time.time(), time.process_time()
        value = score(compact(base, keep=args.keep, cameras=views[name]).cloud)
        print(f"{name:14s} {value:.3f} ({value - before:+.2f}) {time.time() - t:.0f} s, CPU "
              f"{time.process_time() - c0:.0f} s, load {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main()
