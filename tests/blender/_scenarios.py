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


def user_cache() -> str:
    """gvae's user cache directory as it is before a scenario changes HOME (`kernels.kernel_cache_dir`)."""
    return os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "gvae")


def setup(args: dict):
    home = args["home"]
    os.makedirs(home, exist_ok=True)
    if args.get("block_torch"):
        sys.modules["torch"] = None  # as in a Blender without torch: `import torch` fails
    if args.get("block_pillow"):
        sys.modules["PIL"] = None  # as in Blender, which bundles no Pillow
    # the user cache stays the suite's: a fresh HOME must not mean compiling the CPU kernels again
    os.environ.setdefault("GVAE_CACHE_DIR", user_cache())
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
            "node_groups": sorted(g.name for g in bpy.data.node_groups),
            "images": sorted(i.name for i in bpy.data.images)}


def evaluated(bpy, obj) -> dict:
    """Instances and points of the evaluated (modifier applied) object."""
    obj.update_tag()  # modifier inputs set from Python do not tag the object themselves
    dg = bpy.context.evaluated_depsgraph_get()
    dg.update()
    instances = points = 0  # through the depsgraph's instance list: Object.evaluated_geometry is 4.4+
    for inst in dg.object_instances:
        if inst.parent is None or inst.parent.original != obj:
            continue
        if inst.object.type == "POINTCLOUD":
            points += len(inst.object.data.points)
        elif inst.is_instance:
            instances += 1
    return {"instances": instances, "points": points}


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


def native_attributes(obj, path: str) -> None:
    """Every attribute of a Gaussian-splat point cloud object's data into the .npz `path` (":" in a name
    written "__")."""
    import numpy as np

    pc = obj.data
    n = len(pc.points)
    out = {}
    for attr in pc.attributes:
        if attr.name.startswith("."):
            continue
        width = {"FLOAT_VECTOR": 3, "FLOAT4": 4, "QUATERNION": 4}.get(attr.data_type, 1)
        buf = np.empty(n * width, np.int32 if attr.data_type == "INT" else np.float32)
        attr.data.foreach_get("vector" if attr.data_type in ("FLOAT_VECTOR", "FLOAT4") else "value", buf)
        out[attr.name.replace(":", "__")] = buf.reshape(n, width) if width > 1 else buf
    np.savez(path, **out)


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

    _splat_inputs(obj, {"Display Fraction": 0.5})
    res["eval_half"] = evaluated(bpy, obj)
    _splat_inputs(obj, {"Display Fraction": 1.0, "Min Opacity": 0.5})
    res["eval_opaque"] = evaluated(bpy, obj)
    _splat_inputs(obj, {"Min Opacity": 0.0, "Points Only": True})
    res["eval_points"] = evaluated(bpy, obj)
    _splat_inputs(obj, {"Points Only": False})

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

    # A splat that says what it was trained over: shown over it (the world's colour), kept on export.
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply_background"])
    world = bpy.context.scene.world
    res["world_colour"] = list(world.color)
    res["world_node_colour"] = [list(n.inputs["Color"].default_value) for n in world.node_tree.nodes
                                if n.type == "BACKGROUND"] if world.node_tree is not None else []
    bpy.ops.export_scene.gaussian_splat(filepath=args["export_background"])

    # The add-on finds sockets by name and type: Random Value's float output whichever its place,
    # and a clear error for a socket the node does not have (Probability is its boolean mode's).
    from bl_ext.user_default.gaussian_vae.gvae_addon import nodes

    ng = bpy.data.node_groups.new("socket probe", "GeometryNodeTree")
    rand = ng.nodes.new("FunctionNodeRandomValue")
    rand.data_type = "FLOAT"
    res["random_value"] = [nodes.socket(rand, "Value", "VALUE", output=True).identifier,
                           [s.identifier for s in rand.outputs]]
    try:
        nodes.socket(rand, "Probability", "VALUE")
    except LookupError as exc:
        res["missing_socket"] = str(exc)
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
            from gvae_core.vae import GaussianVAE, load_default_model, save_model
        except Exception as exc:
            res.update(model=None, what=f"gvae_core.refinement is not importable: {exc}")
            return res
        try:
            load_default_model()
            res.update(model="", what="bundled model")
        except Exception:
            path = save_model(GaussianVAE.create(seed=0), args["model_dir"])
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
               fidelity=None, progress=None):
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
    for name in ("GVAE_PT_main", "GVAE_PT_photos", "GVAE_PT_display", "GVAE_PT_refine", "GVAE_PT_compact"):
        cls = getattr(bpy.types, name)
        layout = mock.MagicMock()
        layout.label.side_effect = lambda text="", **kw: labels.append(text)
        layout.box.return_value = layout.column.return_value = layout.row.return_value = layout
        me = mock.MagicMock(layout=layout)  # the panel: its class attributes, its methods bound
        for attr in ("bl_label", "operator", "icon", "note", "module", "_settings", "_fill"):
            if hasattr(cls, attr):
                value = getattr(cls, attr)
                setattr(me, attr, value.__get__(me) if callable(value) and attr.startswith("_") else value)
        if cls.poll(bpy.context) if hasattr(cls, "poll") else True:
            cls.draw(me, bpy.context)
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
    # 2. A refine that raises: reported, object unchanged. Refine asks for PyTorch and safetensors
    # before it calls gvae_core.refinement: where Blender's Python has none (Python 3.13 here), an
    # empty placeholder module answers for each (the stand-in needs neither).
    import importlib.util
    import types

    for module in ("torch", "safetensors"):
        if importlib.util.find_spec(module) is None:
            sys.modules[module] = types.ModuleType(f"{module} (test placeholder)")
            if module == "torch":  # nor can the core's CPU kernels be made ready (the job does that first)
                warmup = sys.modules["gvae_core.warmup"] = types.ModuleType("gvae_core.warmup (test placeholder)")
                warmup.compile_kernels = lambda progress: None
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
    """The extension zip's bundled stand-in (`gvae_probe`, which says its wheel's Python), then the
    preferences' install button with local wheels instead of torch (no network)."""
    import gvae_probe

    from bl_ext.user_default.gaussian_vae.gvae_addon import runtime

    target = runtime.torch_dir()
    result = bpy.ops.gvae.install_torch(requirement=args["requirement"], pip_args=args["pip_args"])
    installed = os.path.join(target, "gvae_probe", "__init__.py")
    return {"bundled": gvae_probe.PYTHON, "result": sorted(result), "target": target, "on_path": target in sys.path,
            "listing": sorted(os.listdir(target)) if os.path.isdir(target) else [],
            "installed": open(installed).read() if os.path.exists(installed) else None}


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
        _splat_inputs(splat, {"Points Only": points, "Viewport Only": False})  # Points Only in the render too
        scene.render.filepath = os.path.join(os.path.dirname(args["out"]), f"{tag}.exr")
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(scene.render.filepath)
        px = np.empty(args["width"] * args["height"] * 4, np.float32)
        img.pixels.foreach_get(px)
        np.save(args["out"] + f".{tag}.npy", px.reshape(args["height"], args["width"], 4)[::-1])
    return {}


