"""The compiled renderer's training step by stage beside the yardstick rasteriser (a plain C forward
pass at the machine's limit, kept outside the project in ../shared/yardstick), in one run on the
yardstick's standard scene and camera (100k flat Gaussians on two tori, SH 3, 800x800): the figures
of docs/benchmarks/kernels.md "Against the yardstick, by stage".

The yardstick is compiled here (gcc -O3 -march=native -fopenmp -ffast-math) and fed by its own
prep.py; its time is binning + compositing (its projection is numpy, outside the timing). The
project's rows are `render` with kernels="compiled" and the backward pass of a per-pixel weighted
sum to all six raw parameter tensors, each stage timed where it is called (medians over repeats).

Usage: python tools/yardstick_stages.py [--yardstick ../shared/yardstick] [--threads 2] [--repeats 10]
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gvae_core.camera import Camera  # noqa: E402
from gvae_core.cloud import GaussianCloud  # noqa: E402
from gvae_core.benchmarks.kernels import FIELDS  # noqa: E402
from gvae_core.rendering import RenderSettings, compiled, render  # noqa: E402

STAGES = ("project_arrays", "bin_gaussians", "composite_forward", "composite_backward")


def yardstick_run(src: Path, work: Path, threads: int, repeats: int) -> tuple[dict, np.ndarray]:
    """The yardstick's JSON line and image (H, W, 3) for the standard scene."""
    exe, scene, image = work / "raster", work / "s100k.bin", work / "out.f32"
    subprocess.run(["gcc", "-O3", "-march=native", "-fopenmp", "-ffast-math", str(src / "raster.c"), "-o", str(exe),
                    "-lm"], check=True)
    subprocess.run([sys.executable, str(src / "prep.py"), "100000", str(scene)], check=True, capture_output=True)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    out = subprocess.run([str(exe), str(scene), str(image), str(repeats)], check=True, capture_output=True, text=True,
                         env=env)
    info = json.loads(out.stdout)
    return info, np.fromfile(image, np.float32).reshape(info["H"], info["W"], 3)


def standard_scene(src: Path) -> tuple[GaussianCloud, Camera]:
    """The yardstick's cloud and camera as the project's types."""
    sys.path.insert(0, str(src))
    prep = importlib.import_module("prep")  # the yardstick's own scene maker

    c, w2c = prep.std_scene(100000)
    k = prep.STD_CAM
    cloud = GaussianCloud(means=c["means"].astype(np.float64), scales=c["scales"], quats=c["quats"],
                          opacities=c["opacities"], sh_dc=c["sh_dc"], sh_rest=c["sh_rest"]).to_torch()
    cam = Camera(world_to_cam=w2c, fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"], width=k["W"], height=k["H"])
    return cloud, cam


def project_stages(cloud: GaussianCloud, cam: Camera, repeats: int) -> tuple[dict, np.ndarray]:
    """Milliseconds per step of each stage (median over repeats) and the forward image."""
    times: dict[str, list[float]] = collections.defaultdict(list)
    step: dict[str, float] = {}

    def timed(fn, key):
        def call(*args, **kwargs):
            t = time.perf_counter()
            result = fn(*args, **kwargs)
            step[key] = step.get(key, 0.0) + time.perf_counter() - t
            return result
        return call

    saved = {name: getattr(compiled, name) for name in STAGES}
    saved_backward = compiled.ProjectFunction.backward
    for name in STAGES:
        setattr(compiled, name, timed(saved[name], name))
    compiled.ProjectFunction.backward = staticmethod(timed(saved_backward, "project_backward"))
    try:
        for name in FIELDS:
            getattr(cloud, name).requires_grad_()
        settings = RenderSettings(kernels="compiled")
        weights = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0))
        for i in range(repeats + 2):  # two warm-up steps
            step.clear()
            for name in FIELDS:
                getattr(cloud, name).grad = None
            t0 = time.perf_counter()
            out = render(cloud, cam, background=(0.0, 0.0, 0.0), settings=settings)
            t1 = time.perf_counter()
            (out.image * weights).sum().backward()
            t2 = time.perf_counter()
            step["forward"], step["backward"], step["forward + backward"] = t1 - t0, t2 - t1, t2 - t0
            if i >= 2:
                for key, value in step.items():
                    times[key].append(value)
    finally:
        for name in STAGES:
            setattr(compiled, name, saved[name])
        compiled.ProjectFunction.backward = saved_backward
    return {key: 1e3 * statistics.median(v) for key, v in times.items()}, out.image.detach().numpy()


def main() -> None:
    parser = argparse.ArgumentParser(prog="python tools/yardstick_stages.py")
    parser.add_argument("--yardstick", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "yardstick")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        ys, ys_image = yardstick_run(args.yardstick, Path(tmp), args.threads, args.repeats)
    stages, image = project_stages(*standard_scene(args.yardstick), args.repeats)
    base = ys["total_ms"]
    print(f"{args.threads} threads, load {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"yardstick: bin {ys['bin_ms']:.1f} + composite {ys['comp_ms']:.1f} = {base:.1f} ms "
          f"({ys['tile_pairs']} tile pairs of 16x16)")
    for key in ("project_arrays", "bin_gaussians", "composite_forward", "forward", "composite_backward",
                "project_backward", "backward", "forward + backward"):
        print(f"  {key:20s} {stages[key]:7.1f} ms  {stages[key] / base:5.2f}x the yardstick")
    print(f"max |image - yardstick image| {float(np.abs(image - ys_image).max()):.2e}")


if __name__ == "__main__":
    main()
