"""The bpy side of scene generation: materials, mesh objects, lights, render set-up, and export
of the ground truth. This package is the only part of gvae_core that touches bpy, and it does so
only inside functions (`require_bpy`), so importing gvae_core never needs Blender."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .geometry import Mesh

INSTALL_HINT = "pip install bpy==5.0.1 (or `make install`)"


class BlenderNotAvailable(ImportError):
    """Raised when scene generation is asked for but the bpy module is missing."""


def require_bpy():
    """The bpy module, or a clear error saying how to install it."""
    try:
        import bpy
    except ImportError as exc:
        raise BlenderNotAvailable(f"generating scenes needs Blender's Python module bpy: {INSTALL_HINT}") from exc
    return bpy


def reset():
    """An empty Blender session: no objects, default units, z up."""
    bpy = require_bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


# ---------------------------------------------------------------------------------- materials
def node(tree, kind: str, location=(0, 0), **inputs):
    """Add a shader node of type `kind` and set its inputs by name (or properties, for names
    that are not sockets)."""
    n = tree.nodes.new(kind)
    n.location = location
    for key, value in inputs.items():
        if key in n.inputs:
            n.inputs[key].default_value = value
        else:
            setattr(n, key, value)
    return n


def material(name: str, color=(0.8, 0.8, 0.8), *, roughness: float = 0.5, metallic: float = 0.0,
             specular: float = 0.5, coat: float = 0.0, coat_roughness: float = 0.03,
             anisotropic: float = 0.0, shader=None):
    """A Principled BSDF material. `shader(tree, bsdf)` may wire textures into the BSDF."""
    bpy = require_bpy()
    mat = bpy.data.materials.new(name)
    tree = mat.node_tree
    bsdf = tree.nodes.get("Principled BSDF")
    values = {"Base Color": (*color, 1.0), "Roughness": roughness, "Metallic": metallic,
              "Specular IOR Level": specular, "Coat Weight": coat, "Coat Roughness": coat_roughness,
              "Anisotropic": anisotropic}
    for key, value in values.items():
        bsdf.inputs[key].default_value = value
    if shader is not None:
        shader(tree, bsdf)
    return mat


# ------------------------------------------------------------------------------------ objects
def add_mesh(name: str, mesh: Mesh, mat, *, smooth: bool | float = False, bevel: float = 0.0,
             bevel_segments: int = 2, subdivide: int = 0):
    """Link a mesh object built from numpy (verts, faces). `smooth` True shades smooth, a float
    shades smooth below that angle (radians) and sharp above it; modifiers are optional."""
    bpy = require_bpy()
    verts, faces = mesh
    me = bpy.data.meshes.new(name)
    me.from_pydata(np.asarray(verts, np.float64).tolist(), [], [tuple(int(i) for i in f) for f in faces])
    me.validate(clean_customdata=False)
    me.update()
    if smooth is not False:
        me.shade_smooth()
        if smooth is not True:
            me.set_sharp_from_angle(angle=float(smooth))
    me.materials.append(mat)
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    if bevel > 0:
        mod = obj.modifiers.new("bevel", "BEVEL")
        mod.width = bevel
        mod.segments = bevel_segments
        mod.limit_method = "ANGLE"
    if subdivide:
        mod = obj.modifiers.new("subdivide", "SUBSURF")
        mod.levels = mod.render_levels = subdivide  # same in viewport and render: the GT mesh matches
    return obj


def add_light(kind: str, location, *, energy: float, size: float = 0.5, target=(0.0, 0.0, 0.0),
              angle: float = math.radians(3.0)):
    """A light at `location` aimed at `target` (SUN, AREA or POINT)."""
    bpy = require_bpy()
    from mathutils import Vector

    data = bpy.data.lights.new(f"{kind.lower()}_light", kind)
    data.energy = energy
    if kind == "AREA":
        data.size = size
    elif kind == "SUN":
        data.angle = angle
    else:
        data.shadow_soft_size = size
    obj = bpy.data.objects.new(data.name, data)
    obj.location = location
    direction = Vector(target) - Vector(location)
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(obj)
    return obj


def studio_world(strength: float = 0.8):
    """A world that lights from everywhere but not evenly (ground darker, a bright band at the
    horizon, blue-white zenith), so that glossy surfaces have something to reflect."""
    bpy = require_bpy()
    world = bpy.data.worlds.new("studio")
    bpy.context.scene.world = world
    tree = world.node_tree
    bg = tree.nodes.get("Background")
    coords = node(tree, "ShaderNodeTexCoord", (-900, 0))
    split = node(tree, "ShaderNodeSeparateXYZ", (-700, 0))
    tree.links.new(coords.outputs["Generated"], split.inputs[0])
    ramp = node(tree, "ShaderNodeValToRGB", (-500, 0))
    stops = [(0.0, (0.12, 0.10, 0.09)), (0.45, (0.35, 0.33, 0.30)), (0.52, (1.0, 0.97, 0.9)),
             (0.62, (0.55, 0.6, 0.7)), (1.0, (0.75, 0.85, 1.0))]
    elems = ramp.color_ramp.elements
    elems[0].position, elems[0].color = stops[0][0], (*stops[0][1], 1.0)
    elems[1].position, elems[1].color = stops[-1][0], (*stops[-1][1], 1.0)
    for pos, col in stops[1:-1]:
        e = elems.new(pos)
        e.color = (*col, 1.0)
    remap = node(tree, "ShaderNodeMapRange", (-650, -200), **{"From Min": -1.0, "From Max": 1.0})
    tree.links.new(split.outputs["Z"], remap.inputs["Value"])
    tree.links.new(remap.outputs["Result"], ramp.inputs["Fac"])
    tree.links.new(ramp.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = strength
    return world


# ------------------------------------------------------------------------------------ render
def setup_render(resolution: int, samples: int, seed: int, threads: int, angle_x: float):
    """Cycles on the CPU, transparent film, RGBA PNG, denoised, reproducible for a seed; adds the
    camera and returns it."""
    bpy = require_bpy()
    scene = bpy.context.scene
    render = scene.render
    render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = samples
    cycles.use_adaptive_sampling = False  # fixed work per pixel: simpler to reason about timings
    cycles.seed = seed
    cycles.use_animated_seed = False
    cycles.max_bounces = 4
    cycles.diffuse_bounces = 2
    cycles.glossy_bounces = 2
    cycles.transmission_bounces = 2
    cycles.transparent_max_bounces = 4
    cycles.volume_bounces = 0
    cycles.caustics_reflective = False
    cycles.caustics_refractive = False
    cycles.sample_clamp_indirect = 10.0  # no fireflies from the few samples
    cycles.use_denoising = True
    cycles.denoiser = "OPENIMAGEDENOISE"
    cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    cycles.denoising_prefilter = "FAST"  # the albedo/normal guides are clean enough; 3x cheaper
    cycles.denoising_quality = "BALANCED"
    render.film_transparent = True
    render.resolution_x = render.resolution_y = resolution
    render.resolution_percentage = 100
    render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    render.threads_mode = "FIXED"
    render.threads = threads
    render.use_persistent_data = True  # keep the BVH between views
    for prop in render.bl_rna.properties:  # no metadata (render time, date...): reproducible files
        if prop.identifier.startswith("use_stamp") and not prop.is_readonly:
            setattr(render, prop.identifier, False)
    settings = render.image_settings
    settings.file_format = "PNG"
    settings.color_mode = "RGBA"
    settings.color_depth = "8"
    settings.compression = 15
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0

    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = angle_x
    cam_data.clip_start = 0.05
    cam_data.clip_end = 100.0
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


def render_view(camera, c2w: np.ndarray, path: Path) -> None:
    """Render the scene from a Blender camera-to-world matrix into `path` (a .png)."""
    bpy = require_bpy()
    from mathutils import Matrix

    camera.matrix_world = Matrix(np.asarray(c2w, np.float64).tolist())
    scene = bpy.context.scene
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    _strip_metadata(Path(path))


def _strip_metadata(path: Path) -> None:
    """Rewrite a PNG without the text chunks Cycles adds (render times differ on every run), so
    that the same seed gives byte-identical files."""
    from PIL import Image

    with Image.open(path) as im:
        im.load()
        pixels = im.copy()
    pixels.save(path, format="PNG", compress_level=6)


def fit_in_sphere(radius: float) -> tuple[np.ndarray, float]:
    """Move (and, if needed, shrink) all mesh objects so that their bounding box is centred on
    the origin and every vertex lies within `radius`: then no camera at the NeRF-Synthetic
    distance cuts the object off. Returns the applied offset and scale."""
    bpy = require_bpy()
    from mathutils import Matrix

    verts, _ = world_triangles()
    center = 0.5 * (verts.min(0) + verts.max(0))
    extent = np.linalg.norm(verts - center, axis=1).max()
    scale = min(1.0, radius / extent)
    fit = Matrix.Diagonal((scale, scale, scale, 1.0)) @ Matrix.Translation((-center).tolist())
    for obj in bpy.context.scene.objects:
        if obj.type == "MESH":
            obj.matrix_world = fit @ obj.matrix_world
    bpy.context.view_layer.update()
    return center, scale


# ------------------------------------------------------------------------------ ground truth
def world_triangles() -> tuple[np.ndarray, np.ndarray]:
    """All mesh objects of the scene, evaluated (modifiers applied), joined and triangulated, in
    world coordinates: vertices (V,3) float64 and triangles (F,3) int64."""
    bpy = require_bpy()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    verts, tris, offset = [], [], 0
    for obj in sorted(bpy.context.scene.objects, key=lambda o: o.name):
        if obj.type != "MESH":
            continue
        ev = obj.evaluated_get(depsgraph)
        me = ev.to_mesh()
        me.calc_loop_triangles()
        co = np.empty(len(me.vertices) * 3, np.float64)
        me.vertices.foreach_get("co", co)
        tri = np.empty(len(me.loop_triangles) * 3, np.int64)
        me.loop_triangles.foreach_get("vertices", tri)
        m = np.array(ev.matrix_world, np.float64)
        co = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
        verts.append(co)
        tris.append(tri.reshape(-1, 3) + offset)
        offset += len(co)
        ev.to_mesh_clear()
    return np.vstack(verts), np.vstack(tris)


def visible_points(points: np.ndarray, verts: np.ndarray, tris: np.ndarray, cameras: list) -> np.ndarray:
    """Boolean mask: which surface points some camera (`gvae_core.Camera`) sees, i.e. they lie in
    its image and the ray from its centre reaches them unoccluded (mathutils BVH ray casts)."""
    require_bpy()
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    bvh = BVHTree.FromPolygons(verts.tolist(), tris.tolist(), all_triangles=True, epsilon=0.0)
    seen = np.zeros(len(points), bool)
    for cam in cameras:
        uv, z = cam.project(points)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        todo = np.flatnonzero(inside & ~seen)
        if not len(todo):
            continue
        origin = Vector(cam.center.tolist())
        delta = points[todo] - cam.center
        dist = np.linalg.norm(delta, axis=1)
        dirs = delta / dist[:, None]
        reach = dist - (1e-4 + 1e-4 * dist)  # a hit closer than this is an occluder
        cast = bvh.ray_cast
        for k, d, r in zip(todo.tolist(), dirs.tolist(), reach.tolist()):
            if cast(origin, Vector(d), r)[0] is None:
                seen[k] = True
    return seen