def scenario_formats(bpy, args: dict) -> dict:
    """File > Import of every splat format (one file at a time, then all at once; a SOG folder's
    meta.json), File > Export to .spz and .sog, bad files of each format, and the drag-and-drop file
    handler's extensions."""
    import numpy as np

    res: dict = {"imported": {}}
    for name, path in {**args["files"], "sog_folder": args["sog_folder"]}.items():
        before = counts(bpy)
        bpy.ops.import_scene.gaussian_splat(filepath=path)
        obj = bpy.context.active_object
        res["imported"][name] = {"object": obj.name, "vertices": len(obj.data.vertices),
                                 "new": sorted(set(counts(bpy)["objects"]) - set(before["objects"]))}
        np.savez(args["out"] + f".{name}.npz", **attributes(obj))
    spz_obj = bpy.data.objects[res["imported"]["spz"]["object"]]
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    spz_obj.select_set(True)
    bpy.context.view_layer.objects.active = spz_obj
    res["export_spz_poll"] = bpy.ops.export_scene.gaussian_splat_spz.poll()
    res["export_spz"] = sorted(bpy.ops.export_scene.gaussian_splat_spz(filepath=args["export_spz"]))
    res["export_ply"] = sorted(bpy.ops.export_scene.gaussian_splat(filepath=args["export_ply"]))
    sog_obj = bpy.data.objects[res["imported"]["sog"]["object"]]
    spz_obj.select_set(False)
    sog_obj.select_set(True)
    bpy.context.view_layer.objects.active = sog_obj
    images = counts(bpy)["images"]
    res["export_sog"] = sorted(bpy.ops.export_scene.gaussian_splat_sog(filepath=args["export_sog"]))
    np.savez(args["out"] + ".exported_sog_object.npz", **attributes(sog_obj))
    res["images_left"] = sorted(set(counts(bpy)["images"]) - set(images))
    res["images"] = counts(bpy)["images"]
    res["bad"] = {name: failure(bpy, lambda p=path: bpy.ops.import_scene.gaussian_splat(filepath=p))
                  for name, path in args["bad"].items()}
    files = [{"name": os.path.basename(p)} for p in args["files"].values()]
    before = counts(bpy)
    bpy.ops.import_scene.gaussian_splat(directory=os.path.dirname(args["files"]["spz"]), files=files)
    res["multi_new"] = len(set(counts(bpy)["objects"]) - set(before["objects"]))
    res["file_handler_extensions"] = bpy.types.GVAE_FH_gaussian_splat.bl_file_extensions
    res["import_filter"] = bpy.ops.import_scene.gaussian_splat.get_rna_type().properties["filter_glob"].default
    # glTF: export to .glb; an ordinary .glb goes to Blender's own glTF importer; Blender's splats need 5.3
    glb_obj = bpy.data.objects[res["imported"]["glb"]["object"]]
    for obj in bpy.context.view_layer.objects:
        obj.select_set(False)
    glb_obj.select_set(True)
    bpy.context.view_layer.objects.active = glb_obj
    res["export_glb"] = sorted(bpy.ops.export_scene.gaussian_splat_glb(filepath=args["export_glb"]))
    before = counts(bpy)
    res["plain_glb"] = sorted(bpy.ops.import_scene.gaussian_splat(filepath=args["plain_glb"]))
    res["plain_new"] = sorted((o.name, o.type, len(o.data.vertices)) for o in bpy.data.objects
                              if o.name not in before["objects"])
    from bl_ext.user_default.gaussian_vae.gvae_addon import convert

    res["native_available"] = convert.native_available()
    if not res["native_available"]:
        res["native_refused"] = failure(bpy, lambda: bpy.ops.import_scene.gaussian_splat(
            filepath=args["files"]["ply"], splat_type="NATIVE"))
    return res


def scenario_native(bpy, args: dict) -> dict:
    """Blender 5.3+: File > Import as a Gaussian-splat point cloud (beside Blender's own PLY importer
    on the same file), File > Export of such an object (ours and Blender's own) to .ply and .glb."""
    def dump(obj, name):
        native_attributes(obj, args["out"] + f".{name}.npz")
        return {"type": obj.type, "data_type": obj.data.type, "points": len(obj.data.points)}

    res = {}
    before = counts(bpy)
    res["import"] = sorted(bpy.ops.import_scene.gaussian_splat(filepath=args["ply"], splat_type="NATIVE"))
    ours = bpy.context.active_object
    res["ours"] = dump(ours, "ours")
    res["new"] = sorted(set(counts(bpy)["objects"]) - set(before["objects"]))
    bpy.ops.wm.ply_import(filepath=args["ply"])
    blenders = bpy.context.active_object
    res["blender"] = dump(blenders, "blender")
    for obj, path in ((ours, args["export_ply"]), (blenders, args["export_glb"])):
        for other in bpy.context.view_layer.objects:
            other.select_set(False)
        obj.select_set(True)
        bpy.context.view_layer.objects.active = obj
        res.setdefault("poll", []).append(bpy.ops.export_scene.gaussian_splat.poll())
        op = bpy.ops.export_scene.gaussian_splat_glb if path.endswith(".glb") else bpy.ops.export_scene.gaussian_splat
        res.setdefault("export", []).append(sorted(op(filepath=path)))
    bpy.ops.import_scene.gaussian_splat(filepath=args["glb"], splat_type="NATIVE")
    res["from_glb"] = dump(bpy.context.active_object, "from_glb")
    return res


