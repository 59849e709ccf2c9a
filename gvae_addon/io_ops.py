"""File > Import / Export > Gaussian Splat: splat files (.ply, .splat, .spz, .sog, .glb/.gltf) <-> splat objects.

A .glb or .gltf without Gaussian splats is handed to Blender's own glTF importer (an ordinary glTF
file dropped on the viewport offers both importers, Blender's first: a file handler sees only the
file's extension, not its content). Blender 5.3 and later draw splats themselves: Import can make
such a Gaussian-splat point cloud instead of the add-on's splat mesh, and Export writes either."""

from __future__ import annotations

import math
import os
import tempfile
import time
import warnings
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, CollectionProperty, EnumProperty, FloatProperty, StringProperty
from bpy.types import Operator, OperatorFileListElement
from bpy_extras.io_utils import ExportHelper, ImportHelper

from gvae_core.cloud import GaussianCloud
from gvae_core.formats import WebpCodec, detect_format, read_splat_file, write_splat_file
from gvae_core.formats.gltf import has_splats
from gvae_core.octaves import bake as bake_octaves
from gvae_core.octaves import has_octaves

from . import convert, nodes, render_setup

#: Object rotation (Euler XYZ) per axis option: the data stay as in the file.
AXES = {
    "NONE": (0.0, 0.0, 0.0),
    # y down, z forward (3DGS / COLMAP / OpenCV) -> Blender z up, y forward: +y -> -z, +z -> +y.
    "Y_DOWN": (-math.pi / 2, 0.0, 0.0),
}


#: What a splat object can be: the add-on's splat mesh (every version) or Blender 5.3+'s own splat.
SPLAT_TYPES = (
    ("MESH", "Add-on Splat", "A mesh drawn by the add-on's Geometry Nodes (every Blender version; the closest to gvae "
     "render in Cycles, with the display options of the sidebar)"),
    ("NATIVE", "Blender Gaussian Splat", "A point cloud of type Gaussian Splat, drawn by Blender itself (Blender 5.3 "
     "and later; a modifier adds the anti-aliasing and a refinement for the scene camera; Cycles blends it in its "
     "own order, a little further from gvae render)"))
#: The choices of `AXES`, for an operator's enum.
AXES_ITEMS = (("NONE", "As Stored (Z Up)", "Keep the file's axes (scenes made in Blender, NeRF-Synthetic)"),
              ("Y_DOWN", "Y Down, Z Forward", "3DGS/COLMAP/OpenCV scenes: rotate the object so that -Y becomes up "
               "(an object rotation; the data are not changed)"))


def set_up_scene(scene, setup: bool = True, background=None) -> list[str]:
    """What a new splat object needs of its scene (`render_setup`): the focal length its filters follow
    and, with `setup`, the Standard view transform, Cycles' transparent bounces and the world colour the
    splat was trained over (`background`, when known). Returns a description of each change made."""
    render_setup.sync_focal_length(scene)
    if not setup:
        return []
    changes = render_setup.setup_scene(scene)
    if background is not None:
        changes.append(render_setup.set_world_colour(scene, background))
    return changes


