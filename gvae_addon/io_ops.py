"""File > Import / Export > Gaussian Splat: splat files (.ply, .splat, .spz, .sog) <-> splat objects."""

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
from gvae_core.formats import WebpCodec, read_splat_file, write_splat_file

from . import convert, nodes, render_setup

#: Object rotation (Euler XYZ) per axis option: the data stay as in the file.
AXES = {
    "NONE": (0.0, 0.0, 0.0),
    # y down, z forward (3DGS / COLMAP / OpenCV) -> Blender z up, y forward: +y -> -z, +z -> +y.
    "Y_DOWN": (-math.pi / 2, 0.0, 0.0),
}


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


def build_splat(context, cloud: GaussianCloud, name: str, *, axes: str = "NONE",
                scale_factor: float = nodes.DEFAULT_SCALE_FACTOR, fraction: float = 1.0,
                points_only: bool = False, min_opacity: float = 0.0, view_dependent: bool = True):
    """A new splat object holding `cloud`, linked to the active collection (removed again if
    anything fails). An integer `gvae_step` property (written by Export with "Write Refine Step")
    becomes the object's `gvae_step` attribute again."""
    steps = cloud.extra.get(convert.STEP_ATTR)
    if steps is not None and np.issubdtype(steps.dtype, np.integer):
        cloud = cloud.replace(extra={k: v for k, v in cloud.extra.items() if k != convert.STEP_ATTR})
    else:
        steps = None
    me = convert.mesh_from_cloud(cloud, name, steps=steps)
    obj = None
    try:
        obj = bpy.data.objects.new(name, me)
        obj.rotation_euler = AXES[axes]
        nodes.add_splat_modifier(obj, scale_factor=scale_factor, fraction=fraction,
                                 points_only=points_only, min_opacity=min_opacity,
                                 view_dependent=view_dependent)
        context.collection.objects.link(obj)
    except BaseException:
        if obj is not None:
            bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(me)
        raise
    return obj


def export_splat(obj, path: str, *, apply_transform: bool = False, write_step: bool = False):
    """Write a splat object in the format `path` asks for (`write_splat_file`: a 3DGS PLY, .spz,
    .sog, ...; atomic). Returns (count, messages)."""
    cloud, steps = convert.cloud_from_object(obj)
    messages = []
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
    """Import Gaussian splat files (3DGS or compressed PLY, .splat, .spz, .sog or a SOG meta.json) as splat
    objects (one per file)"""

    bl_idname = "import_scene.gaussian_splat"
    bl_label = "Import Gaussian Splat"
    bl_options = {"REGISTER", "UNDO", "PRESET"}

    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply;*.splat;*.spz;*.sog;*meta.json", options={"HIDDEN"})
    files: CollectionProperty(type=OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})

    axis_conversion: EnumProperty(
        name="Axes", default="NONE",
        items=(("NONE", "As Stored (Z Up)", "Keep the file's axes (scenes made in Blender, NeRF-Synthetic)"),
               ("Y_DOWN", "Y Down, Z Forward", "3DGS/COLMAP/OpenCV scenes: rotate the object so that "
                "-Y becomes up (an object rotation; the data are not changed)")))
    scale_factor: FloatProperty(name="Scale Factor", default=nodes.DEFAULT_SCALE_FACTOR, min=0.0,
                                soft_max=5.0, description="Multiplies every Gaussian's size (1: as trained)")
    view_dependent: BoolProperty(name="View-Dependent Colour", default=True,
                                 description="Spherical-harmonics colour seen from the scene camera; off: "
                                 "the base (DC) colour only (faster, independent of the camera)")
    setup_scene: BoolProperty(name="Set Up Scene", default=True,
                              description="Standard view transform (splat colours are display-referred: "
                              "AgX or Filmic would tone-map them) and enough Cycles transparent bounces "
                              "for overlapping splats")
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
        try:
            # Read every file first: a bad file leaves the blend file untouched.
            loaded = []
            for path in self._paths():
                cloud, messages = _with_messages(read_splat_file, path, sanitize=self.drop_invalid,
                                                 webp=blender_webp())
                loaded.append((path, cloud))
                for msg in messages:
                    self.report({"WARNING"}, msg)
            for path, cloud in loaded:
                name = splat_name(path)
                try:
                    made.append(build_splat(
                        context, cloud, name, axes=self.axis_conversion,
                        scale_factor=self.scale_factor, fraction=self.display_fraction,
                        points_only=self.points_only, min_opacity=self.min_opacity,
                        view_dependent=self.view_dependent))
                except ValueError as exc:
                    raise ValueError(f"{path}: {exc}") from exc
        except Exception as exc:
            for obj in made:
                me = obj.data
                bpy.data.objects.remove(obj)
                bpy.data.meshes.remove(me)
            self.report({"ERROR"}, f"Gaussian splat import failed: {exc}")
            return {"CANCELLED"}
        for other in context.view_layer.objects:
            other.select_set(False)
        for obj in made:
            obj.select_set(True)
        context.view_layer.objects.active = made[-1]
        total = sum(len(o.data.vertices) for o in made)
        scene_note = self._scene(context.scene)
        self.report({"INFO"}, f"Imported {total} Gaussians into {len(made)} object(s) in "
                    f"{time.perf_counter() - start:.2f} s{scene_note}")
        return {"FINISHED"}

    def _scene(self, scene) -> str:
        """Set up (or check) the scene for splats: the INFO note of what changed; warnings when
        Set Up Scene is off and the scene would show the splats wrong."""
        render_setup.sync_focal_length(scene)
        if self.setup_scene:
            changes = render_setup.setup_scene(scene)
            return f"; scene set up for splats: {', '.join(changes)}" if changes else ""
        for problem in (render_setup.view_transform_problem(scene), render_setup.bounce_problem(scene)):
            if problem:
                self.report({"WARNING"}, f"Gaussian splats: {problem}")
        return ""

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        for prop in ("axis_conversion", "scale_factor", "view_dependent", "display_fraction", "points_only",
                     "min_opacity", "setup_scene", "drop_invalid"):
            layout.prop(self, prop)


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
        return convert.is_splat(context.active_object)

    def execute(self, context):
        obj = context.active_object
        start = time.perf_counter()
        try:
            count, messages = export_splat(obj, self.filepath, apply_transform=self.apply_transform,
                                           write_step=self.write_step)
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