def scenario_native_jobs(bpy, args: dict) -> dict:
    """Blender 5.3+: a splat imported by Blender's own PLY importer, refined and compacted through the
    add-on's jobs (TEST-ONLY stand-ins for the core functions, NOT the model: the refine returns the
    refined cloud the test made, the compaction keeps every other row), rendered by Cycles at 200% and
    100% with the modifier's Refinement on and off; then exported."""
    import types

    import numpy as np

    from bl_ext.user_default.gaussian_vae.gvae_addon import convert, nodes, refine_ops, render_setup
    from gvae_core.ply import read_ply

    def dump(obj, name):
        native_attributes(obj, args["out"] + f".{name}.npz")
        mod = nodes.splat_modifier(obj)
        return {"type": obj.type, "data_type": obj.data.type, "points": len(obj.data.points),
                "modifier": None if mod is None else mod.node_group.name}

    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    bpy.ops.wm.ply_import(filepath=args["ply"])  # Blender's own importer: no modifier, no gvae_ply
    name = bpy.context.active_object.name
    res = {"imported": dump(bpy.data.objects[name], "imported")}
    res["draw_as_gvae"] = sorted(bpy.ops.gvae.native_modifier())  # (Display's button; Refine would add it too)
    res["drawn"] = getattr(nodes.splat_modifier(bpy.data.objects[name]), "node_group", None) is not None
    received = {}
    refined_cloud = read_ply(args["refined"])

    def refine(cloud, *, progress=None, **kw):
        received.update(n=len(cloud), extra=sorted(cloud.extra))
        progress(1.0, "stand-in done")
        n = len(cloud)
        return types.SimpleNamespace(cloud=refined_cloud, added=np.arange(n, len(refined_cloud)),
                                     step=np.ones(len(refined_cloud) - n, np.int64), timings={"total": 0.0})

    def compact(cloud, *, progress=None, **kw):
        rows = np.arange(0, len(cloud), 2)
        progress(1.0, "stand-in done")
        return types.SimpleNamespace(cloud=cloud.select(rows), rows=rows, psnr=99.0, timings={}, warnings=[])

    job = refine_ops.RefineJob(bpy.data.objects[name], refine=refine).start()
    job.wait(60)
    res["refine_info"] = {k: job.finish()[k] for k in ("before", "after", "added")}
    res["received"] = received
    res["refined"] = dump(bpy.data.objects[name], "refined")
    obj = bpy.data.objects[name]
    bpy.context.view_layer.objects.active = obj
    res["panels"] = draw_panels(bpy)
    render_setup.add_camera(scene, args["c2w"], args["fov_x"], args["width"], args["height"])
    _converged_cycles(scene)
    scene.cycles.samples = args["samples"]
    scene.cycles.min_transparent_bounces = scene.cycles.transparent_max_bounces = 256
    render_setup.setup_scene(scene)
    mod = nodes.splat_modifier(obj)
    for percentage in (200, 100):
        for on in (True, False):
            nodes.set_modifier_input(mod, "Refinement", on)
            obj.update_tag()
            scene.render.resolution_percentage = percentage
            scene.render.filepath = os.path.join(os.path.dirname(args["out"]), f"native_{percentage}_{int(on)}.png")
            bpy.ops.render.render(write_still=True)
    res["focal"] = nodes.get_modifier_input(mod, "Focal Length (px)")
    bpy.ops.export_scene.gaussian_splat(filepath=args["export"])
    job = refine_ops.CompactJob(bpy.data.objects[name], compact=compact).start()
    job.wait(60)
    res["compact_info"] = {k: job.finish()[k] for k in ("before", "after")}
    res["compacted"] = dump(bpy.data.objects[name], "compacted")
    res["native_poll"] = [bpy.ops.gvae.refine.poll(), bpy.ops.gvae.compact.poll()]
    res["is_native"] = convert.is_native_splat(bpy.data.objects[name])
    return res


