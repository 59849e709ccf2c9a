"""Blender scenarios for tests/blender/test_extension.py, each run in a fresh process.

    python tests/blender/_scenarios.py NAME ARGS.json

Blender's state is global per process, so every scenario starts its own: HOME and
BLENDER_USER_RESOURCES point into the test's temporary directory *before* bpy is imported, the
built extension zip is installed with `bpy.ops.extensions.package_install_files` and enabled,
and the operators run through the installed extension. Results (JSON, and arrays as .npz) go to
ARGS["out"]; pytest makes the assertions.
"""

from __future__ import annotations

import json
import os
import sys
import traceback


def setup(args: dict):
    home = args["home"]
    os.makedirs(home, exist_ok=True)
    if args.get("block_torch"):
        sys.modules["torch"] = None  # as in a Blender without torch: `import torch` fails
    os.environ["HOME"] = home
    os.environ["BLENDER_USER_RESOURCES"] = os.path.join(home, "blender")
    import bpy

    if args.get("install", True):
        result = bpy.ops.extensions.package_install_files(
            filepath=args["zip"], repo="user_default", enable_on_install=True)
        assert result == {"FINISHED"}, result
        if args.get("save_prefs"):
            bpy.ops.wm.save_userpref()
    return bpy


def counts(bpy) -> dict:
    """How many of each datablock the file holds (to show a failed operator changed nothing)."""
    return {"objects": sorted(o.name for o in bpy.data.objects),
            "meshes": sorted(m.name for m in bpy.data.meshes),
            "materials": sorted(m.name for m in bpy.data.materials),
            "node_groups": sorted(g.name for g in bpy.data.node_groups)}


def evaluated(bpy, obj) -> dict:
    """Instances and points of the evaluated (modifier applied) object."""
    obj.update_tag()  # modifier inputs set from Python do not tag the object themselves
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    geo = obj.evaluated_get(dg).evaluated_geometry()
    inst = geo.instances_pointcloud()
    pc = geo.pointcloud
    return {"instances": len(inst.points) if inst is not None else 0,
            "points": len(pc.points) if pc is not None else 0}


def attributes(obj) -> dict:
    """Every point attribute of the object's mesh, as numpy arrays by name."""
    import numpy as np

    out = {}
    me = obj.data
    n = len(me.vertices)
    for attr in me.attributes:
        if attr.domain != "POINT" or attr.name.startswith("."):
            continue
        width = {"FLOAT_VECTOR": 3, "INT32_2D": 2}.get(attr.data_type, 1)
        dtype = {"FLOAT": np.float32, "FLOAT_VECTOR": np.float32, "INT": np.int32,
                 "INT8": np.int8, "BOOLEAN": bool, "INT32_2D": np.int32}[attr.data_type]
        buf = np.empty(n * width, dtype)
        attr.data.foreach_get("vector" if attr.data_type == "FLOAT_VECTOR" else "value", buf)
        out[attr.name] = buf.reshape(n, width) if width > 1 else buf
    return out


def failure(bpy, call) -> dict:
    """Run `call`; report whether it raised, its message, and the datablocks before and after."""
    before = counts(bpy)
    try:
        call()
        error = None
    except Exception as exc:
        error = str(exc)
    return {"error": error, "unchanged": counts(bpy) == before}


# --------------------------------------------------------------------------------- scenarios

def scenario_io(bpy, args: dict) -> dict:
    import numpy as np

    res: dict = {}
    import gvae_core

    res["gvae_core_file"] = gvae_core.__file__
    res["addons"] = list(bpy.context.preferences.addons.keys())
    from bl_ext.user_default.gaussian_vae.gvae_addon import runtime

    res["refine_status"] = runtime.refine_status()
    before = counts(bpy)
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    obj = bpy.context.active_object
    res["new_objects"] = sorted(set(counts(bpy)["objects"]) - set(before["objects"]))
    res["modifiers"] = [m.type for m in obj.modifiers]
    res["eval"] = evaluated(bpy, obj)
    np.savez(args["out"] + ".attrs.npz", **attributes(obj))

    mod = obj.modifiers[0]
    ids = {item.name: item.identifier for item in mod.node_group.interface.items_tree
           if getattr(item, "in_out", None) == "INPUT"}
    mod[ids["Display Fraction"]] = 0.5
    res["eval_half"] = evaluated(bpy, obj)
    mod[ids["Display Fraction"]] = 1.0
    mod[ids["Min Opacity"]] = 0.5
    res["eval_opaque"] = evaluated(bpy, obj)
    mod[ids["Min Opacity"]] = 0.0
    mod[ids["Points Only"]] = True
    res["eval_points"] = evaluated(bpy, obj)
    mod[ids["Points Only"]] = False

    bpy.ops.export_scene.gaussian_splat(filepath=args["export"])

    # Object transform applied on export: rotation + uniform scale + translation.
    obj.rotation_euler = (0.3, -0.2, 1.1)
    obj.scale = (2.0, 2.0, 2.0)
    obj.location = (1.0, -2.0, 0.5)
    bpy.context.view_layer.update()
    res["matrix_world"] = [list(r) for r in obj.matrix_world]
    bpy.ops.export_scene.gaussian_splat(filepath=args["export_transformed"], apply_transform=True)
    obj.scale = (1.0, 2.0, 1.0)
    bpy.context.view_layer.update()
    res["nonuniform"] = failure(bpy, lambda: bpy.ops.export_scene.gaussian_splat(
        filepath=args["export_nonuniform"], apply_transform=True))
    res["nonuniform_written"] = os.path.exists(args["export_nonuniform"])

    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"], axis_conversion="Y_DOWN")
    res["y_down_rotation"] = list(bpy.context.active_object.rotation_euler)
    return res


