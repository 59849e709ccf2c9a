"""Benchmark-scene generation time per profile, with the camera/mesh consistency of the same run.

For each profile and scene, `python -m gvae_core.scenes.build` renders a few views (tiny: the
whole scene; default and full: the first views of each split, `--limit-views`), and the row
gives the median wall and CPU seconds per view, the projected time of the whole scene (the
process's time without its views + median view time x all views; the ground truth is always
computed in full), and the error: the
share of ground-truth mesh surface samples that project, through the loaded cameras, onto
pixels the render left transparent (0 when images, cameras and mesh agree). A complete run of
a profile is `gvae make-scene all --profile P` (BENCHMARKS.md has those times)."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from plyfile import PlyData

from ..capture import load_nerf_synthetic
from ..scenes import PROFILES, bpy_available, list_scenes
from ..scenes.geometry import sample_surface

LIMITS = {"tiny": None, "default": 2, "full": 1}  # views per split actually rendered


def silhouette_miss(root: Path) -> float:
    """Share of mesh surface samples that land on alpha == 0 pixels, over all rendered views."""
    ply = PlyData.read(str(root / "mesh.ply"))
    v = ply["vertex"]
    verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    tris = np.stack(list(ply["face"]["vertex_indices"])).astype(np.int64)
    pts, _ = sample_surface(verts, tris, 20_000, np.random.default_rng(0))
    miss, total = 0, 0
    for split in ("train", "test"):
        views = load_nerf_synthetic(root, split)
        for cam, alpha in zip(views.cameras, views.alphas):
            uv, z = cam.project(pts)
            px = np.clip(np.floor(np.nan_to_num(uv, nan=-1.0)).astype(int), -1, max(cam.width, cam.height))
            inside = (z > 0) & (px >= 0).all(1) & (px[:, 0] < cam.width) & (px[:, 1] < cam.height)
            hit = np.zeros(len(pts), bool)
            hit[inside] = alpha[px[inside, 1], px[inside, 0]] > 0
            miss += int((~hit).sum())
            total += len(pts)
    return miss / total


def run(args) -> None:
    if not bpy_available():
        print("skipped: needs the bpy module (pip install bpy==5.0.1)")
        return
    profiles = ["tiny"] if args.quick else list(LIMITS)
    print("| profile | scene | views rendered | s/view wall (median) | s/view CPU | projected scene s "
          "| silhouette miss |")
    print("|---|---|---|---|---|---|---|")
    totals = {}
    for profile in profiles:
        prof = PROFILES[profile]
        load = os.getloadavg()[0]
        for name in list_scenes():
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / name
                cmd = [sys.executable, "-m", "gvae_core.scenes.build", name, str(out), "--profile", profile]
                if LIMITS[profile] is not None:
                    cmd += ["--limit-views", str(LIMITS[profile])]
                start = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                elapsed = time.perf_counter() - start
                meta = json.loads((out / "scene.json").read_text())
                wall = statistics.median(meta["frame_s"])
                cpu = statistics.median(meta["frame_cpu_s"])
                # Everything but the rendered views (start-up, scene, ground truth) + all views.
                projected = elapsed - sum(meta["frame_s"]) + wall * (prof.n_train + prof.n_test)
                totals[profile] = totals.get(profile, 0.0) + projected
                print(f"| {profile} ({prof.resolution} px, {prof.n_train}+{prof.n_test}, load {load:.1f}) | {name} "
                      f"| {len(meta['frame_s'])} | {wall:.2f} | {cpu:.2f} | {projected:.0f} "
                      f"| {100 * silhouette_miss(out):.2f} % |", flush=True)
    for profile, total in totals.items():
        print(f"projected {profile}, all scenes: {total / 60:.1f} min")