def _with_messages(function, *args, **kwargs):
    """function(*args, **kwargs) and the warnings it gave (dropped rows, say), as messages."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = function(*args, **kwargs)
    return value, [str(w.message) for w in caught]


def blender_webp() -> WebpCodec:
    """Lossless WebP through Blender's own image reader and writer, for SOG files: Blender bundles no
    Pillow. Exact both ways, except that Blender's writer drops the colour of fully transparent
    pixels (in SOG: the colour of Gaussians stored with opacity code 0, which are invisible)."""

    def decode(data: bytes) -> np.ndarray:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "image.webp")
            Path(path).write_bytes(data)
            image = bpy.data.images.load(path, check_existing=False)
            try:
                width, height = image.size
                channels = image.channels
                if not width or not height or image.is_float or channels not in (3, 4):
                    raise ValueError("Blender could not read it as an 8-bit image")
                pixels = np.empty(width * height * channels, np.float32)
                image.pixels.foreach_get(pixels)
            finally:
                bpy.data.images.remove(image)
        rgba = np.full((height, width, 4), 255, np.uint8)
        rgba[..., :channels] = np.rint(pixels.reshape(height, width, channels)[::-1] * 255.0)
        return rgba

    def encode(rgba: np.ndarray) -> bytes:
        height, width = rgba.shape[:2]
        image = bpy.data.images.new("gvae_sog_image", width, height, alpha=True, float_buffer=False)
        try:
            image.pixels.foreach_set((rgba[::-1].astype(np.float32) / 255.0).reshape(-1))
            image.file_format = "WEBP"
            with tempfile.TemporaryDirectory() as tmp:
                path = os.path.join(tmp, "image.webp")
                image.save(filepath=path, quality=100)  # quality 100: lossless
                return Path(path).read_bytes()
        finally:
            bpy.data.images.remove(image)

    return WebpCodec("Blender", decode, encode)


def _remove_data(data) -> None:
    (bpy.data.meshes if isinstance(data, bpy.types.Mesh) else bpy.data.pointclouds).remove(data)


def _new_object(context, name: str, data, axes: str, setup=None):
    """A new object of `data` (a splat mesh or point cloud) turned by `axes`, `setup(obj)` applied,
    linked to the active collection; on any failure the object and its data are removed again."""
    obj = None
    try:
        obj = bpy.data.objects.new(name, data)
        obj.rotation_euler = AXES[axes]
        if setup is not None:
            setup(obj)
        context.collection.objects.link(obj)
    except BaseException:
        if obj is not None:
            bpy.data.objects.remove(obj)
        _remove_data(data)
        raise
    return obj


def build_native_splat(context, cloud: GaussianCloud, name: str, *, axes: str = "NONE"):
    """A new Blender 5.3+ Gaussian-splat point cloud object holding `cloud` (`convert.pointcloud_from_cloud`)
    with the modifier that draws it as `gvae_core.render` does for the scene camera
    (`nodes.add_native_modifier`), linked to the active collection (removed again if anything fails)."""
    cloud, steps = _split_steps(cloud)
    return _new_object(context, name, convert.pointcloud_from_cloud(cloud, name, steps=steps), axes,
                       nodes.add_native_modifier)


def _split_steps(cloud: GaussianCloud):
    """(cloud without its integer `gvae_step` property, those steps or None): Export's "Write Refine Step"
    property becomes the object's `gvae_step` attribute again."""
    steps = cloud.extra.get(convert.STEP_ATTR)
    if steps is None or not np.issubdtype(steps.dtype, np.integer):
        return cloud, None
    return cloud.replace(extra={k: v for k, v in cloud.extra.items() if k != convert.STEP_ATTR}), steps


def remove_splat(obj) -> None:
    """Remove a splat object made by an import, and its data."""
    data = obj.data
    bpy.data.objects.remove(obj)
    _remove_data(data)


def is_plain_gltf(path: str) -> bool:
    """Whether `path` is a glTF file without Gaussian splats (for Blender's own glTF importer)."""
    try:
        return detect_format(path) == "gltf" and not has_splats(path)
    except (OSError, ValueError):
        return False  # (the splat reader says what is wrong with it)


def build_splat(context, cloud: GaussianCloud, name: str, *, axes: str = "NONE",
                scale_factor: float = nodes.DEFAULT_SCALE_FACTOR, fraction: float = 1.0,
                points_only: bool = False, min_opacity: float = 0.0, view_dependent: bool = True):
    """A new splat object holding `cloud`, linked to the active collection (removed again if
    anything fails). An integer `gvae_step` property (written by Export with "Write Refine Step")
    becomes the object's `gvae_step` attribute again."""
    cloud, steps = _split_steps(cloud)
    return _new_object(context, name, convert.mesh_from_cloud(cloud, name, steps=steps), axes, lambda obj:
                       nodes.add_splat_modifier(obj, scale_factor=scale_factor, fraction=fraction,
                                                points_only=points_only, min_opacity=min_opacity,
                                                view_dependent=view_dependent))


def export_splat(obj, path: str, *, apply_transform: bool = False, write_step: bool = False, bake: float = 0.0):
    """Write a splat object in the format `path` asks for (`write_splat_file`: a 3DGS PLY, .spz,
    .sog, ...; atomic). `bake` > 0: a refined object's changes per octave baked in for that factor
    of its training resolution (`gvae_core.octaves.bake`). Returns (count, messages)."""
    cloud, steps = convert.cloud_from_object(obj)
    messages = []
    if bake > 0 and has_octaves(cloud):
        cloud = bake_octaves(cloud, bake)
        messages.append(f"refinement baked in for {bake:g}x the training resolution")
    if apply_transform:
        try:
            cloud, messages = _with_messages(cloud.transformed, obj.matrix_world)
        except ValueError as exc:
            raise ValueError(f"object {obj.name!r}: {exc}; apply or clear its scale, or export without "
                             "Apply Transform") from None
    if write_step and steps is not None:
        cloud = cloud.replace(extra={**cloud.extra, convert.STEP_ATTR: steps})
    _, written = _with_messages(write_splat_file, cloud, path, webp=blender_webp())
    return len(cloud), messages + written