def scenario_install(bpy, args: dict) -> dict:
    """Install (and with save_prefs, keep enabled for later processes). With `model_dir`: find the
    model Refine will use, with the extension's own gvae_core: "" for the bundled one when it
    loads, else untrained weights saved to model_dir (the real refine path, not a useful model);
    None with the reason when gvae_core.refine cannot run at all."""
    res = {"addons": list(bpy.context.preferences.addons.keys())}
    if args.get("model_dir"):
        try:
            import gvae_core.refinement  # noqa: F401
            from gvae_core.vae import GaussianVAE, load_default_model
        except Exception as exc:
            res.update(model=None, what=f"gvae_core.refinement is not importable: {exc}")
            return res
        try:
            load_default_model()
            res.update(model="", what="bundled model")
        except Exception:
            path = GaussianVAE.create(seed=0).save(args["model_dir"])
            res.update(model=str(path), what="untrained weights")
    return res


def scenario_bad(bpy, args: dict) -> dict:
    bpy.ops.import_scene.gaussian_splat(filepath=args["good"])  # a scene with something in it
    res = {}
    for name, path in args["bad"].items():
        res[name] = failure(bpy, lambda p=path: bpy.ops.import_scene.gaussian_splat(filepath=p))
    # Several files, the last bad: nothing is added.
    d = os.path.dirname(args["good"])
    files = [{"name": os.path.basename(args["good"])}, {"name": os.path.basename(args["bad"]["nan"])}]
    res["multi"] = failure(bpy, lambda: bpy.ops.import_scene.gaussian_splat(directory=d, files=files))
    return res