class EXPORT_SCENE_OT_gaussian_splat_spz(_SplatExport, Operator):
    """Export the active splat object as a Niantic .spz file (compressed: 8-bit colours, rotations and SH)"""

    bl_idname = "export_scene.gaussian_splat_spz"
    bl_label = "Export Gaussian Splat (.spz)"

    filename_ext = ".spz"
    filter_glob: StringProperty(default="*.spz", options={"HIDDEN"})
    write_step = False  # .spz holds no extra properties such as gvae_step


class EXPORT_SCENE_OT_gaussian_splat_sog(_SplatExport, Operator):
    """Export the active splat object as a PlayCanvas SOG file (.sog: WebP images, for SuperSplat and the web)"""

    bl_idname = "export_scene.gaussian_splat_sog"
    bl_label = "Export Gaussian Splat (.sog)"

    filename_ext = ".sog"
    filter_glob: StringProperty(default="*.sog", options={"HIDDEN"})
    write_step = False  # SOG holds no extra properties such as gvae_step


class GVAE_FH_gaussian_splat(bpy.types.FileHandler):
    """Drag and drop of .ply, .splat, .spz, .sog files and SOG meta.json files into the viewport."""

    bl_idname = "GVAE_FH_gaussian_splat"
    bl_label = "Gaussian Splat"
    bl_import_operator = "import_scene.gaussian_splat"
    bl_file_extensions = ".ply;.splat;.spz;.sog;.json"

    @classmethod
    def poll_drop(cls, context):
        return context.area is not None and context.area.type == "VIEW_3D"


def menu_import(self, context):
    self.layout.operator(IMPORT_SCENE_OT_gaussian_splat.bl_idname, text="Gaussian Splat (.ply, .splat, .spz, .sog)")


def menu_export(self, context):
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat.bl_idname, text="Gaussian Splat (.ply)")
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_spz.bl_idname, text="Gaussian Splat (.spz)")
    self.layout.operator(EXPORT_SCENE_OT_gaussian_splat_sog.bl_idname, text="Gaussian Splat (.sog)")


classes = (IMPORT_SCENE_OT_gaussian_splat, EXPORT_SCENE_OT_gaussian_splat, EXPORT_SCENE_OT_gaussian_splat_spz,
           EXPORT_SCENE_OT_gaussian_splat_sog, GVAE_FH_gaussian_splat)


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