def splat_name(path: str) -> str:
    """The object name for a splat file: its name without extension (a SOG meta.json: its folder's)."""
    p = Path(path)
    if p.name.lower() == "meta.json" and p.parent.name:
        return p.parent.name
    return p.stem or "splat"


class IMPORT_SCENE_OT_gaussian_splat(Operator, ImportHelper):
    """Import Gaussian splat files (3DGS or compressed PLY, .splat, .spz, .sog or a SOG meta.json, glTF
    .glb/.gltf) as splat objects (one per file); a glTF file without splats goes to Blender's glTF importer"""

    bl_idname = "import_scene.gaussian_splat"
    bl_label = "Import Gaussian Splat"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply;*.splat;*.spz;*.sog;*meta.json;*.glb;*.gltf", options={"HIDDEN"})
    files: CollectionProperty(type=OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})

    splat_type: EnumProperty(name="Splat Type", default="MESH", items=SPLAT_TYPES)
    axis_conversion: EnumProperty(name="Axes", default="NONE", items=AXES_ITEMS)
    scale_factor: FloatProperty(name="Scale Factor", default=nodes.DEFAULT_SCALE_FACTOR, min=0.0,
                                soft_max=5.0, description="Multiplies every Gaussian's size (1: as trained)")
    view_dependent: BoolProperty(name="View-Dependent Colour", default=True,
                                 description="Spherical-harmonics colour seen from the scene camera; off: "
                                 "the base (DC) colour only (faster, independent of the camera)")
    setup_scene: BoolProperty(name="Set Up Scene", default=True,
                              description="Standard view transform (splat colours are display-referred: "
                              "AgX or Filmic would tone-map them), enough Cycles transparent bounces "
                              "for overlapping splats, and the world colour the splat was trained over "
                              "(when its file says)")
    display_fraction: FloatProperty(name="Display Fraction", default=1.0, min=0.0, max=1.0,
                                    subtype="FACTOR", description="Fraction of the splats shown")
    points_only: BoolProperty(name="Points Only", default=False,
                              description="Show points instead of ellipsoids (fast for large scenes)")
    min_opacity: FloatProperty(name="Min Opacity", default=0.0, min=0.0, max=1.0, subtype="FACTOR",
                               description="Hide splats below this opacity")
    drop_invalid: BoolProperty(name="Drop Invalid Gaussians", default=False,
                               description="Drop Gaussians with NaN values, infinite positions or colours "
                               "instead of refusing the file (infinite opacities and zero scales are kept "
                               "as what they mean: opacity 1 or 0, a flat axis)")

    def _paths(self) -> list[str]:
        names = [f.name for f in self.files if f.name]
        if names and self.directory:
            return [os.path.join(self.directory, name) for name in names]
        return [self.filepath]

    def execute(self, context):
        start = time.perf_counter()
        made = []
        paths = self._paths()
        plain = [p for p in paths if is_plain_gltf(p)]
        try:
            if self.splat_type == "NATIVE" and not convert.native_available():
                raise ValueError(f"Blender {bpy.app.version_string} has no Gaussian-splat point clouds (5.3 and "
                                 "later); import as Add-on Splat")
            # Read every file first: a bad file leaves the blend file untouched.
            loaded = []
            for path in (p for p in paths if p not in plain):
                cloud, messages = _with_messages(read_splat_file, path, sanitize=self.drop_invalid,
                                                 webp=blender_webp())
                loaded.append((path, cloud))
                for msg in messages:
                    self.report({"WARNING"}, msg)
            for path in plain:  # ordinary glTF: Blender's own importer
                if not hasattr(bpy.ops.import_scene, "gltf"):
                    raise ValueError(f"{path}: a glTF file without Gaussian splats; enable Blender's glTF 2.0 "
                                     "add-on to import it")
                bpy.ops.import_scene.gltf(filepath=path)
                self.report({"INFO"}, f"{path}: no Gaussian splats, imported with Blender's glTF 2.0 importer")
            for path, cloud in loaded:
                name = splat_name(path)
                try:
                    if self.splat_type == "NATIVE":
                        made.append(build_native_splat(context, cloud, name, axes=self.axis_conversion))
                    else:
                        made.append(build_splat(
                            context, cloud, name, axes=self.axis_conversion,
                            scale_factor=self.scale_factor, fraction=self.display_fraction,
                            points_only=self.points_only, min_opacity=self.min_opacity,
                            view_dependent=self.view_dependent))
                except ValueError as exc:
                    raise ValueError(f"{path}: {exc}") from exc
                made[-1][convert.SOURCE_PROP] = os.path.abspath(path)  # (where Compact finds its cameras)
        except Exception as exc:
            for obj in made:
                remove_splat(obj)
            self.report({"ERROR"}, f"Gaussian splat import failed: {exc}")
            return {"CANCELLED"}
        if not made:
            return {"FINISHED"}
        for other in context.view_layer.objects:
            other.select_set(False)
        for obj in made:
            obj.select_set(True)
        context.view_layer.objects.active = made[-1]
        total = sum(len(o.data.vertices if o.type == "MESH" else o.data.points) for o in made)
        scene_note = self._scene(context.scene, next((c.background for _, c in reversed(loaded) if c.background),
                                                     None))
        self.report({"INFO"}, f"Imported {total} Gaussians into {len(made)} object(s) in "
                    f"{time.perf_counter() - start:.2f} s{scene_note}")
        return {"FINISHED"}

    def _scene(self, scene, background=None) -> str:
        """Set up (or check) the scene for splats: the INFO note of what changed; warnings when
        Set Up Scene is off and the scene would show the splats wrong. `background`: the colour
        the (last) imported splat was trained over, shown as the world's."""
        changes = set_up_scene(scene, self.setup_scene, background)
        if self.setup_scene:
            return f"; scene set up for splats: {', '.join(changes)}" if changes else ""
        for problem in (render_setup.view_transform_problem(scene), render_setup.bounce_problem(scene)):
            if problem:
                self.report({"WARNING"}, f"Gaussian splats: {problem}")
        return ""

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        native = convert.native_available()
        if native:
            layout.prop(self, "splat_type")
        mesh_only = ("scale_factor", "view_dependent", "display_fraction", "points_only", "min_opacity")
        for prop in ("axis_conversion", *mesh_only, "setup_scene", "drop_invalid"):
            row = layout.row()
            row.enabled = not (native and self.splat_type == "NATIVE" and prop in mesh_only)
            row.prop(self, prop)


