"""Blender import and export of a 1M-Gaussian SH-3 PLY through the add-on's operators.

Runs real Blender (the bpy module) in a subprocess with the add-on registered from the source
tree. Rows: median time of the repeats and the error of the same runs: for import, the max abs
difference between the object's attributes and the written cloud, and the instance count of
the evaluated object (one per Gaussian expected); for export, whether every written file was
byte-identical to the imported one. Blender's own C++ PLY importer (vertices and attributes, no
splat set-up) is timed on the same file for scale. Goals: import <= 1.5 s and export
<= 1.5 s, instances included. Refine is timed once through the operator as a batch run
calls it, beside the core's refine of the same cloud.

Then (`run_render`) what the user sees and what it costs: a Cycles render of the renderer
benchmark's 100k scene at 400 px, imported with the default options, with its PSNR and
silhouette IoU against gvae_core.render of the same camera.
"""

from __future__ import annotations

import argparse
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

from ..capture import read_capture
from ..ply import read_ply, write_ply
from ..refinement import refine
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


#: Where `splat-types` looks for a Blender 5.3+ Python when GVAE_BLENDER_PYTHON is unset (`make
#: build/bpy-5.3.0/.installed` makes it).
NATIVE_BLENDER_PYTHON = Path(__file__).resolve().parents[2] / "build" / "bpy-5.3.0" / "bin" / "python"


def _display(png) -> tuple[np.ndarray, np.ndarray]:
    """A straight-alpha RGBA PNG over white (display space, as an image viewer shows it), and its alpha."""
    rgba = np.asarray(Image.open(png).convert("RGBA"), np.float64) / 255.0
    a = rgba[..., 3:]
    return rgba[..., :3] * a + (1.0 - a), rgba[..., 3]


