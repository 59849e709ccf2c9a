"""Blender side of `make bench` (gvae_core/benchmarks/blender.py runs this in a subprocess with the
bpy module: `python -m gvae_addon.benchmark N REPEATS`). Registers the add-on from the source
tree, times its operators (import, export, Refine) on an N-Gaussian SH-3 PLY and prints one JSON
line. `... render PLY
CAMERA.json OUT_DIR`: Cycles renders of an imported PLY (`render_main`); `... splat-types SPEC.json OUT_DIR`
(Blender 5.3+): the add-on's splat and Blender's own side by side (`splat_types_main`)."""

from __future__ import annotations

import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np

import gvae_addon

from gvae_addon import convert, nodes, render_setup
from gvae_core.examples import random_cloud
from gvae_core.ply import read_ply, write_ply


def _clear():
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    for me in list(bpy.data.meshes):
        bpy.data.meshes.remove(me)


def _instances(obj) -> int:
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    geometry = obj.evaluated_get(dg).evaluated_geometry()  # keep alive while its parts are read
    inst = geometry.instances_pointcloud()
    return len(inst.points) if inst is not None else 0


def _attribute_error(obj, cloud) -> float:
    """Max abs difference between the object's attributes and the written cloud (own reader,
    not the add-on's: foreach_get of each named attribute)."""
    me = obj.data
    n = len(me.vertices)
    pos = np.empty(3 * n, np.float32)
    me.attributes["position"].data.foreach_get("vector", pos)
    err = float(np.abs(pos.reshape(n, 3) - cloud.means).max())
    k = cloud.sh_rest.shape[1]
    expected = {"opacity": cloud.opacities}
    for i in range(3):
        expected[f"f_dc_{i}"] = cloud.sh_dc[:, i]
        expected[f"scale_{i}"] = cloud.scales[:, i]
        for j in range(k):
            expected[f"f_rest_{i * k + j}"] = cloud.sh_rest[:, j, i]
    for i in range(4):
        expected[f"rot_{i}"] = cloud.quats[:, i]
    buf = np.empty(n, np.float32)
    for name, want in expected.items():
        me.attributes[name].data.foreach_get("value", buf)
        err = max(err, float(np.abs(buf - want).max()))
    return err


#: Display settings whose re-evaluation is timed when the scene camera moves (the modifier
#: depends on it: SH colour and screen filter); orbiting the viewport re-evaluates nothing.
CAMERA_MOVE_SETTINGS = {
    "ellipsoids, view-dependent colour (default)": {},
    "ellipsoids, DC colour only": {"View-Dependent Colour": False},
    "viewport: Points Only": {"Points Only": True},
    "viewport: Display Fraction 0.1": {"Display Fraction": 0.1},
}