class _SplatExport(ExportHelper):
    """What the splat exporters share: the active splat object, Apply Transform, and execute()
    (the format follows the file name, `gvae_core.formats.write_splat_file`)."""

    bl_options = {"REGISTER", "PRESET"}

    apply_transform: BoolProperty(
        name="Apply Transform", default=False,
        description="Write positions, rotations and scales in world space (uniform scale only; "
        "view-dependent SH colour is not rotated)")

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return convert.is_splat(obj) or convert.is_native_splat(obj)

    def execute(self, context):
        obj = context.active_object
        start = time.perf_counter()
        try:
            count, messages = export_splat(obj, self.filepath, apply_transform=self.apply_transform,
                                           write_step=self.write_step, bake=self.bake_refinement)
        except Exception as exc:
            self.report({"ERROR"}, f"Gaussian splat export failed: {exc}")
            return {"CANCELLED"}
        for msg in messages:
            self.report({"WARNING"}, msg)
        self.report({"INFO"}, f"Exported {count} Gaussians to {self.filepath} in "
                    f"{time.perf_counter() - start:.2f} s")
        return {"FINISHED"}


class EXPORT_SCENE_OT_gaussian_splat(_SplatExport, Operator):
    """Export the active splat object as a 3D Gaussian Splatting PLY file"""

    bl_idname = "export_scene.gaussian_splat"
    bl_label = "Export Gaussian Splat"

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})
    write_step: BoolProperty(name="Write Refine Step", default=False,
                             description="Also write the gvae_step attribute as an int property")
    bake_refinement: FloatProperty(
        name="Bake Refinement", default=0.0, min=0.0, soft_max=8.0,
        description="A refined splat's changes written into the Gaussians as they are drawn at this factor of "
        "the training resolution, for other tools (0: kept as properties, which only this add-on and gvae draw; "
        "other tools then show the splat as it was before refining)")