def run_splat_types(args) -> None:
    """The add-on's splat and Blender 5.3's own splat (its PLY importer and the add-on's modifier) side by
    side: Cycles renders of each scene at its training resolution (the input cloud) and at 2x (the cloud
    refined by `gvae_core.refine`'s defaults, the detail model), PSNR (over white, display space) against
    gvae_core.render of the same cloud and camera, beside the render times; and a picture, one row a
    scene and resolution: gvae_core.render | the add-on's splat | Blender's splat. Scenes: the bundled
    chair from its first test camera, and with `--cloud PLY --capture DIR` a cloud trained from a real
    capture from its first held-out photo's camera (every `--test-every`-th), at `--height`."""
    blender = Path(os.environ.get("GVAE_BLENDER_PYTHON") or NATIVE_BLENDER_PYTHON)
    if not blender.exists():
        print(f"skipped: needs a Python with bpy 5.3 or later ({blender}; make build/bpy-5.3.0/.installed, or set "
              "GVAE_BLENDER_PYTHON)")
        return
    root = Path(__file__).resolve().parents[2]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    chair = read_capture(root / "examples" / "trained", kind="nerf-synthetic", images=False)
    scenes = [("chair", root / "examples" / "trained" / "scene.ply", chair.split_cameras("test")[0].scaled(100))]
    if args.cloud:
        capture = read_capture(args.capture, args.test_every, images=False)
        scenes.append((Path(args.capture).name, Path(args.cloud), capture.split_cameras("test")[0].scaled(args.height)))
    jobs, clouds = [], {}
    for name, ply, cam in scenes:
        refined = work / f"{name}_refined.ply"
        if not refined.exists():  # (cached: the detail model's refine of a large cloud takes minutes)
            write_ply(refine(read_ply(ply)).cloud, refined)
        for what, path, factor in (("1x", ply, 1), ("2x refined", refined, 2)):
            clouds[f"{name} {what}"] = (path, cam.scaled(cam.height * factor))
            for kind in ("mesh", "native"):
                jobs.append({"name": f"{name}_{what.split()[0]}_{kind}", "key": f"{name} {what}", "ply": str(path),
                             "kind": kind, "c2w": cam.to_blender_c2w().tolist(), "fov_x": cam.fov_x,
                             "width": cam.width, "height": cam.height, "percentage": 100 * factor,
                             "samples": args.samples})
    spec, done = work / "splat_types.json", work / "splat_types_result.json"
    if args.reuse and done.exists() and spec.exists() and json.loads(spec.read_text()) == jobs:
        got = json.loads(done.read_text())  # the renders of an earlier run with the same spec
        print(f"(the renders of {done}, made earlier)")
    else:
        spec.write_text(json.dumps(jobs))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
        proc = subprocess.run([str(blender), "-m", "gvae_addon.benchmark", "splat-types", str(spec), str(work)],
                              capture_output=True, text=True, cwd=root, env=env)
        lines = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            raise RuntimeError(f"Blender splat-types benchmark failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
        got = json.loads(lines[-1][len("RESULT "):])
        done.write_text(json.dumps(got))
    print(f"Cycles (CPU, 2 threads) against gvae_core.render, display space over white; the add-on's splat: 1 "
          f"sample at the pixel centres; Blender's: {args.samples} samples there; load {os.getloadavg()[0]:.1f}")
    print(f"| {'scene':<18} | {'Gaussians':>9} | {'add-on dB':>9} | {'s (CPU s)':>14} | {'Blender dB':>10} | "
          f"{'s (CPU s)':>14} |")
    print(f"|{'-' * 20}|{'-' * 10}:|{'-' * 10}:|{'-' * 15}:|{'-' * 11}:|{'-' * 15}:|")
    rows = []
    for key, (path, cam) in clouds.items():
        cloud = read_ply(path)
        ref = render(cloud, cam, background=(1.0, 1.0, 1.0)).image.numpy().clip(0, 1).astype(np.float64)
        cells, row = [], [ref]
        for kind in ("mesh", "native"):
            r = next(got[j["name"]] for j in jobs if j["key"] == key and j["kind"] == kind)
            img, _ = _display(r["png"])
            row.append(img)
            p = 10.0 * math.log10(1.0 / max(float(((img - ref) ** 2).mean()), 1e-12))
            cells.append((p, r))
        (pm, rm), (pn, rn) = cells
        print(f"| {key:<18} | {len(cloud):>9,} | {pm:>9.2f} | {rm['seconds']:6.1f} ({rm['cpu_seconds']:5.1f}) | "
              f"{pn:>10.2f} | {rn['seconds']:6.1f} ({rn['cpu_seconds']:5.1f}) |")
        rows.append(np.concatenate(row, 1))
    if args.picture:  # each row enlarged (nearest) by the whole factor that brings it nearest the widest
        width = max(r.shape[1] for r in rows)
        big = [r.repeat(width // r.shape[1], 0).repeat(width // r.shape[1], 1) for r in rows]
        pad = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in big]
        Image.fromarray((np.concatenate(pad, 0) * 255 + 0.5).astype(np.uint8)).save(args.picture, quality=88)
        print(f"wrote {args.picture} (rows: {', '.join(clouds)}; columns: gvae_core.render, the add-on's splat, "
              "Blender's splat)")


def run_photos(args) -> None:
    """New from Photos in Blender (the bpy module of this Python) on a capture, as a batch run calls it
    (`gvae_addon.benchmark photos`), beside `gvae train` of the same capture and options (`--against RUN`,
    a finished run of `gvae train CAPTURE --out RUN --test-every 8 --image-height H [--threads N]`): held-out
    PSNR of each stage, time; and a picture of the first held-out photo | Blender's Cycles render of the
    result through its camera | gvae_core.render of the result there."""
    root = Path(__file__).resolve().parents[2]
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    run = work / "run"
    load = os.getloadavg()[0]
    proc = subprocess.run([sys.executable, "-m", "gvae_addon.benchmark", "photos", str(Path(args.capture).resolve()),
                           str(run), str(args.height), str(work), str(args.threads or 0)],
                          capture_output=True, text=True, cwd=root, env=env)
    lines = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"Blender photos benchmark failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    r = json.loads(lines[-1][len("RESULT "):])
    said = (proc.stdout + proc.stderr).split("New from Photos: ", 1)
    if len(said) > 1:  # the operator's report (with what structure from motion did, when it ran)
        print("the operator's report: New from Photos: " + said[1].split("\nRESULT ")[0].strip())
    print(f"New from Photos on {args.capture} at {args.height} px (Blender {_blender_version()}, {r['status']}): "
          f"{r['count']:,} Gaussians in {r['seconds']:.0f} s ({r['cpu_seconds']:.0f} CPU s), load {load:.1f} at the "
          f"start, {os.getloadavg()[0]:.1f} at the end")
    against = json.loads((Path(args.against) / "log.json").read_text()) if args.against else []
    print(f"| {'stage':>5} | {'px':>4} | {'Blender held-out dB':>19} | {'gvae train held-out dB':>22} |")
    print(f"|{'-' * 7}:|{'-' * 6}:|{'-' * 21}:|{'-' * 24}:|")
    for i, e in enumerate(r["log"]):
        theirs = f"{against[i]['test_psnr']:.2f}" if i < len(against) else "-"
        print(f"| {e['stage']:>5} | {e['resolution']:>4} | {e['test_psnr']:>19.2f} | {theirs:>22} |")
    capture = read_capture(args.capture, 8)  # (after the job: a folder of photos has its SfM model now)
    cam = capture.cameras[capture.indices("test")[0]].scaled(args.height)
    photo = capture.load("test", args.height).images[0]
    ref = render(read_ply(run / f"stage_{len(r['log']) - 1}.ply"), cam, background=(1.0, 1.0, 1.0))
    shown, _ = _display(r["png"])
    ref_img = ref.image.numpy().clip(0, 1).astype(np.float64)
    p = 10.0 * math.log10(1.0 / max(float(((shown - ref_img) ** 2).mean()), 1e-12))
    print(f"held-out camera {r['camera']}: Blender's render against gvae_core.render of the result {p:.2f} dB")
    if args.picture:
        row = np.concatenate([np.asarray(photo, np.float64), shown, ref_img], 1)
        Image.fromarray((row * 255 + 0.5).astype(np.uint8)).save(args.picture, quality=92)
        print(f"wrote {args.picture} (the held-out photo, Blender's Cycles render, gvae_core.render)")


def _blender_version() -> str:
    try:
        return version("bpy")
    except Exception:
        return "?"


def main(argv=None) -> int:
    """`python -m gvae_core.benchmarks.blender splat-types [...]` (`run_splat_types`) and `... photos [...]`
    (`run_photos`)."""
    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.blender")
    parser.add_argument("what", choices=("splat-types", "photos"))
    parser.add_argument("--work", default="build/splat-types", help="renders and refined clouds (cached) go here")
    parser.add_argument("--samples", type=int, default=256, help="Cycles samples of Blender's own splats")
    parser.add_argument("--cloud", help="a cloud trained from --capture")
    parser.add_argument("--capture", help="the capture --cloud was trained from")
    parser.add_argument("--test-every", type=int, default=8)
    parser.add_argument("--height", type=int, help="the height --cloud was trained at")
    parser.add_argument("--against", help="photos: a gvae train run of --capture with the same options")
    parser.add_argument("--threads", type=int, help="photos: torch threads (gvae train --threads; default: its own)")
    parser.add_argument("--picture", help="write the side-by-side picture here")
    parser.add_argument("--reuse", action="store_true",
                        help="splat-types: the renders of an earlier run with the same spec in --work (no Blender)")
    args = parser.parse_args(argv)
    if args.what == "photos":
        if not (args.capture and args.height):
            parser.error("photos needs --capture and --height")
        run_photos(args)
        return 0
    if args.cloud and not (args.capture and args.height):
        parser.error("--cloud needs --capture and --height")
    run_splat_types(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
