"""Blender import and export of a 1M-Gaussian SH-3 PLY through the add-on's operators.

Runs real Blender (the bpy module) in a subprocess with the add-on registered from the source
tree. Rows: median time of the repeats and the error of the same runs: for import, the max abs
difference between the object's attributes and the written cloud, and the instance count of
the evaluated object (one per Gaussian expected); for export, whether every written file was
byte-identical to the imported one. Blender's own C++ PLY importer (vertices and attributes, no
splat set-up) is timed on the same file for scale. Goals (issue 7): import <= 1.5 s and export
<= 1.5 s, instances included.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path


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
        ("  part: read_ply", r["read_ply_s"], "(inside import)"),
        ("  part: mesh_from_cloud", r["mesh_from_cloud_s"], "(inside import)"),
        ("Blender wm.ply_import (no splat set-up)", r["native_ply_import_s"],
         f"{r['native_vertices']} vertices"),
    ]
    print(f"{r['n']} Gaussians, SH degree 3, median of {r['repeats']}, Blender {_blender_version()}")
    print(f"| {'operation':<46} | {'time (s)':>8} | {'error / check':<40} |")
    print(f"|{'-' * 48}|{'-' * 9}:|{'-' * 42}|")
    for name, t, e in rows:
        print(f"| {name:<46} | {t:8.3f} | {e:<40} |")
    native = r["native_ply_import_s"]
    print(f"import / Blender's C++ PLY import: {r['import_s'] / native:.2f}x; "
          f"export / C++ import: {r['export_s'] / native:.2f}x (ratios hold better than times under load)")


def _blender_version() -> str:
    try:
        return version("bpy")
    except Exception:
        return "?"