def scenario_photos(bpy, args: dict) -> dict:
    """New from Photos on a small posed capture, in Blender's default scene: said what it needs before
    it starts (torch blocked); cancelled before it trains and between stages (the scene as it was, the
    run folder kept); then the operator as a batch run calls it, and again with the same options (the
    run resumes: nothing more to train)."""
    import time

    from bl_ext.user_default.gaussian_vae.gvae_addon import photos_ops, runtime

    scene = bpy.context.scene

    def state():
        return {**counts(bpy), "cameras": sorted(c.name for c in bpy.data.cameras),
                "collections": sorted(c.name for c in bpy.data.collections),
                "view": scene.view_settings.view_transform, "camera": getattr(scene.camera, "name", None),
                "active": getattr(bpy.context.active_object, "name", None)}

    res = {}
    before = state()
    stash = sys.modules.get("torch")
    sys.modules["torch"] = None  # as in a Blender without torch
    try:
        res["missing"] = [what for what, _ in runtime.photos_missing(args["folder"])]
        res["refused"] = failure(bpy, lambda: bpy.ops.gvae.new_from_photos(folder=args["folder"]))
    finally:
        if stash is None:
            sys.modules.pop("torch")
        else:
            sys.modules["torch"] = stash
    res["refused_same"] = state() == before

    # The Blender side with a TEST-ONLY stand-in for the core's training (NOT a training: it returns the
    # cloud the test wrote, the capture's cameras read by the core): a Blender splat where Blender has
    # them, else the add-on's; cancel while it "trains".
    import threading

    from bl_ext.user_default.gaussian_vae.gvae_addon import convert
    from gvae_core.capture import read_capture
    from gvae_core.ply import read_ply

    def stand_in(folder, run_dir, *, report, cancelled, **kw):
        report(0.5, "stand-in training", 20.0)
        while args_release.is_set() is False and not cancelled():
            time.sleep(0.01)
        report(1.0, "stand-in done", 21.5)
        capture = read_capture(folder, 8, images=False)
        return {"cloud": read_ply(args["cloud"]), "log": [{"test_psnr": 21.5, "resolution": 16}], "sfm": None,
                "cameras": capture.cameras, "names": capture.names, "splits": capture.splits, "kind": capture.kind}

    native = convert.native_available()
    args_release = threading.Event()
    job = photos_ops.PhotosJob(args["folder"], run_dir=args["run_cancel"], train=stand_in).start()
    time.sleep(0.1)
    res["stand_in_heldout"] = job.heldout
    job.cancel()
    job.wait(30)
    res["stand_in_cancel"] = failure(bpy, job.finish)
    res["stand_in_cancel_same"] = state() == before
    args_release.set()
    job = photos_ops.PhotosJob(args["folder"], run_dir=args["run_cancel"], train=stand_in,
                               splat_type="NATIVE" if native else "MESH").start()
    job.wait(30)
    info = job.finish()
    obj = bpy.data.objects[info["object"]]
    res["stand_in"] = {"type": obj.type, "native": convert.is_native_splat(obj), "count": convert.splat_count(obj),
                       "modifier": [m.node_group.name for m in obj.modifiers], "cameras": info["cameras"],
                       "heldout": info["heldout"], "rotation": list(obj.rotation_euler)}
    cams = bpy.data.collections[f"{obj.name} cameras"]
    bpy.data.objects.remove(obj)  # (back to the scene as it was, for the real job below)
    for cam in list(cams.objects):
        data = cam.data
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(data)
    bpy.data.collections.remove(cams)
    for name in ("meshes", "pointclouds"):
        for data in list(getattr(bpy.data, name)):
            if data.users == 0:
                getattr(bpy.data, name).remove(data)
    res["available"] = runtime.torch_available()
    before = state()  # (the scene now: the stand-in's node group and material stay in the file)
    if not res["available"]:
        return res
    options = {"height": args["height"], "profile": "TINY", "iterations": args["iterations"]}
    t_start = time.perf_counter()
    job = photos_ops.PhotosJob(args["folder"], run_dir=args["run_cancel"], **options).start()
    job.cancel()
    job.wait(120)
    res["cancel"] = failure(bpy, job.finish)
    res["cancel_same"] = state() == before
    job = photos_ops.PhotosJob(args["folder"], run_dir=args["run_cancel"], **options).start()
    t0, messages = time.perf_counter(), []
    while not job.wait(0.02):
        messages.append(job.message)
        if job.message.startswith("stage 2"):
            job.cancel()
        assert time.perf_counter() - t0 < 300, "the job did not end"
    res["cancel_later"] = failure(bpy, job.finish)
    res["cancel_later_messages"] = sorted(set(messages))
    res["cancel_later_same"] = state() == before
    res["kept"] = sorted(os.listdir(args["run_cancel"]))
    res["seconds"] = {"cancels": time.perf_counter() - t_start}

    res["batch"] = sorted(bpy.ops.gvae.new_from_photos(folder=args["folder"], run_dir=args["run"], **options))
    obj = bpy.context.active_object
    res["object"] = {"name": obj.name, "type": obj.type, "count": len(obj.data.vertices),
                     "modifiers": [m.type for m in obj.modifiers], "rotation": list(obj.rotation_euler)}
    cams = bpy.data.collections.get(f"{obj.name} cameras")
    res["cameras"] = sorted(o.name for o in cams.objects) if cams is not None else None
    res["camera_parent"] = sorted({o.parent.name for o in cams.objects}) if cams is not None else None
    res["after"] = state()
    res["run"] = sorted(os.listdir(args["run"]))
    res["seconds"]["batch"] = time.perf_counter() - t_start - res["seconds"]["cancels"]
    res["again"] = sorted(bpy.ops.gvae.new_from_photos(folder=args["folder"], run_dir=args["run"], cameras=False,
                                                       **options))
    res["seconds"]["all"] = time.perf_counter() - t_start
    res["again_count"] = len(bpy.context.active_object.data.vertices)
    return res


def _input_names(obj) -> list[str]:
    return [item.name for item in obj.modifiers[0].node_group.interface.items_tree
            if getattr(item, "in_out", None) == "INPUT"]


def _splat_inputs(obj, values: dict) -> list[str]:
    """Set inputs of the splat modifier by name (through the add-on's accessor: where the values
    live depends on the Blender version); returns the names it does not have."""
    from bl_ext.user_default.gaussian_vae.gvae_addon import nodes

    names = _input_names(obj)
    for name, value in values.items():
        if name in names:
            nodes.set_modifier_input(obj.modifiers[0], name, value)
    obj.update_tag()
    return [name for name in values if name not in names]


def _splat_input(obj, name: str):
    from bl_ext.user_default.gaussian_vae.gvae_addon import nodes

    return nodes.get_modifier_input(obj.modifiers[0], name)


def _camera(bpy, args: dict):
    """The scene camera at args["c2w"] (Blender convention) with horizontal field of view fov_x."""
    from bl_ext.user_default.gaussian_vae.gvae_addon.render_setup import add_camera

    return add_camera(bpy.context.scene, args["c2w"], args["fov_x"], args["width"], args["height"])


