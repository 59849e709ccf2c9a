"""Blender import and export of a 1M-Gaussian SH-3 PLY through the add-on's operators.

Runs real Blender (the bpy module) in a subprocess with the add-on registered from the source
tree. Rows: median time of the repeats and the error of the same runs: for import, the max abs
difference between the object's attributes and the written cloud, and the instance count of
the evaluated object (one per Gaussian expected); for export, whether every written file was
byte-identical to the imported one. Blender's own C++ PLY importer (vertices and attributes, no
splat set-up) is timed on the same file for scale. Goals (issue 7): import <= 1.5 s and export
<= 1.5 s, instances included. Refine (issue 18) is timed once through the operator as a batch run
calls it, beside the core's refine of the same cloud.

Then (`run_render`) what the user sees and what it costs: a Cycles render of the renderer
benchmark's 100k scene at 400 px, imported with the default options, with its PSNR and
silhouette IoU against gvae_core.render of the same camera (issue 17).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
from importlib.metadata import version
from pathlib import Path

import numpy as np
from PIL import Image

from ..ply import write_ply
from ..rendering import render
from .render import benchmark_camera, benchmark_scene


def run(args) -> None:
    if importlib.util.find_spec("bpy") is None:
        print("skipped: needs the bpy module (pip install bpy==5.0.1)")
        return
    quick = getattr(args, "quick", False)
    n, repeats = (100_000, 3) if quick else (1_000_000, 5)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "gvae_addon.benchmark", str(n), str(repeats)],
                          capture_output=True, text=True, cwd=root, env=env)
    lines = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"Blender benchmark failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    r = json.loads(lines[-1][len("RESULT "):])
    imp_err = f"attr max err {r['attribute_error']:.3g}, {r['instances']} instances"
    exp_err = "byte-identical" if r["export_identical"] else "FILES DIFFER"
    rows = [
        ("import operator (instances evaluated in it)", r["import_s"], imp_err),
        ("import, then count instances", r["import_instances_s"], imp_err),
        ("  part: re-evaluate the modifier", r["reevaluate_s"], f"{r['instances']} instances"),
        ("export operator (atomic write)", r["export_s"], exp_err),
        ("Refine operator, defaults (execute; first Refine: imports torch)", r["refine_s"],
         f"{'/'.join(r['refine_status'])}, {r['refine_added']:+,} Gaussians"),
        ("  for scale: gvae_core.refine of the same cloud", r["refine_core_s"],
         f"{r['refine_core_added']:+,} Gaussians"),
        ("  part: read_ply", r["read_ply_s"], "(inside import)"),
        ("  part: mesh_from_cloud", r["mesh_from_cloud_s"], "(inside import)"),
        ("Blender wm.ply_import (no splat set-up)", r["native_ply_import_s"],
         f"{r['native_vertices']} vertices"),
    ] + [(f"scene camera moved: {label}", t, "modifier re-evaluated") for label, t in r["camera_move_s"].items()]
    print(f"{r['n']} Gaussians, SH degree 3, median of {r['repeats']}, Blender {_blender_version()}")
    print(f"| {'operation':<64} | {'time (s)':>8} | {'error / check':<40} |")
    print(f"|{'-' * 66}|{'-' * 9}:|{'-' * 42}|")
    for name, t, e in rows:
        print(f"| {name:<64} | {t:8.3f} | {e:<40} |")
    native = r["native_ply_import_s"]
    print(f"import / Blender's C++ PLY import: {r['import_s'] / native:.2f}x; "
          f"export / C++ import: {r['export_s'] / native:.2f}x (ratios hold better than times under load)")
    print()
    run_render(args)


def run_render(args) -> None:
    """Cycles render of the renderer benchmark's scene (gvae_core.benchmarks.render: 100k Gaussians,
    SH degree 3, on a sphere and a ground plane) at 400 px, imported with the default options, to
    PNG; PSNR (over white, display space) and silhouette IoU against gvae_core.render of the same
    camera, beside the time of each render."""
    quick = getattr(args, "quick", False)
    n, height = (10_000, 200) if quick else (100_000, 400)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    cloud, cam = benchmark_scene(n), benchmark_camera(height)
    ref = render(cloud, cam, background=(1.0, 1.0, 1.0))
    ref_img, ref_alpha = ref.image.numpy().clip(0, 1).astype(np.float64), ref.alpha.numpy()
    with tempfile.TemporaryDirectory() as tmp:
        ply, cam_json = Path(tmp) / "scene.ply", Path(tmp) / "camera.json"
        write_ply(cloud, ply)
        cam_json.write_text(json.dumps({"c2w": cam.to_blender_c2w().tolist(), "fov_x": cam.fov_x,
                                        "width": cam.width, "height": cam.height}))
        proc = subprocess.run([sys.executable, "-m", "gvae_addon.benchmark", "render", str(ply), str(cam_json), tmp],
                              capture_output=True, text=True, cwd=root, env=env)
        lines = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            raise RuntimeError(f"Blender render benchmark failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
        r = json.loads(lines[-1][len("RESULT "):])
        print(f"{r['n']} Gaussians (SH 3) at {cam.width}x{cam.height}, Cycles CPU 2 threads, "
              f"import {r['import_s']:.2f} s, Blender {_blender_version()}")
        print(f"| {'Cycles settings':<48} | {'render s':>8} | {'CPU s':>7} | {'PSNR dB':>7} | {'IoU':>5} |")
        print(f"|{'-' * 50}|{'-' * 9}:|{'-' * 8}:|{'-' * 8}:|{'-' * 6}:|")
        for name, row in r["renders"].items():
            rgba = np.asarray(Image.open(row["png"]).convert("RGBA"), np.float64) / 255.0
            a = rgba[..., 3:]
            img = rgba[..., :3] * a + (1.0 - a)
            psnr = 10.0 * math.log10(1.0 / max(float(((img - ref_img) ** 2).mean()), 1e-12))
            ours, theirs = a[..., 0] > 0.5, ref_alpha > 0.5
            iou = float((ours & theirs).sum() / max(1, (ours | theirs).sum()))
            print(f"| {name:<48} | {row['seconds']:8.1f} | {row['cpu_seconds']:7.1f} | {psnr:7.2f} | {iou:5.3f} |")
        print(f"(transparent bounces {next(iter(r['renders'].values()))['bounces']}, set by the import; "
              "render s includes Cycles' scene sync and BVH build)")


def _blender_version() -> str:
    try:
        return version("bpy")
    except Exception:
        return "?"
