"""The scene around splat objects: the colour management and Cycles settings they need, and the
scene camera's focal length that their screen-space filter follows.

- Colour: splat colours are display-referred (fitted to sRGB images); the material emits their
  sRGB-to-linear value, so the *Standard* view transform shows them exactly. Blender 4.x/5.x
  default to AgX (Filmic before 4.0), which tone-maps and desaturates: a splat under AgX is not
  the splat. Import sets Standard (and look None) unless asked not to, and says so; otherwise it
  warns (`view_transform_problem`).
- Background: a splat's see-through parts were fitted over the colour it was trained over (stored
  with it); import shows that colour as the world's (`set_world_colour`) unless asked not to.
- Cycles: every Gaussian along a camera ray costs a transparent bounce (its camera-facing disc
  in renders; two, front and back, for the viewport's ellipsoids); with the default limit (8) a
  ray stops after eight and the rest of the pixel renders black. Import raises
  `transparent_max_bounces` to TRANSPARENT_BOUNCES.
- The reference renderer's screen-space anti-aliasing is emulated per Gaussian at its depth
  from the scene camera, which needs the camera's focal length in pixels of the render: the
  handlers below keep the modifier input "Focal Length (px)" of every splat object in step with
  the scene camera, lens and render size (on load, on every depsgraph update, on frame change
  and before a render). 0 (no perspective camera) turns the filter off.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.app.handlers import persistent
from mathutils import Matrix

from gvae_core.conventions import srgb_to_linear

from . import nodes

#: The view transform that shows display-referred colours as they are.
VIEW_TRANSFORM = "Standard"
#: Cycles' transparent bounce limit set on import: 256 Gaussians along one ray in a render (Cycles'
#: default of 8 stops a ray long before a splat's Gaussians are all met; docs/benchmarks/blender.md).
TRANSPARENT_BOUNCES = 256
FOCAL_INPUT = "Focal Length (px)"


def add_camera(scene, c2w, fov_x: float, width: int, height: int):
    """A new scene camera at camera-to-world `c2w` (4x4, Blender's convention, as
    `gvae_core.camera.Camera.to_blender_c2w` gives it) with horizontal field of view `fov_x`
    (radians), the scene rendering width x height at 100%: a capture's camera in Blender."""
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.matrix_world = Matrix(c2w)
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.angle_x = fov_x
    cam.data.clip_start = 0.01
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    return cam


def camera_focal_px(scene) -> float:
    """Focal length of the scene camera in pixels of the final render (0: none, or not a
    perspective camera). Sensor fit as Blender's: Auto fits the larger image side."""
    cam = scene.camera
    if cam is None or cam.type != "CAMERA" or cam.data.type != "PERSP":
        return 0.0
    data, r = cam.data, scene.render
    scale = r.resolution_percentage / 100.0
    w, h = r.resolution_x * scale * r.pixel_aspect_x, r.resolution_y * scale * r.pixel_aspect_y
    fit = data.sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if w >= h else "VERTICAL"
        size = w if fit == "HORIZONTAL" else h
        sensor = data.sensor_width
    else:
        size = w if fit == "HORIZONTAL" else h
        sensor = data.sensor_width if fit == "HORIZONTAL" else data.sensor_height
    return float(data.lens) * size / max(float(sensor), 1e-6)


def sync_focal_length(scene) -> int:
    """Set "Focal Length (px)" of the splat objects of `scene` from its camera; returns how many
    changed (only those are written, so calling this from an update handler settles)."""
    if not any(ng.name.startswith(nodes.GROUP_NAMES) for ng in bpy.data.node_groups):
        return 0
    focal = camera_focal_px(scene)
    changed = 0
    for obj in scene.objects:
        mod = nodes.splat_modifier(obj)
        if mod is None or not any(i.name == FOCAL_INPUT for i in mod.node_group.interface.items_tree):
            continue
        if abs(float(nodes.get_modifier_input(mod, FOCAL_INPUT)) - focal) > 1e-6 * max(1.0, focal):
            nodes.set_modifier_input(mod, FOCAL_INPUT, focal)
            obj.update_tag()
            changed += 1
    return changed


def view_transform_problem(scene) -> str | None:
    """Why the scene does not show splat colours as they are, or None."""
    vs = scene.view_settings
    if vs.view_transform != VIEW_TRANSFORM or vs.look not in ("None", ""):
        return (f"the view transform is {vs.view_transform}" + (f" with look {vs.look}" if vs.look not in
                                                                ("None", "") else "")
                + f": splat colours are shown tone-mapped; set Render > Colour Management > View "
                f"Transform to {VIEW_TRANSFORM} to see them as trained")
    return None


def setup_scene(scene) -> list[str]:
    """Set what splats need (Standard view transform, look None, Cycles transparent bounces);
    returns a description of each change made (empty when the scene was already set)."""
    changes = []
    vs = scene.view_settings
    if vs.view_transform != VIEW_TRANSFORM:
        changes.append(f"view transform {vs.view_transform} -> {VIEW_TRANSFORM}")
        vs.view_transform = VIEW_TRANSFORM
    if vs.look not in ("None", ""):
        changes.append(f"look {vs.look} -> None")
        vs.look = "None"
    cycles = getattr(scene, "cycles", None)
    if cycles is not None and cycles.transparent_max_bounces < TRANSPARENT_BOUNCES:
        changes.append(f"Cycles transparent bounces {cycles.transparent_max_bounces} -> {TRANSPARENT_BOUNCES}")
        cycles.transparent_max_bounces = TRANSPARENT_BOUNCES
    return changes


def set_world_colour(scene, background) -> str:
    """Show `background` (display-referred RGB, what a splat was trained over) behind the splats:
    the world's colour and its Background node, as the linear value the Standard view transform
    shows as it (a world is made when the scene has none). Returns a description of the change."""
    linear = tuple(float(v) for v in srgb_to_linear(np.asarray(background, np.float64)))
    world = scene.world
    if world is None:
        world = scene.world = bpy.data.worlds.new("World")
    world.color = linear
    if world.node_tree is not None:
        for node in world.node_tree.nodes:
            if node.type == "BACKGROUND":
                node.inputs["Color"].default_value = (*linear, 1.0)
    return "world colour " + ",".join(f"{v:g}" for v in background) + " (what the splat was trained over)"


def bounce_problem(scene) -> str | None:
    """Why Cycles would cut rays through the splats short, or None."""
    cycles = getattr(scene, "cycles", None)
    if cycles is not None and cycles.transparent_max_bounces < TRANSPARENT_BOUNCES:
        return (f"Cycles stops rays after {cycles.transparent_max_bounces} transparent bounces (one per "
                f"Gaussian in a render): set Light Paths > Max Bounces > Transparent to {TRANSPARENT_BOUNCES} or more, "
                "or dense splats render dark")
    return None


@persistent
def _on_load(*_args):
    nodes.upgrade_outdated()  # a file saved with an older add-on: its splats draw as this one does
    for scene in bpy.data.scenes:
        sync_focal_length(scene)


@persistent
def _on_scene(scene, *_args):
    sync_focal_length(scene)


_HANDLERS = (("load_post", _on_load), ("depsgraph_update_post", _on_scene), ("frame_change_pre", _on_scene),
             ("render_pre", _on_scene))


def register():
    for name, fn in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if fn not in handlers:
            handlers.append(fn)


def unregister():
    for name, fn in _HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if fn in handlers:
            handlers.remove(fn)