def _converged_cycles(scene) -> None:
    """Cycles on the CPU, 1 sample at each pixel's centre (filter width 0.01, the reference renderer's
    point sampling), film transparent, to 8-bit RGBA PNG."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 1
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.filter_width = 0.01
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = "8"


def scenario_display_refined(bpy, args: dict) -> dict:
    """Refined and unrefined splats imported with the default options, each rendered alone by Cycles
    (as scenario_display) at the camera's size and at given Resolution % (a user's 200%: twice the
    training resolution), without Russian roulette on transparent bounces; then exported."""
    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    objects = {}
    for key, path in args["plys"].items():
        bpy.ops.import_scene.gaussian_splat(filepath=path)
        objects[key] = bpy.context.active_object
    _camera(bpy, args)
    _converged_cycles(scene)
    scene.cycles.min_transparent_bounces = scene.cycles.transparent_max_bounces
    res = {"focal": {}, "seconds": {}}
    import time
    for r in args["renders"]:
        t0 = time.perf_counter()
        for key, obj in objects.items():
            obj.hide_render = key != r["ply"]
        scene.render.resolution_percentage = r["percentage"]
        scene.render.filepath = os.path.join(os.path.dirname(args["out"]), f"{r['name']}.png")
        bpy.ops.render.render(write_still=True)
        res["focal"][r["name"]] = _splat_input(objects[r["ply"]], "Focal Length (px)")
        res["seconds"][r["name"]] = time.perf_counter() - t0
    for e in args.get("exports", []):  # File > Export of an object, with the operator's options
        bpy.context.view_layer.objects.active = objects[e["ply"]]
        operator = getattr(bpy.ops.export_scene, e["operator"])
        assert operator(filepath=e["path"], **e.get("options", {})) == {"FINISHED"}, e
    return res


def scenario_display(bpy, args: dict) -> dict:
    """File > Import with the default options into Blender's default scene, then Cycles renders to
    8-bit RGBA PNG (display space, as a user saves them) from the given camera, once per variant.
    Render settings that are not the import's: 1 sample at each pixel's centre (filter width 0.01,
    the reference renderer's point sampling) without Russian roulette on transparent bounces, so
    that one sample is the converged image; film transparent (the test composites over white)."""
    scene = bpy.context.scene
    for obj in list(bpy.data.objects):  # the default cube, light and camera; the settings stay
        bpy.data.objects.remove(obj)
    res = {"before": {"view": scene.view_settings.view_transform, "look": scene.view_settings.look,
                      "bounces": scene.cycles.transparent_max_bounces}}
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    obj = bpy.context.active_object
    res["after"] = {"view": scene.view_settings.view_transform, "look": scene.view_settings.look,
                    "bounces": scene.cycles.transparent_max_bounces}
    _camera(bpy, args)
    _converged_cycles(scene)
    default_bounces = scene.cycles.transparent_max_bounces
    res["missing_inputs"] = []
    for variant in args["variants"]:
        res["missing_inputs"] += _splat_inputs(obj, {"View-Dependent Colour": True, **variant.get("inputs", {})})
        scene.view_settings.view_transform = variant.get("view", res["after"]["view"])
        bounces = variant.get("bounces", default_bounces)
        scene.cycles.transparent_max_bounces = scene.cycles.min_transparent_bounces = bounces
        scene.render.filepath = os.path.join(os.path.dirname(args["out"]), f"{variant['name']}.png")
        bpy.ops.render.render(write_still=True)
    res["focal"] = _splat_input(obj, "Focal Length (px)")

    # Import with Set Up Scene off into a scene that shows splats wrong: the scene is left as it
    # is, with a warning for each problem.
    scene.view_settings.view_transform = "AgX"
    scene.cycles.transparent_max_bounces = 8
    res["no_setup"] = failure(bpy, lambda: bpy.ops.import_scene.gaussian_splat(filepath=args["ply"],
                                                                               setup_scene=False))
    res["no_setup"].update(view=scene.view_settings.view_transform, bounces=scene.cycles.transparent_max_bounces)
    return res


def scenario_display_nodes(bpy, args: dict) -> dict:
    """What the Geometry Nodes give each Gaussian, read back from the evaluated object: the
    instance matrices (ellipsoids) and, with Points Only, the points' gvae_color / gvae_alpha;
    and the focal length the handlers keep in step with the scene camera."""
    import numpy as np
    from mathutils import Matrix

    scene = bpy.context.scene
    _camera(bpy, args)
    res = {}
    for key, path in args["plys"].items():
        bpy.ops.import_scene.gaussian_splat(filepath=path, axis_conversion="Y_DOWN",
                                            scale_factor=args["scale_factor"])
        obj = bpy.context.active_object
        obj.matrix_world = Matrix(args["object_matrix"])
        bpy.context.view_layer.update()
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        mats = [np.array(inst.matrix_world) for inst in dg.object_instances
                if inst.is_instance and inst.parent is not None and inst.parent.original == obj]
        _splat_inputs(obj, {"Points Only": True})
        dg.update()
        pts = None
        for inst in dg.object_instances:
            if inst.object.type == "POINTCLOUD" and inst.parent is not None and inst.parent.original == obj:
                pc = inst.object.data
                n = len(pc.points)
                pts = {"position": np.empty(3 * n, np.float32), "gvae_color": np.empty(3 * n, np.float32),
                       "gvae_alpha": np.empty(n, np.float32)}
                pc.attributes["position"].data.foreach_get("vector", pts["position"])
                pc.attributes["gvae_color"].data.foreach_get("vector", pts["gvae_color"])
                pc.attributes["gvae_alpha"].data.foreach_get("value", pts["gvae_alpha"])
        np.savez(args["out"] + f".{key}.npz", matrices=np.array(mats).reshape(-1, 4, 4),
                 **{k: v for k, v in (pts or {}).items()})
        items = obj.modifiers[0].node_group.interface.items_tree
        res[key] = {"matrix_world": [list(r) for r in obj.matrix_world], "points": pts is not None,
                    "inputs": {i.name: _splat_input(obj, i.name) for i in items
                               if getattr(i, "in_out", None) == "INPUT" and i.socket_type in
                               ("NodeSocketFloat", "NodeSocketBool", "NodeSocketInt")}}
        if "inradius" not in res:  # the icosphere of each Detail, in instance space
            res["inradius"] = []
            for detail in (1, 2, 3, 4):
                _splat_inputs(obj, {"Points Only": False, "Detail": detail})
                dg.update()
                me = next(inst.object.data for inst in dg.object_instances
                          if inst.is_instance and inst.parent is not None and inst.parent.original == obj)
                res["inradius"].append(min(abs(p.normal.dot(me.vertices[p.vertices[0]].co)) for p in me.polygons))
        obj.hide_viewport = obj.hide_render = True  # out of the way of the next one
    # The focal length follows the render size and the camera (depsgraph handler).
    scene.render.resolution_percentage = 50
    bpy.context.evaluated_depsgraph_get().update()
    res["focal_half"] = _splat_input(bpy.context.active_object, "Focal Length (px)")
    scene.render.resolution_percentage = 100
    if args.get("upgrade"):
        res["upgrade"] = _upgrade_on_load(bpy, bpy.context.active_object.name, args["out"] + ".old.blend")
    return res


def _upgrade_on_load(bpy, name: str, path: str) -> dict:
    """A file saved by the add-on's previous version (its group marked older and without the node
    that moves a refined cloud's centres) opened again: the group is rebuilt on load, the object
    draws as this version does and keeps its modifier's inputs."""
    import numpy as np
    from bl_ext.user_default.gaussian_vae.gvae_addon import nodes

    def instances():
        obj = bpy.data.objects[name]
        obj.update_tag()
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        return np.array([np.array(i.matrix_world) for i in dg.object_instances
                         if i.is_instance and i.parent is not None and i.parent.original == obj])

    obj = bpy.data.objects[name]
    obj.hide_viewport = obj.hide_render = False
    _splat_inputs(obj, {"Min Opacity": 0.02, "Scale Factor": 1.1, "Points Only": False})
    now = instances()
    inputs = {n: _splat_input(obj, n) for n in _input_names(obj) if n not in ("Geometry", "Material")}
    ng = obj.modifiers[0].node_group
    ng["gvae_nodes_version"] = nodes.NODES_VERSION - 1
    ng.nodes.remove(next(n for n in ng.nodes if n.bl_idname == "GeometryNodeSetPosition"))
    old = instances()
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    obj = bpy.data.objects[name]
    ng = obj.modifiers[0].node_group
    after = instances()
    return {"old_differs": bool(len(old) != len(now) or not np.allclose(old, now, atol=1e-6)),
            "same": bool(len(after) == len(now) and np.allclose(after, now, rtol=1e-6, atol=1e-7)),
            "count": len(now), "version": ng.get("gvae_nodes_version") == nodes.NODES_VERSION,
            "inputs": inputs == {n: _splat_input(obj, n) for n in inputs},
            "material": getattr(_splat_input(obj, "Material"), "name", None) == nodes.MATERIAL_NAME,
            "set_position": any(n.bl_idname == "GeometryNodeSetPosition" for n in ng.nodes)}


def _job_stand_in(release, fail: bool = False):
    """TEST-ONLY stand-in for gvae_core.refinement.refine (NOT the model), for the refine job: it
    reports progress every few milliseconds until `release` is set (or the job cancels it through
    its progress callback), then appends a shifted copy of the first quarter of the input."""
    import time
    import types

    import numpy as np

    def refine(cloud, *, steps=1, budget="auto", model=None, seed=0, progress=None, **kw):
        k = 0
        while not release.is_set():
            k += 1
            progress(min(0.9, 0.01 * k), f"stand-in working {k}")
            time.sleep(0.005)
        if fail:
            raise ValueError("stand-in failure")
        n = len(cloud)
        child = cloud.select(np.arange(max(1, n // 4)))
        child.means = child.means + np.float32(0.01)
        out = cloud.append_children(child.replace(extra={}), np.arange(len(child)))
        progress(1.0, "stand-in done")
        return types.SimpleNamespace(cloud=out, added=np.arange(n, len(out)), step=np.ones(len(child), np.int64),
                                     timings={"hessian": 0.0, "model": 0.0, "total": 0.0})

    return refine


def scenario_refine_job(bpy, args: dict) -> dict:
    """The Refine job driven without a window: start, poll while the main thread works, finish;
    cancel; failure; the object changed meanwhile; the real gvae_core.refine through the job
    (and cancelled at its first progress report); the modal operator's handling of timer and Esc
    events (called with stand-in context and events); `invoke` without a window."""
    import threading
    import time
    import types
    from unittest import mock

    import numpy as np

    from bl_ext.user_default.gaussian_vae.gvae_addon import refine_ops

    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    obj = bpy.context.active_object
    name = obj.name
    n = len(obj.data.vertices)
    res = {"n": n}

    def state():
        o = bpy.data.objects[name]
        return {"counts": counts(bpy), "vertices": len(o.data.vertices), "mesh": o.data.name,
                "position": attributes(o)["position"].tolist()}

    def drive(job, release=None, cancel_after=None):
        """Poll until done while the main thread keeps working; returns the polls."""
        polls, t0 = [], time.perf_counter()
        while not job.done:
            done, fraction, message = job.poll()
            polls.append((fraction, message, len(bpy.data.objects[name].data.vertices)))
            bpy.data.meshes.remove(bpy.data.meshes.new("main thread is free"))
            if release is not None and len(polls) == 20:
                release.set()
            if cancel_after is not None and len(polls) == cancel_after:
                job.cancel()
            time.sleep(0.01)
            assert time.perf_counter() - t0 < 60, "job did not end"
        return polls

    # 1. success
    before = state()
    release = threading.Event()
    job = refine_ops.RefineJob(obj, refine=_job_stand_in(release)).start()
    polls = drive(job, release)
    res["polls"] = len(polls)
    res["fractions_rise"] = all(a[0] <= b[0] for a, b in zip(polls, polls[1:]))
    res["untouched_while_running"] = all(p[2] == n for p in polls)
    res["messages"] = sorted({p[1].split(" ")[0] for p in polls})
    info = job.finish()
    res["info"] = {k: info[k] for k in ("before", "after", "added")}
    res["after_success"] = len(bpy.data.objects[name].data.vertices)
    np.savez(args["out"] + ".success.npz", **attributes(bpy.data.objects[name]))

    # 2. cancel: the object stays as it was
    before = state()
    job = refine_ops.RefineJob(bpy.data.objects[name], refine=_job_stand_in(threading.Event())).start()
    drive(job, cancel_after=5)
    res["cancel_flag"] = job.cancelled
    res["cancel"] = failure(bpy, job.finish)
    res["cancel_state_same"] = state() == before

    # 3. failure
    release = threading.Event()
    job = refine_ops.RefineJob(bpy.data.objects[name], refine=_job_stand_in(release, fail=True)).start()
    drive(job, release)
    res["fail"] = failure(bpy, job.finish)
    res["fail_state_same"] = state() == before

    # 4. the object's mesh replaced while the job runs: the result is not written
    release = threading.Event()
    job = refine_ops.RefineJob(bpy.data.objects[name], refine=_job_stand_in(release)).start()
    other = bpy.data.meshes.new("replacement")
    other.from_pydata([(0, 0, 0)], [], [])
    old_mesh = bpy.data.objects[name].data
    bpy.data.objects[name].data = other
    drive(job, release)
    res["changed"] = failure(bpy, job.finish)
    res["changed_vertices"] = len(bpy.data.objects[name].data.vertices)
    bpy.data.objects[name].data = old_mesh
    bpy.data.meshes.remove(other)

    # 5. the real gvae_core.refine through the job, and cancelled at its first progress report
    from bl_ext.user_default.gaussian_vae.gvae_addon import runtime

    res["real_available"] = runtime.refine_status()[0]
    if not res["real_available"]:  # a Blender without torch: the rest needs it
        return res
    before = state()
    real = refine_ops.RefineJob(bpy.data.objects[name], steps=1, budget=0.5, model=args["model"] or None,
                                fidelity=None).start()
    real.cancel()
    real.wait(120)
    res["real_cancel"] = failure(bpy, real.finish)
    res["real_cancel_state_same"] = state() == before
    real = refine_ops.RefineJob(bpy.data.objects[name], steps=1, budget=0.5, model=args["model"] or None,
                                fidelity=None).start()
    real_polls = drive(real)
    res["real_messages"] = sorted({p[1] for p in real_polls})[:5]
    info = real.finish()
    res["real_info"] = {k: info[k] for k in ("before", "after", "added")}
    res["real_after"] = len(bpy.data.objects[name].data.vertices)

    # 6. the modal operator: timer events while running, Esc cancels, the object is unchanged;
    # then a run to the end (FINISHED); stand-in context, window manager and events
    op_cls = bpy.types.GVAE_OT_refine
    before = state()
    reports = []
    wm = mock.MagicMock()
    context = mock.MagicMock(window_manager=wm)
    status = []
    context.workspace.status_text_set.side_effect = status.append
    op = types.SimpleNamespace(report=lambda kind, text: reports.append((sorted(kind), text)), _timer=object())
    for name_ in ("_status", "_end", "_report_text"):
        setattr(op, name_, getattr(op_cls, name_).__get__(op))
    release = threading.Event()
    op._running = refine_ops.RefineJob(bpy.data.objects[name], refine=_job_stand_in(release)).start()
    refine_ops.RUNNING[name] = op._running
    res["poll_while_running"] = op_cls.poll(bpy.context)
    results = []
    for k in range(400):
        kind = "ESC" if k == 10 else ("TIMER" if k % 2 else "MOUSEMOVE")
        results.append(sorted(op_cls.modal(op, context, types.SimpleNamespace(type=kind))))
        if results[-1] != ["PASS_THROUGH"]:
            break
        time.sleep(0.01)
    res["modal_cancel"] = {"results": results[-1], "passed_through": results.count(["PASS_THROUGH"]),
                           "reports": reports[:], "status_cleared": status[-1] is None,
                           "status_progress": any(s and "Esc" in s for s in status[:-1]),
                           "running_cleared": name not in refine_ops.RUNNING, "state_same": state() == before}
    reports.clear()
    release = threading.Event()
    op._running = refine_ops.RefineJob(bpy.data.objects[name], refine=_job_stand_in(release)).start()
    refine_ops.RUNNING[name] = op._running
    for k in range(400):
        if k == 5:
            release.set()
        out = sorted(op_cls.modal(op, context, types.SimpleNamespace(type="TIMER")))
        if out != ["PASS_THROUGH"]:
            break
        time.sleep(0.01)
    res["modal_finish"] = {"result": out, "reports": reports[:],
                           "vertices": len(bpy.data.objects[name].data.vertices)}

    # 7. invoke without a user interface (background): runs to the end like execute
    res["invoke"] = sorted(bpy.ops.gvae.refine("INVOKE_DEFAULT", steps=1, budget="0.5", model=args["model"],
                                               fidelity_check=False))
    res["invoke_vertices"] = len(bpy.data.objects[name].data.vertices)
    # the fidelity check reaches the core: at tolerance 0 the untrained model's work is all put back
    bpy.ops.gvae.refine(steps=1, budget="0.5", model=args["model"], fidelity=0.0)
    res["checked_vertices"] = len(bpy.data.objects[name].data.vertices)

    # 8. one undo step: undo brings the object back as it was before the refine, redo refines again
    res["undo"] = undo_round(bpy, name, lambda: bpy.ops.gvae.refine("EXEC_DEFAULT", True, steps=1, budget="0.5",
                                                                    model=args["model"], fidelity_check=False))
    return res


def scenario_refine_images(bpy, args: dict) -> dict:
    """Refine with the capture's images, as a user runs it from the panel (the operator's `execute`,
    batch): images of another scene are refused and the object stays as it was; the capture's own
    are fitted (a few steps), the report (printed in batch) says what the fit measured, one undo step
    takes it back."""
    from bl_ext.user_default.gaussian_vae.gvae_addon import refine_ops, runtime

    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    name = bpy.context.active_object.name
    res = {"available": runtime.refine_status()[0]}
    if not res["available"]:
        return res
    before = len(bpy.data.objects[name].data.vertices)
    res["wrong"] = failure(bpy, lambda: bpy.ops.gvae.refine(images=args["wrong"], fit_steps=2))
    res["wrong_same"] = len(bpy.data.objects[name].data.vertices) == before
    print("--- refine with the capture's images", flush=True)
    res["undo"] = undo_round(bpy, name, lambda: bpy.ops.gvae.refine("EXEC_DEFAULT", True, images=args["images"],
                                                                    fit_steps=4))
    attrs = attributes(bpy.data.objects[name])
    res["octave_attrs"] = sorted(k for k in attrs if k.startswith("gvae_octave_"))
    res["settings"] = [p for p in ("images", "image_height") if hasattr(bpy.context.scene.gvae, p)]
    res["job_fields"] = all(hasattr(refine_ops.RefineJob(bpy.data.objects[name]), k)
                            for k in ("images", "image_height", "fit_steps"))
    return res


def undo_round(bpy, name: str, run) -> list[int]:
    """The object's vertex count before `run()` (an operator called as a button calls it: with the
    undo push that scripts leave out by default), after it, after undo and after redo."""
    bpy.ops.ed.undo_push(message="before the operator")
    counts = [len(bpy.data.objects[name].data.vertices)]
    run()
    counts.append(len(bpy.data.objects[name].data.vertices))
    bpy.ops.ed.undo()
    counts.append(len(bpy.data.objects[name].data.vertices))
    bpy.ops.ed.redo()
    return counts + [len(bpy.data.objects[name].data.vertices)]


def scenario_compact_job(bpy, args: dict) -> dict:
    """The Compact job (the Refine job's machinery) with the real gvae_core.compact: cancelled at
    its first progress report, a bad count (refused, nothing changed), a run through the job,
    the operator in batch (`execute`) and as a button without a window (`invoke`), one undo step."""
    import numpy as np

    from bl_ext.user_default.gaussian_vae.gvae_addon import refine_ops, runtime

    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    name = bpy.context.active_object.name
    res = {"available": runtime.refine_status()[0]}
    if not res["available"]:
        return res

    def state():
        o = bpy.data.objects[name]
        return {"counts": counts(bpy), "vertices": len(o.data.vertices), "mesh": o.data.name}

    before = state()
    job = refine_ops.CompactJob(bpy.data.objects[name], keep=0.5, distill=0).start()
    job.cancel()
    job.wait(120)
    res["cancel"] = failure(bpy, job.finish)
    res["cancel_same"] = state() == before
    job = refine_ops.CompactJob(bpy.data.objects[name], keep=None, count=10 ** 6, distill=0).start()
    job.wait(120)
    res["bad"] = failure(bpy, job.finish)
    res["bad_same"] = state() == before
    job = refine_ops.CompactJob(bpy.data.objects[name], keep=0.5, distill=0).start()
    messages = set()
    while not job.wait(0.05):
        messages.add(job.poll()[2].split(" ")[0])
    res["last_message"] = job.poll()[2]
    res["info"] = {k: v for k, v in job.finish().items() if k in ("before", "after", "psnr", "warnings")}
    res["messages"] = sorted(messages)
    np.savez(args["out"] + ".job.npz", **attributes(bpy.data.objects[name]))
    res["batch"] = sorted(bpy.ops.gvae.compact(keep=0.5, distill=1))  # (fine-tuned: a glimpse of the plumbing)
    res["batch_vertices"] = len(bpy.data.objects[name].data.vertices)
    res["batch_attrs"] = sorted(attributes(bpy.data.objects[name]))
    res["invoke"] = sorted(bpy.ops.gvae.compact("INVOKE_DEFAULT", count=5, removal="PRUNE", distill=0))
    res["invoke_vertices"] = len(bpy.data.objects[name].data.vertices)
    res["undo"] = undo_round(bpy, name, lambda: bpy.ops.gvae.compact("EXEC_DEFAULT", True, count=2, distill=0))
    return res


def scenario_compact_cameras(bpy, args: dict) -> dict:
    """What the Compact job hands the core (a stand-in that records it): the cameras found beside the
    imported file (the reference 3DGS's MODEL/cameras.json), none with Training Cameras off, the
    Cameras path's when given, the Photos' images (with the core's default removal); and what it says."""
    import types

    import numpy as np

    from bl_ext.user_default.gaussian_vae.gvae_addon import convert, refine_ops

    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    obj = bpy.context.active_object
    res = {"source": obj.get(convert.SOURCE_PROP)}
    got = []

    def compact(cloud, *, progress=None, cameras=None, images=None, removal="?", **kw):
        got.append([None if cameras is None else len(cameras), None if images is None else len(images), removal])
        rows = np.arange(len(cloud))
        progress(1.0, "stand-in done")
        rounds = [] if images is None else [{"iterations": 7, "best_at": 5, "judged_on": "the 1 of 4 set aside",
                                             "psnr_before": 20.0, "psnr_after": 21.5}]
        return types.SimpleNamespace(cloud=cloud, rows=rows, psnr=99.0, timings={}, warnings=[], rounds=rounds)

    notes, tuned = [], []
    for kw in ({}, {"found_cameras": False}, {"cameras": args["cameras"]}, {"images": args["images"], "removal": None}):
        job = refine_ops.CompactJob(obj, keep=1.0, compact=compact, **kw).start()
        job.wait(60)
        info = job.finish()
        notes.append(info["views"])
        tuned.append(info["tuned"])
    res["got"], res["notes"], res["tuned"] = got, notes, tuned
    return res


def scenario_eevee(bpy, args: dict) -> dict:
    """EEVEE (Blender's default engine) renders the imported splats to PNG. First an empty scene
    (the probe: whether EEVEE runs here at all, without a GPU it needs a software OpenGL), then the
    default import from the given camera."""
    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    scene.render.engine = "BLENDER_EEVEE_NEXT" if bpy.app.version < (5, 0, 0) else "BLENDER_EEVEE"
    _camera(bpy, {**args, "width": 8, "height": 8})
    scene.render.filepath = os.path.join(os.path.dirname(args["out"]), "probe.png")
    try:
        bpy.ops.render.render(write_still=True)
    except Exception as exc:
        return {"unavailable": f"EEVEE cannot render an empty scene here: {exc}"}
    print("EEVEE probe rendered", flush=True)
    bpy.ops.import_scene.gaussian_splat(filepath=args["ply"])
    scene.render.resolution_x, scene.render.resolution_y = args["width"], args["height"]
    scene.eevee.taa_render_samples = args["samples"]
    # Nothing here casts or takes light (the splats emit): without shadows and ray tracing EEVEE
    # draws the same pixels (checked: identical PNGs, 5.0.1) in a fifth of llvmpipe's time.
    for name in ("use_shadows", "use_raytracing"):
        if hasattr(scene.eevee, name):
            setattr(scene.eevee, name, False)
    scene.render.film_transparent = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.filepath = os.path.join(os.path.dirname(args["out"]), "eevee.png")
    bpy.ops.render.render(write_still=True)
    return {"engine": scene.render.engine}


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
    result["blender_version"] = list(bpy.app.version)
    with open(args["out"], "w") as f:
        json.dump(result, f)
    return 0


if __name__ == "__main__":
    code = main()
    import bpy

    if bpy.app.version < (5, 0, 0):
        # The bpy module of Blender 4.2 crashes, and 4.5's hangs, at interpreter exit once any
        # Python operator with execute/invoke/modal is registered (the Blender executable does
        # not): leave without the module's teardown there; the results are written.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