class _StandInResult:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def _stand_in_module(fail: bool):
    """TEST-ONLY stand-in for gvae_core.refinement: NOT the model. It appends, per step, a shifted copy
    of the first quarter of the input, so the glue's bookkeeping (rows, parents, steps, extras,
    gvae_step) can be checked exactly."""
    import types

    import numpy as np

    calls = []

    def refine(cloud, *, steps=1, budget="auto", model=None, cameras=None, lineage=None, seed=0,
               progress=None):
        calls.append({"steps": steps, "budget": budget, "model": model, "seed": seed, "n": len(cloud)})
        if fail:
            raise ValueError("stand-in failure")
        n = len(cloud)
        k = max(1, n // 4)
        out, parents, step = cloud, [], []
        for s in range(1, steps + 1):
            child = cloud.select(np.arange(k))
            child.means = child.means + np.float32(0.01 * s)
            out = out.append_children(child.replace(extra={}), np.arange(k))  # the core's extras policy
            parents.append(np.arange(k))
            step.append(np.full(k, s))
            if progress:
                progress(s / steps, f"stand-in step {s}")
        return _StandInResult(cloud=out, added=np.arange(n, len(out)), parents=np.concatenate(parents),
                              step=np.concatenate(step), scores=np.zeros(n),
                              timings={"hessian": 0.0, "model": 0.0, "total": 0.0})

    module = types.ModuleType("gvae_core.refinement")
    module.refine = refine
    module.calls = calls
    return module


def draw_panels(bpy) -> list[str]:
    """Call every panel's draw() with a recording layout (there is no UI in background mode);
    returns the labels it showed. Catches errors in the draw code itself."""
    from unittest import mock

    labels = []
    for name in ("GVAE_PT_main", "GVAE_PT_display", "GVAE_PT_refine"):
        cls = getattr(bpy.types, name)
        layout = mock.MagicMock()
        layout.label.side_effect = lambda text="", **kw: labels.append(text)
        layout.box.return_value = layout
        if cls.poll(bpy.context) if hasattr(cls, "poll") else True:
            cls.draw(mock.MagicMock(layout=layout), bpy.context)
    prefs = bpy.context.preferences.addons["bl_ext.user_default.gaussian_vae"].preferences
    layout = mock.MagicMock()
    layout.label.side_effect = lambda text="", **kw: labels.append(text)
    layout.box.return_value = layout
    type(prefs).draw(mock.MagicMock(layout=layout), bpy.context)
    return labels


def scenario_refine_glue(bpy, args: dict) -> dict:
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    obj = bpy.context.active_object
    res = {}
    # 1. Refine not importable: a clear error, object unchanged, the panel says so.
    sys.modules["gvae_core.refinement"] = None
    res["panel_unavailable"] = draw_panels(bpy)
    n0 = len(obj.data.vertices)
    res["unavailable"] = failure(bpy, lambda: bpy.ops.gvae.refine(steps=1))
    res["unavailable_count"] = len(obj.data.vertices)
    # 2. A refine that raises: reported, object unchanged.
    sys.modules["gvae_core.refinement"] = _stand_in_module(fail=True)
    res["failing"] = failure(bpy, lambda: bpy.ops.gvae.refine(steps=1))
    res["failing_count"] = len(obj.data.vertices)
    # 3. The stand-in, twice (steps continue from the first run).
    stand_in = _stand_in_module(fail=False)
    sys.modules["gvae_core.refinement"] = stand_in
    res["panel_available"] = draw_panels(bpy)
    res["bad_budget"] = failure(bpy, lambda: bpy.ops.gvae.refine(budget="lots"))
    bpy.ops.gvae.refine(steps=2, budget="0.5", seed=7)
    res["calls"] = list(stand_in.calls)
    import numpy as np

    np.savez(args["out"] + ".first.npz", **attributes(obj))
    res["materials"] = [m.name for m in obj.data.materials]
    res["modifiers"] = [m.type for m in obj.modifiers]
    res["eval"] = evaluated(bpy, obj)
    bpy.ops.gvae.refine(steps=1)
    np.savez(args["out"] + ".second.npz", **attributes(obj))
    res["n0"] = n0
    bpy.ops.export_scene.gaussian_splat(filepath=args["export"])
    bpy.ops.export_scene.gaussian_splat(filepath=args["export_step"], write_step=True)
    bpy.ops.import_scene.gaussian_splat(filepath=args["export_step"])
    np.savez(args["out"] + ".reimport.npz", **attributes(bpy.context.active_object))
    return res


def scenario_install_package(bpy, args: dict) -> dict:
    """The preferences' install button with a local wheel instead of torch (no network)."""
    from bl_ext.user_default.gaussian_vae.gvae_addon import runtime

    target = runtime.torch_dir()
    result = bpy.ops.gvae.install_torch(requirement=args["requirement"], pip_args=args["pip_args"])
    return {"result": sorted(result), "target": target, "on_path": target in sys.path,
            "listing": sorted(os.listdir(target)) if os.path.isdir(target) else []}


def scenario_cycles(bpy, args: dict) -> dict:
    """Render the imported scene with Cycles from a given camera, as ellipsoids and as points."""
    import numpy as np
    from mathutils import Matrix

    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"], scale_factor=args["scale_factor"])
    splat = bpy.context.active_object
    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("cam")
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.matrix_world = Matrix(args["c2w"])
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle_x = args["fov_x"]
    cam_data.clip_start = 0.01
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = args["samples"]
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.transparent_max_bounces = 64
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    scene.render.resolution_x, scene.render.resolution_y = args["width"], args["height"]
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = True
    scene.cycles.filter_width = 0.01
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    for tag, points in (("ellipsoids", False), ("points", True)):
        mod = splat.modifiers[0]
        ident = next(i.identifier for i in mod.node_group.interface.items_tree
                     if getattr(i, "in_out", None) == "INPUT" and i.name == "Points Only")
        mod[ident] = points
        splat.update_tag()
        scene.render.filepath = os.path.join(os.path.dirname(args["out"]), f"{tag}.exr")
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(scene.render.filepath)
        px = np.empty(args["width"] * args["height"] * 4, np.float32)
        img.pixels.foreach_get(px)
        np.save(args["out"] + f".{tag}.npy", px.reshape(args["height"], args["width"], 4)[::-1])
    return {}


SCENARIOS = {name[len("scenario_"):]: fn for name, fn in globals().items() if name.startswith("scenario_")}


def main() -> int:
    name, args_path = sys.argv[1], sys.argv[2]
    with open(args_path) as f:
        args = json.load(f)
    bpy = setup(args)
    try:
        result = SCENARIOS[name](bpy, args)
    except Exception:
        traceback.print_exc()
        return 3
    result["torch_imported"] = "torch" in sys.modules and sys.modules["torch"] is not None
    with open(args["out"], "w") as f:
        json.dump(result, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
