"""Sidebar (N-panel) tab "GaussianVAE" in the 3D viewport: display options, Refine, Compact, import/export."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty
from bpy.types import Panel, PropertyGroup

from . import convert, io_ops, nodes, photos_ops, refine_ops, runtime


class GVAE_Settings(PropertyGroup):
    """Refine and Compact settings kept with the scene (the panels pass them to `gvae.refine` and
    `gvae.compact`)."""

    steps: IntProperty(name="Octaves", default=1, min=1, max=4,
                       description="Resolution doublings above the trained one that the refined Gaussians "
                       "get detail for")
    budget_auto: BoolProperty(name="All Gaussians", default=True,
                              description="Refine every Gaussian (the model's default); off: only the fraction "
                              "with the highest Hessian scores")
    budget_fraction: FloatProperty(name="Budget", default=0.25, min=0.001, max=1.0, subtype="FACTOR",
                                   description="Fraction of Gaussians refined (the highest Hessian scores)")
    model_source: EnumProperty(name="Model", default="BUNDLED",
                               items=(("BUNDLED", "Bundled", "The model shipped with the extension"),
                                      ("FILE", "Folder", "A model folder (config.json + weights)")))
    model_path: StringProperty(name="Model Folder", subtype="DIR_PATH", default="")
    seed: IntProperty(name="Seed", default=0, min=0)
    fidelity_check: BoolProperty(name="Fidelity Check", default=True,
                                 description="Put back what the models did wherever it changes the picture at the "
                                 "training resolution (off: keep everything, which measurably lowers quality)")
    images: StringProperty(name="Images", subtype="DIR_PATH", default="", description=refine_ops.IMAGES_DESCRIPTION)
    image_height: IntProperty(name="Image Height", default=0, min=0,
                              description=refine_ops.IMAGE_HEIGHT_DESCRIPTION)
    compact_keep: FloatProperty(name="Keep", default=0.5, min=0.001, max=1.0, subtype="FACTOR",
                                description="Fraction of the Gaussians Compact keeps")
    compact_removal: EnumProperty(name="Removal", default="AUTO", items=refine_ops.REMOVAL_ITEMS)
    compact_distill: IntProperty(name="Fine-Tune Iterations", default=-1, min=-1,
                                 description=refine_ops.DISTILL_DESCRIPTION)
    compact_images: StringProperty(name="Photos", subtype="DIR_PATH", default="",
                                   description=refine_ops.COMPACT_IMAGES_DESCRIPTION)
    compact_cameras: StringProperty(name="Cameras", subtype="FILE_PATH", default="",
                                    description=refine_ops.CAMERAS_DESCRIPTION)
    compact_found_cameras: BoolProperty(name="Training Cameras", default=True,
                                        description=refine_ops.FOUND_CAMERAS_DESCRIPTION)
    photos_folder: StringProperty(name="Folder", subtype="DIR_PATH", default="",
                                  description=photos_ops.FOLDER_DESCRIPTION)
    photos_height: IntProperty(name="Size", default=0, min=0, soft_max=1080, subtype="PIXEL",
                               description=photos_ops.SIZE_DESCRIPTION)
    photos_held_out: BoolProperty(name="Held-Out Photos", default=True, description=photos_ops.HELD_OUT_DESCRIPTION)
    photos_splat_type: EnumProperty(name="Splat Type", default="MESH", items=io_ops.SPLAT_TYPES)
    photos_cameras: BoolProperty(name="Cameras", default=True,
                                 description="Also add the capture's cameras as Blender cameras")


class GVAE_PT_main(Panel):
    bl_label = "GaussianVAE"
    bl_idname = "GVAE_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GaussianVAE"

    def draw(self, context):
        layout = self.layout
        row = layout.row(align=True)
        row.operator("import_scene.gaussian_splat", text="Import", icon="IMPORT")
        row.operator("export_scene.gaussian_splat", text="Export", icon="EXPORT")
        obj = context.active_object
        if not convert.is_any_splat(obj):
            layout.label(text="Select a splat object", icon="INFO")
            return
        kind = " (Blender's own splat)" if convert.is_native_splat(obj) else ""
        layout.label(text=f"{obj.name}: {convert.splat_count(obj):,} Gaussians{kind}", icon="POINTCLOUD_DATA")


class GVAE_PT_display(Panel):
    bl_label = "Display"
    bl_parent_id = "GVAE_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GaussianVAE"

    @classmethod
    def poll(cls, context):
        return convert.is_any_splat(context.active_object)

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        obj = context.active_object
        native = convert.is_native_splat(obj)
        mod = nodes.splat_modifier(obj)
        if mod is None and native:
            layout.operator("gvae.native_modifier", icon="MODIFIER")
        elif mod is None:
            layout.label(text="No splat modifier (re-import to add one)", icon="ERROR")
            return
        else:
            for name, *_ in (nodes.NATIVE_INPUTS if native else nodes.INPUTS):
                layout.prop(*nodes.modifier_input(mod, name), text=name)
        if native:
            box = layout.box().column(align=True)
            for line in NATIVE_NOTE:
                box.label(text=line)


class _JobPanel(Panel):
    """A sub-panel that runs a job on the active splat object: its settings, then the job's
    progress while one runs on the object, else the button (greyed out, with the install button
    above, while PyTorch is missing) and a note on what it does. Subclasses set `operator`, `icon`,
    `note`, `module` (the core module it needs) and define `_settings(col, settings, obj)` and
    `_fill(op, settings)`."""

    bl_parent_id = "GVAE_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GaussianVAE"
    operator, icon, note, module = "", "NONE", (), "gvae_core.refinement"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.gvae
        ok, message = runtime.refine_status(self.module, self.bl_label)
        if not ok:
            box = layout.box()
            box.label(text=message, icon="ERROR")
            if not runtime.runtime_installed():
                box.operator("gvae.install_torch", text="Install PyTorch (CPU)", icon="IMPORT")
        col = layout.column()
        col.use_property_split = True
        obj = context.active_object
        self._settings(col, settings, obj)
        job = refine_ops.RUNNING.get(obj.name) if obj is not None else None
        if job is not None:
            layout.progress(factor=job.fraction, type="BAR", text=f"{100 * job.fraction:.0f}% {job.message}")
            layout.label(text=f"{job.label} running in the background (Esc: cancel)", icon="TIME")
            return
        row = layout.row()
        row.enabled = ok and convert.is_any_splat(obj)
        row.scale_y = 1.4
        self._fill(row.operator(self.operator, icon=self.icon), settings)
        box = layout.box().column(align=True)
        for line in self.note:
            box.label(text=line)

    def _settings(self, col, settings, obj) -> None:
        raise NotImplementedError

    def _fill(self, op, settings) -> None:
        raise NotImplementedError


#: What Blender's own splat (5.3+) does not show that the add-on's does (docs/blender.md), under its Display.
NATIVE_NOTE = (
    "Blender draws this splat itself; the modifier",
    "adds the anti-aliasing and a refinement for",
    "the scene camera. Not as the add-on's splat:",
    "Cycles blends overlapping Gaussians in its own",
    "order (further from gvae render than the",
    "add-on's splat); no Scale Factor, Display",
    "Fraction, Points Only or Min Opacity.",
)


#: What Refine does and does not do (docs/refine.md), under its button.
REFINE_NOTE = (
    "Resizes each Gaussian for viewing above its",
    "training resolution, from how it changed while",
    "training; the training-resolution picture stays.",
    "What it gains: docs/refine.md.",
)

#: What Compact does (docs/compact.md), under its button.
COMPACT_NOTE = (
    "Drops what no view sees and the tenth the",
    "picture needs least (by the Hessian), merges",
    "the rest pairwise; scored from the training",
    "cameras found beside the imported file (or",
    "Cameras), else from views placed all around",
    "the object (inside a scene), then fine-tunes",
    "against the object's own renders (-1: up to",
    "1000 iterations, 50,000 Gaussians). With",
    "Photos: fine-tuned on the capture's photos",
    "instead, as gvae compact --images. Warns",
    "when the views miss part of it",
    "(docs/compact.md).",
)


class GVAE_PT_refine(_JobPanel):
    bl_label = "Refine"
    operator, icon, note = "gvae.refine", "SHADERFX", REFINE_NOTE

    def _settings(self, col, settings, obj) -> None:
        col.prop(settings, "steps")
        col.prop(settings, "images")
        with_images = bool(settings.images.strip())
        if with_images:
            col.prop(settings, "image_height")
        sub = col.column()
        sub.enabled = not with_images  # the fit changes every Gaussian and keeps the training picture itself
        sub.prop(settings, "budget_auto")
        frac = sub.column()
        frac.enabled = not settings.budget_auto
        frac.prop(settings, "budget_fraction")
        col.prop(settings, "model_source")
        if settings.model_source == "FILE":
            col.prop(settings, "model_path")
        col.prop(settings, "seed")
        check = col.column()
        check.enabled = not with_images
        check.prop(settings, "fidelity_check")

    def _fill(self, op, settings) -> None:
        op.steps = settings.steps
        op.budget = "" if settings.budget_auto else f"{settings.budget_fraction:.6g}"
        op.model = settings.model_path if settings.model_source == "FILE" else ""
        op.seed = settings.seed
        op.fidelity_check = settings.fidelity_check
        op.images = settings.images
        op.image_height = settings.image_height


class GVAE_PT_compact(_JobPanel):
    bl_label = "Compact"
    operator, icon, note, module = "gvae.compact", "MOD_DECIM", COMPACT_NOTE, runtime.COMPACT_MODULE

    def _settings(self, col, settings, obj) -> None:
        col.prop(settings, "compact_keep")
        col.prop(settings, "compact_removal")
        col.prop(settings, "compact_images")
        with_photos = bool(settings.compact_images.strip())
        views = col.column()
        views.enabled = not with_photos  # (the photos' own cameras score, and the photos fine-tune)
        views.prop(settings, "compact_distill")
        views.prop(settings, "compact_cameras")
        found = views.column()
        found.enabled = not settings.compact_cameras.strip()
        found.prop(settings, "compact_found_cameras")
        if convert.is_any_splat(obj):
            n = convert.splat_count(obj)
            col.label(text=f"{n:,} -> {max(1, round(settings.compact_keep * n)):,} Gaussians")

    def _fill(self, op, settings) -> None:
        op.keep = settings.compact_keep
        op.removal = settings.compact_removal
        op.distill = settings.compact_distill
        op.cameras = settings.compact_cameras
        op.images = settings.compact_images
        op.found_cameras = settings.compact_found_cameras


#: What New from Photos does, under its button.
PHOTOS_NOTE = (
    "Structure from motion when the folder has",
    "only photos, then 3DGS training on the CPU, as",
    "gvae train does; the run folder is kept (gvae",
    "train RUN --more N; the same options again",
    "resume it). The scene changes only at the end.",
)


class GVAE_PT_photos(Panel):
    """New from Photos: the folder and options, what must be installed first, then the button, or the
    running job's stage, step and held-out figure."""

    bl_label = "New from Photos"
    bl_parent_id = "GVAE_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "GaussianVAE"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.gvae
        col = layout.column()
        col.use_property_split = True
        for prop in ("photos_folder", "photos_height", "photos_held_out", "photos_cameras"):
            col.prop(settings, prop)
        if convert.native_available():
            col.prop(settings, "photos_splat_type")
        job = refine_ops.RUNNING.get(photos_ops.JOB_KEY)
        if job is not None:
            layout.progress(factor=job.fraction, type="BAR", text=f"{100 * job.fraction:.0f}%")
            box = layout.box().column(align=True)
            box.label(text=job.message, icon="TIME")
            if job.heldout is not None:
                box.label(text=f"Held-out photos: {job.heldout:.2f} dB PSNR")
            box.label(text="Running in the background (Esc: cancel)")
            return
        folder = bpy.path.abspath(settings.photos_folder) if settings.photos_folder else ""
        missing = runtime.photos_missing(folder)
        if missing:
            box = layout.box()
            for what, requirements in missing:
                box.label(text=f"Needs {what}", icon="ERROR")
                op = box.operator("gvae.install_torch", text=f"Install {' '.join(requirements)}", icon="IMPORT")
                op.requirement = " ".join(requirements)
        row = layout.row()
        row.enabled = bool(folder) and not missing
        row.scale_y = 1.4
        op = row.operator(photos_ops.GVAE_OT_new_from_photos.bl_idname, icon="IMAGE_DATA")
        op.folder, op.height, op.held_out = settings.photos_folder, settings.photos_height, settings.photos_held_out
        op.cameras = settings.photos_cameras
        op.splat_type = settings.photos_splat_type if convert.native_available() else "MESH"
        box = layout.box().column(align=True)
        for line in PHOTOS_NOTE:
            box.label(text=line)


classes = (GVAE_Settings, GVAE_PT_main, GVAE_PT_photos, GVAE_PT_display, GVAE_PT_refine, GVAE_PT_compact)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.gvae = PointerProperty(type=GVAE_Settings)


def unregister():
    del bpy.types.Scene.gvae
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