def _camera_moves(obj, repeats: int) -> dict:
    """Median seconds of the depsgraph update after the scene camera moves, per display setting."""
    scene = bpy.context.scene
    cam = bpy.data.objects.new("bench_cam", bpy.data.cameras.new("bench_cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    mod = nodes.splat_modifier(obj)
    defaults = {name: nodes.get_modifier_input(mod, name) for name in ("View-Dependent Colour", "Points Only",
                                                                       "Display Fraction")}
    out = {}
    for label, values in CAMERA_MOVE_SETTINGS.items():
        for name, value in {**defaults, **values}.items():
            nodes.set_modifier_input(mod, name, value)
        obj.update_tag()
        bpy.context.evaluated_depsgraph_get().update()
        times = []
        for r in range(repeats):
            cam.location = (3.0 + 0.1 * r, -3.0, 2.0)
            t0 = time.perf_counter()
            bpy.context.evaluated_depsgraph_get().update()
            times.append(time.perf_counter() - t0)
        out[label] = statistics.median(times)
    for name, value in defaults.items():
        nodes.set_modifier_input(mod, name, value)
    bpy.data.objects.remove(cam)
    return out


def main() -> int:
    n, repeats = int(sys.argv[1]), int(sys.argv[2])
    gvae_addon.register()
    bpy.context.preferences.edit.undo_steps = 0  # as in a batch run; the UI's undo is separate
    out = {"n": n, "repeats": repeats}
    cloud = random_cloud(n)
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "bench.ply"
        write_ply(cloud, src)
        obj = _time_import(src, repeats, out)
        out["attribute_error"] = _attribute_error(obj, cloud)
        _time_export(Path(tmp), src.read_bytes(), repeats, out)
        _time_refine(obj, src, out)
        _time_parts(src, repeats, out)
    print("RESULT " + json.dumps(out))
    return 0


def _time_import(src: Path, repeats: int, out: dict):
    """Import (the operator, and with the instances evaluated), then the instances re-evaluated and
    the camera moved; the imported object."""
    t_imp, t_inst, counts = [], [], []
    for _ in range(repeats):
        _clear()
        t0 = time.perf_counter()
        bpy.ops.import_scene.gaussian_splat(filepath=str(src))
        t1 = time.perf_counter()
        counts.append(_instances(bpy.context.active_object))
        t2 = time.perf_counter()
        t_imp.append(t1 - t0)
        t_inst.append(t2 - t0)
    obj = bpy.context.active_object
    t_eval = []
    for _ in range(repeats):  # the operator's own call already evaluated the instances once
        obj.update_tag()
        t0 = time.perf_counter()
        bpy.context.evaluated_depsgraph_get().update()
        t_eval.append(time.perf_counter() - t0)
    out["reevaluate_s"] = statistics.median(t_eval)
    out["camera_move_s"] = _camera_moves(obj, repeats)
    out["import_s"] = statistics.median(t_imp)
    out["import_instances_s"] = statistics.median(t_inst)
    out["instances"] = min(counts)
    return obj


def _time_export(tmp: Path, raw: bytes, repeats: int, out: dict) -> None:
    """Export of the imported object, and whether it wrote the imported file's bytes."""
    t_exp, same = [], True
    for r in range(repeats):
        dst = tmp / f"out{r}.ply"
        t0 = time.perf_counter()
        bpy.ops.export_scene.gaussian_splat(filepath=str(dst))
        t_exp.append(time.perf_counter() - t0)
        same &= dst.read_bytes() == raw
        dst.unlink()
    out["export_s"] = statistics.median(t_exp)
    out["export_identical"] = bool(same)


def _time_refine(obj, src: Path, out: dict) -> None:
    """Refine as a batch run or script calls it (the operator's execute: the object read, refined
    by gvae_core.refine in the job's worker thread, written back; the first Refine of a session
    also imports torch and loads the model), then the core's refine of the same cloud on this
    thread. In that order: once this thread has run torch's parallel loops, their OpenMP threads
    slow a worker thread's own."""
    before = len(obj.data.vertices)
    t0 = time.perf_counter()
    status = bpy.ops.gvae.refine()
    out["refine_s"] = time.perf_counter() - t0
    out["refine_status"] = sorted(status)
    out["refine_added"] = len(bpy.context.active_object.data.vertices) - before
    from gvae_core.refinement import refine  # noqa: PLC0415 - imported by the operator above
    t0 = time.perf_counter()
    core = refine(read_ply(src))
    out["refine_core_s"] = time.perf_counter() - t0
    out["refine_core_added"] = len(core.added)


def _time_parts(src: Path, repeats: int, out: dict) -> None:
    """Context: the add-on's own parts (reading the PLY, making the mesh), and Blender's C++ PLY
    importer (no splat set-up)."""
    t_read, t_mesh = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        c = read_ply(src)
        t1 = time.perf_counter()
        me = convert.mesh_from_cloud(c, "bench")
        t_mesh.append(time.perf_counter() - t1)
        t_read.append(t1 - t0)
        bpy.data.meshes.remove(me)
    out["read_ply_s"] = statistics.median(t_read)
    out["mesh_from_cloud_s"] = statistics.median(t_mesh)
    t_native = []
    for _ in range(repeats):
        _clear()
        t0 = time.perf_counter()
        bpy.ops.wm.ply_import(filepath=str(src))
        t_native.append(time.perf_counter() - t0)
    out["native_ply_import_s"] = statistics.median(t_native)
    out["native_vertices"] = len(bpy.context.active_object.data.vertices)


#: Cycles settings of the render benchmark: "converged" samples each pixel once at its centre
#: without Russian roulette on transparent bounces (deterministic: the converged image of the
#: reference renderer's point sampling); "16 spp" is Blender's pixel filter with 16 samples.
RENDER_CONFIGS = {
    "converged (1 spp at pixel centres, no roulette)": {"samples": 1, "filter_width": 0.01, "roulette": False},
    "16 spp, Blender's default pixel filter": {"samples": 16, "filter_width": 1.5, "roulette": True},
}


def _cpu_seconds() -> float:
    """User + system CPU time of this process, all threads (steadier than wall time under load)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _cycles(scene):
    """(render settings, Cycles settings) of `scene` set for the benchmark renders: Cycles on the CPU with
    2 threads, no denoising or adaptive sampling, film transparent, to 8-bit RGBA PNG."""
    r, c = scene.render, scene.cycles
    r.engine, r.film_transparent = "CYCLES", True
    r.threads_mode, r.threads = "FIXED", 2
    r.image_settings.file_format, r.image_settings.color_mode = "PNG", "RGBA"
    c.device, c.use_denoising, c.use_adaptive_sampling = "CPU", False, False
    return r, c


def render_main(ply: str, camera_json: str, out_dir: str) -> int:
    """`python -m gvae_addon.benchmark render PLY CAMERA.json OUT_DIR`: import with the default
    options, then a Cycles render (CPU, 2 threads) per RENDER_CONFIGS to PNG; prints one JSON line."""
    gvae_addon.register()
    cam_args = json.loads(Path(camera_json).read_text())
    _clear()
    scene = bpy.context.scene
    t0 = time.perf_counter()
    bpy.ops.import_scene.gaussian_splat(filepath=ply)
    out = {"import_s": time.perf_counter() - t0, "n": len(bpy.context.active_object.data.vertices), "renders": {}}
    render_setup.add_camera(scene, cam_args["c2w"], cam_args["fov_x"], cam_args["width"], cam_args["height"])
    r, c = _cycles(scene)
    for i, (name, cfg) in enumerate(RENDER_CONFIGS.items()):
        c.samples, c.filter_width = cfg["samples"], cfg["filter_width"]
        c.min_transparent_bounces = 0 if cfg["roulette"] else c.transparent_max_bounces
        r.filepath = str(Path(out_dir) / f"render{i}.png")
        t0, cpu0 = time.perf_counter(), _cpu_seconds()
        bpy.ops.render.render(write_still=True)
        out["renders"][name] = {"seconds": time.perf_counter() - t0, "cpu_seconds": _cpu_seconds() - cpu0,
                                "png": r.filepath, "samples": cfg["samples"], "bounces": c.transparent_max_bounces}
    gvae_addon.unregister()
    print("RESULT " + json.dumps(out))
    return 0


def splat_types_main(spec_json: str, out_dir: str) -> int:
    """`python -m gvae_addon.benchmark splat-types SPEC.json OUT_DIR` (Blender 5.3+): each render of the
    spec (a list of {name, ply, kind, c2w, fov_x, width, height, percentage, samples}) in a scene of its
    own, Cycles on the CPU (2 threads), to PNG: kind "mesh" the add-on's splat (File > Import, default
    options; one sample at each pixel centre without Russian roulette on transparent bounces, the display
    tests' converged setting), "native" Blender's own splat (its PLY importer, then the add-on's modifier,
    `nodes.add_native_modifier`; its splats are drawn stochastically: `samples` at the pixel centres).
    Prints one JSON line: per render its PNG, seconds and CPU seconds."""
    gvae_addon.register()
    out = {}
    for job in json.loads(Path(spec_json).read_text()):
        _clear()
        for pc in list(bpy.data.pointclouds):
            bpy.data.pointclouds.remove(pc)
        scene = bpy.context.scene
        if job["kind"] == "mesh":
            bpy.ops.import_scene.gaussian_splat(filepath=job["ply"])
        else:
            bpy.ops.wm.ply_import(filepath=job["ply"])
            nodes.add_native_modifier(bpy.context.active_object)
            render_setup.setup_scene(scene)
        render_setup.add_camera(scene, job["c2w"], job["fov_x"], job["width"], job["height"])
        r, c = _cycles(scene)
        r.resolution_percentage = job["percentage"]
        c.samples, c.filter_width = (1 if job["kind"] == "mesh" else job["samples"]), 0.01
        c.min_transparent_bounces = c.transparent_max_bounces
        r.filepath = str(Path(out_dir) / f"{job['name']}.png")
        t0, cpu0 = time.perf_counter(), _cpu_seconds()
        bpy.ops.render.render(write_still=True)
        out[job["name"]] = {"png": r.filepath, "seconds": time.perf_counter() - t0,
                            "cpu_seconds": _cpu_seconds() - cpu0, "samples": c.samples}
    gvae_addon.unregister()
    print("RESULT " + json.dumps(out))
    return 0


def photos_main(folder: str, run_dir: str, height: str, out_dir: str, threads: str) -> int:
    """`python -m gvae_addon.benchmark photos FOLDER RUN_DIR HEIGHT OUT_DIR THREADS`: New from Photos as a
    batch run calls it (`bpy.ops.gvae.new_from_photos`, held-out photos on, THREADS torch threads, 0: its
    choice) in Blender's default scene emptied of its objects, timed; then a Cycles render of the result
    (the add-on's splat, the display tests' converged setting) through the first held-out photo's camera
    at the training size, to OUT_DIR/photos.png. Prints one JSON line."""
    gvae_addon.register()
    _clear()  # (the default cube would stand in front of the capture; its camera goes too: the job sets one)
    t0, cpu0 = time.perf_counter(), _cpu_seconds()
    status = bpy.ops.gvae.new_from_photos(folder=folder, run_dir=run_dir, height=int(height), threads=int(threads))
    out = {"status": sorted(status), "seconds": time.perf_counter() - t0, "cpu_seconds": _cpu_seconds() - cpu0}
    obj = bpy.context.active_object
    out["count"] = len(obj.data.vertices)
    scene = bpy.context.scene
    cams = bpy.data.collections[f"{obj.name} cameras"].objects
    held = sorted((c for c in cams if c.name.endswith("(held out)")), key=lambda c: c.name)
    scene.camera = held[0]
    out["camera"] = held[0].name
    log = json.loads((Path(run_dir) / "log.json").read_text())
    out["log"] = log
    from gvae_core.capture import read_capture  # noqa: PLC0415 - the capture as the job left it (SfM'd)

    capture = read_capture(folder, 8, images=False)
    photo = capture.cameras[capture.indices("test")[0]].scaled(log[-1]["resolution"])
    r, c = _cycles(scene)
    r.resolution_x, r.resolution_y, r.resolution_percentage = photo.width, photo.height, 100
    c.samples, c.filter_width = 1, 0.01
    c.min_transparent_bounces = c.transparent_max_bounces
    r.filepath = str(Path(out_dir) / "photos.png")
    out["render_size"] = [r.resolution_x, r.resolution_y]
    bpy.ops.render.render(write_still=True)
    out["png"] = r.filepath
    gvae_addon.unregister()
    print("RESULT " + json.dumps(out))
    return 0


if __name__ == "__main__":
    if sys.argv[1] == "photos":
        sys.exit(photos_main(*sys.argv[2:7]))
    if sys.argv[1] == "render":
        sys.exit(render_main(*sys.argv[2:5]))
    if sys.argv[1] == "splat-types":
        sys.exit(splat_types_main(*sys.argv[2:4]))
    sys.exit(main())