class EXPORT_SCENE_OT_gaussian_splat_spz(_SplatExport, Operator):
    """Export the active splat object as a Niantic .spz file (compressed: 8-bit colours, rotations and SH)"""

    bl_idname = "export_scene.gaussian_splat_spz"
    bl_label = "Export Gaussian Splat (.spz)"

    filename_ext = ".spz"
    filter_glob: StringProperty(default="*.spz", options={"HIDDEN"})
    write_step = False  # .spz holds no extra properties such as gvae_step
    bake_refinement: FloatProperty(
        name="Bake Refinement", default=2.0, min=0.0, soft_max=8.0,
        description="A refined splat's changes written into the Gaussians as they are drawn at this factor of "
        "the training resolution (.spz keeps no other properties; 0: the splat as it was before refining)")


class EXPORT_SCENE_OT_gaussian_splat_sog(_SplatExport, Operator):
    """Export the active splat object as a PlayCanvas SOG file (.sog: WebP images, for SuperSplat and the web)"""

    bl_idname = "export_scene.gaussian_splat_sog"
    bl_label = "Export Gaussian Splat (.sog)"

    filename_ext = ".sog"
    filter_glob: StringProperty(default="*.sog", options={"HIDDEN"})
    write_step = False  # SOG holds no extra properties such as gvae_step
    bake_refinement: FloatProperty(
        name="Bake Refinement", default=2.0, min=0.0, soft_max=8.0,
        description="A refined splat's changes written into the Gaussians as they are drawn at this factor of "
        "the training resolution (SOG keeps no other properties; 0: the splat as it was before refining)")


class EXPORT_SCENE_OT_gaussian_splat_glb(_SplatExport, Operator):
    """Export the active splat object as glTF 2.0 (.glb, Khronos's KHR_gaussian_splatting: three.js, CesiumJS,
    Babylon.js, PlayCanvas)"""

    bl_idname = "export_scene.gaussian_splat_glb"
    bl_label = "Export Gaussian Splat (.glb)"

    filename_ext = ".glb"
    filter_glob: StringProperty(default="*.glb", options={"HIDDEN"})
    write_step = False  # glTF splats hold no extra properties such as gvae_step
    bake_refinement: FloatProperty(
        name="Bake Refinement", default=2.0, min=0.0, soft_max=8.0,
        description="A refined splat's changes written into the Gaussians as they are drawn at this factor of "
        "the training resolution (glTF splats keep no other properties; 0: the splat as it was before refining)")


class GVAE_OT_native_modifier(Operator):
    """Draw the active Blender Gaussian splat (5.3+) as gvae render does for the scene camera: a modifier that
    adds the reference renderer's anti-aliasing and a refined splat's changes per octave (its data stay as they
    are)"""

    bl_idname = "gvae.native_modifier"
    bl_label = "Draw as GaussianVAE"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return convert.is_native_splat(context.active_object)

    def execute(self, context):
        nodes.add_native_modifier(context.active_object)
        render_setup.sync_focal_length(context.scene)
        return {"FINISHED"}


class GVAE_FH_gaussian_splat(bpy.types.FileHandler):
    """Drag and drop of .ply, .splat, .spz, .sog, .glb/.gltf files and SOG meta.json files into the viewport
    (a .glb or .gltf dropped offers Blender's glTF importer too: the handler cannot see whether it holds
    splats; Import hands one without splats to Blender's importer)."""

    bl_idname = "GVAE_FH_gaussian_splat"
    bl_label = "Gaussian Splat"
    bl_import_operator = "import_scene.gaussian_splat"
    bl_file_extensions = ".ply;.splat;.spz;.sog;.json;.glb;.gltf"

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def menu_import(self, context):
    self.layout.operator(IMPORT_SCENE_OT_gaussian_splat.bl_idname,
                         text="Gaussian Splat (.ply, .splat, .spz, .sog, .glb)")


def menu_export(self, context):
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat.bl_idname, text="Gaussian Splat (.ply)")
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_spz.bl_idname, text="Gaussian Splat (.spz)")
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_sog.bl_idname, text="Gaussian Splat (.sog)")
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_glb.bl_idname, text="Gaussian Splat (.glb)")


classes = (IMPORT_SCENE_OT_gaussian_splat, EXPORT_SCENE_OT_gaussian_splat, EXPORT_SCENE_OT_gaussian_splat_spz,
           EXPORT_SCENE_OT_gaussian_splat_sog, EXPORT_SCENE_OT_gaussian_splat_glb, GVAE_OT_native_modifier,
           GVAE_FH_gaussian_splat)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(menu_import)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
