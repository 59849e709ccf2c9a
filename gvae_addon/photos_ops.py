"""Sidebar > GaussianVAE > New from Photos: a folder of photos (or a COLMAP / transforms.json capture)
becomes a splat object, as `gvae train FOLDER --out RUN [--image-height H] [--test-every 8]` trains it.

A background job (`refine_ops.BackgroundJob`, driven by the same operator machinery as Refine and
Compact): in the worker, the core's front door from a folder to a trained splat
(`gvae_core.train.train_capture`: structure from motion when the folder has photos and no model, then
the training stages) into a run folder that is kept (`gvae train RUN --more N` continues it; starting
the job again on the same folder and size resumes after the last finished stage). Every call into `gvae_core` is in
`train_capture`. Only `finish`, on the main thread, changes the blend file: the splat object (the
add-on's or Blender's own), the capture's cameras as Blender cameras (optional) and the scene set up for
splats, as Import does; so cancel and failure leave the scene as it was.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty
from bpy.types import Operator

from . import convert, io_ops, refine_ops, runtime

#: The folder New from Photos trains into, inside the capture folder (with `run_name`'s name).
RUN_PARENT = "gvae"
#: The profile whose stage proportions and iterations New from Photos uses (`gvae train`'s default).
PROFILES = (("DEFAULT", "Default", "gvae train's default: three stages, the last one trained until the photos set "
                                    "aside stop improving"),
            ("TINY", "Tiny", "A quick look: small stages of fixed length, SH degree 1"),
            ("FULL", "Full", "The reference's schedule: four stages up to 30,000 iterations (hours on a CPU)"))
#: Every n-th photo (sorted by name) held out to judge the training (LLFF / Mip-NeRF 360's 8).
HELD_OUT_EVERY = 8
JOB_KEY = "New from Photos"
#: What the folder, size and held-out options mean (the operator's and the panel's).
FOLDER_DESCRIPTION = ("A folder of photos (in it or in its images/), or a COLMAP capture (sparse/0 and images/) or a "
                      "transforms.json capture")
SIZE_DESCRIPTION = ("Height in pixels of the last training stage, the size the splat is trained at (0: the profile's, "
                    "200 px by default; as gvae train --image-height)")
HELD_OUT_DESCRIPTION = ("Set every 8th photo aside and report how well the splat draws them (the held-out PSNR; as "
                        "gvae train --test-every 8); off: train on every photo")


def run_name(height: int, profile: str, held_out: bool) -> str:
    """The run folder's name for these options: the same options resume the same run."""
    return f"train_{height or 'default'}px_{profile.lower()}" + ("_heldout" if held_out else "")


def train_capture(folder: str, run_dir: str, *, height: int, profile: str, iterations: int, held_out: bool,
                  threads: int | None, report, cancelled) -> dict:
    """The one place New from Photos calls gvae_core (in the worker thread): the core's front door
    (`gvae_core.train.train_capture`, what `gvae train` calls) for these options. `report(fraction,
    message, heldout)` is called as the work goes (it raises to cancel); `cancelled()` says whether to
    stop. Returns the final cloud, the log, the capture's cameras (the held-out ones marked) and what
    structure from motion did."""
    report(0.0, "starting", None)  # (a cancel before the first stage needs no torch)
    from gvae_core.train import train_capture as core_train_capture  # noqa: PLC0415 - imported in the worker
    from gvae_core.train.config import configure  # noqa: PLC0415

    config = configure(profile.lower(), image_height=height or None, iterations=iterations or None,
                       test_every=HELD_OUT_EVERY if held_out else None)
    heldout = [None]

    def on_progress(event: dict) -> None:
        # The bar follows the planned iterations; the last stage may train on past them until its validation
        # photos stop improving, which the message says.
        if event.get("test_psnr") is not None:
            heldout[0] = float(event["test_psnr"])
        report(event["fraction"], _message(event), heldout[0])

    try:
        done = core_train_capture(folder, config, run_dir, own_test_split=True, progress=False, threads=threads,
                                  on_progress=on_progress, cancel=cancelled)
    except Exception:
        if cancelled():  # (the core's cancel, or ours raised through its progress report)
            report(1.0, "cancelled", None)
        raise
    result, capture, config = done.result, done.capture, done.config
    return {"cloud": result.cloud, "log": result.log, "sfm": None if done.sfm is None else done.sfm.summary(),
            "cameras": capture.cameras, "names": capture.names, "splits": capture.splits, "kind": capture.kind,
            "size": (config.resolutions[-1], result.log[-1]["resolution"] if result.log else None),
            "source": str(Path(run_dir).resolve() / f"stage_{len(config.resolutions) - 1}.ply")}


def _message(event: dict) -> str:
    """What the status bar says of a progress event of the core's front door."""
    if event["phase"] == "sfm":
        return event["message"]
    step, planned = event["step"], event["planned"]
    where = f"step {step}/{planned}" if step <= planned else f"step {step}, until it stops improving"
    return f"stage {event['stage'] + 1}/{event['stages']} at {event['resolution']} px, {where}"


class PhotosJob(refine_ops.BackgroundJob):
    """New from Photos as a background job (module docstring). `train`: a stand-in for `train_capture`
    (tests)."""

    label, participle = "New from Photos", "trained"
    unchanged = "the scene is unchanged"

    def __init__(self, folder: str, *, height: int = 0, profile: str = "DEFAULT", iterations: int = 0,
                 held_out: bool = True, run_dir: str = "", splat_type: str = "MESH", cameras: bool = True,
                 axes: str = "AUTO", threads: int = 0, train=None):
        super().__init__()
        self.folder = os.path.abspath(bpy.path.abspath(folder)) if folder else ""
        self.height, self.profile, self.iterations, self.held_out = height, profile, iterations, held_out
        self.run_dir = (os.path.abspath(bpy.path.abspath(run_dir)) if run_dir else
                        os.path.join(self.folder, RUN_PARENT, run_name(height, profile, held_out)))
        self.splat_type, self.cameras, self.axes, self.threads = splat_type, cameras, axes, threads
        self.heldout: float | None = None
        self._train = train
        self.unchanged = f"the scene is unchanged; the run folder {self.run_dir} is kept (start again to resume)"

    @property
    def key(self) -> str:
        return JOB_KEY

    def status_text(self) -> str:
        heldout = f", held-out photos {self.heldout:.2f} dB" if self.heldout is not None else ""
        return f"{self.label} ({Path(self.folder).name}): {100 * self.fraction:.0f}% {self.message}{heldout}"

    def start(self) -> PhotosJob:
        if not self.folder or not os.path.isdir(self.folder):
            raise ValueError(f"{self.folder or 'no folder'}: not a folder (a folder of photos, or a COLMAP or "
                             "transforms.json capture)")
        if self.splat_type == "NATIVE" and not convert.native_available():
            raise ValueError(f"Blender {bpy.app.version_string} has no Gaussian-splat point clouds (5.3 and later); "
                             "choose Add-on Splat")
        if self._train is None:
            missing = runtime.photos_missing(self.folder)
            if missing:
                raise RuntimeError("New from Photos needs " + " and ".join(what for what, _ in missing)
                                   + ": install it first (Sidebar > GaussianVAE > New from Photos)")
        self._launch(self._work)
        return self

    def _report(self, fraction: float, message: str, heldout) -> None:
        if heldout is not None:
            self.heldout = float(heldout)
        self._progress(fraction, message)

    def _work(self):
        train = self._train or train_capture
        return train(self.folder, self.run_dir, height=self.height, profile=self.profile,
                     iterations=self.iterations, held_out=self.held_out, threads=self.threads or None,
                     report=self._report, cancelled=lambda: self.cancelled)

    # ------------------------------------------------------------------ main thread
    def finish(self) -> dict:
        if self.info is not None and self.done:
            return self.info
        self._check_finish()
        r = self.result
        context = bpy.context
        name = Path(self.folder).name or "splat"
        axes = self.axes if self.axes != "AUTO" else ("Y_DOWN" if r["kind"] == "colmap" else "NONE")
        made = []
        try:
            obj = (io_ops.build_native_splat(context, r["cloud"], name, axes=axes) if self.splat_type == "NATIVE"
                   else io_ops.build_splat(context, r["cloud"], name, axes=axes))
            made.append(obj)
            if r.get("source"):  # (the run: where Compact finds its cameras)
                obj[convert.SOURCE_PROP] = r["source"]
            cams = _add_cameras(context, name, r, obj) if self.cameras else None
            if cams is not None:
                made.append(cams)
            notes = io_ops.set_up_scene(context.scene, True, r["cloud"].background)
            first = next((o for o in (cams.objects if cams is not None else ())), None)
            if first is not None and context.scene.camera is None:
                context.scene.camera = first
                notes.append(f"scene camera {first.name}")
        except BaseException:
            for thing in reversed(made):
                _remove(thing)
            raise
        for other in context.view_layer.objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        last = r["log"][-1] if r["log"] else {}
        self.info = {"object": obj.name, "count": len(r["cloud"]), "run_dir": self.run_dir, "sfm": r["sfm"],
                     "heldout": last.get("test_psnr"), "resolution": last.get("resolution"),
                     "cameras": 0 if cams is None else len(cams.objects), "scene": notes,
                     "seconds": self.ended - self.started}
        self.result = None
        return self.info


def _remove(thing) -> None:
    if isinstance(thing, bpy.types.Collection):
        for cam in list(thing.objects):
            data = cam.data
            bpy.data.objects.remove(cam)
            bpy.data.cameras.remove(data)
        bpy.data.collections.remove(thing)
    else:
        io_ops.remove_splat(thing)


def _add_cameras(context, name: str, r: dict, splat) -> bpy.types.Collection:
    """A collection "<name> cameras" holding a Blender camera per photo of the capture (the held-out ones
    named so), children of the splat object (they move with it; placed in its frame, the capture's), with
    the photo's field of view and principal point (lens shift)."""
    from mathutils import Matrix  # noqa: PLC0415 - Blender's

    coll = bpy.data.collections.new(f"{name} cameras")
    try:
        for cam, photo, split in zip(r["cameras"], r["names"], r["splits"]):
            label = Path(photo).stem + (" (held out)" if split == "test" else "")
            data = bpy.data.cameras.new(label)
            data.sensor_fit = "HORIZONTAL"
            data.angle_x = cam.fov_x
            side = max(cam.width, cam.height)
            data.shift_x, data.shift_y = (cam.width / 2 - cam.cx) / side, (cam.cy - cam.height / 2) / side
            data.clip_start = 0.01
            obj = bpy.data.objects.new(label, data)
            obj.parent = splat
            obj.matrix_basis = Matrix(np.asarray(cam.to_blender_c2w(), np.float64).tolist())
            coll.objects.link(obj)
        context.scene.collection.children.link(coll)
    except BaseException:
        _remove(coll)
        raise
    return coll


class GVAE_OT_new_from_photos(refine_ops.JobOperator, Operator):
    """Make a splat object from a folder of photos (or a COLMAP / transforms.json capture): structure from
    motion when needed, then 3DGS training, in the background (needs PyTorch, and pycolmap for photos without
    a model). Progress in the status bar and the sidebar; Esc cancels, leaving the scene as it was"""

    bl_idname = "gvae.new_from_photos"
    bl_label = "New from Photos"
    bl_options = {"REGISTER", "UNDO"}

    folder: StringProperty(name="Folder", subtype="DIR_PATH", default="", description=FOLDER_DESCRIPTION)
    height: IntProperty(name="Size", default=0, min=0, soft_max=1080, subtype="PIXEL", description=SIZE_DESCRIPTION)
    held_out: BoolProperty(name="Held-Out Photos", default=True, description=HELD_OUT_DESCRIPTION)
    profile: EnumProperty(name="Profile", default="DEFAULT", items=PROFILES)
    iterations: IntProperty(name="Iterations", default=0, min=0,
                            description="Iterations of every stage (0: the profile's)")
    splat_type: EnumProperty(name="Splat Type", default="MESH", items=io_ops.SPLAT_TYPES)
    cameras: BoolProperty(name="Cameras", default=True,
                          description="Also add the capture's cameras as Blender cameras (a collection)")
    axes: EnumProperty(name="Axes", default="AUTO",
                       items=(("AUTO", "Automatic", "Y Down, Z Forward for COLMAP captures and photos, as stored "
                               "for transforms.json"), *io_ops.AXES_ITEMS))
    run_dir: StringProperty(name="Run Folder", subtype="DIR_PATH", default="",
                            description="Where the training run goes (kept: gvae train RUN --more N continues it); "
                            "empty: FOLDER/gvae/train_<size>_<profile>[_heldout]")
    threads: IntProperty(name="Threads", default=0, min=0, description="PyTorch CPU threads (0: its choice)")

    @classmethod
    def poll(cls, context):
        return JOB_KEY not in refine_ops.RUNNING

    def _job(self, context) -> PhotosJob:
        return PhotosJob(self.folder, height=self.height, profile=self.profile, iterations=self.iterations,
                         held_out=self.held_out, run_dir=self.run_dir, splat_type=self.splat_type,
                         cameras=self.cameras, axes=self.axes, threads=self.threads)

    def _report_text(self, info: dict) -> str:
        heldout = info["heldout"]
        judged = (f"held-out photos {heldout:.2f} dB PSNR" if heldout is not None and math.isfinite(heldout)
                  else "no held-out photos")
        sfm = f"; structure from motion: {info['sfm']}" if info["sfm"] else ""
        cams = f", {info['cameras']} cameras" if info["cameras"] else ""
        scene = f"; scene set up for splats: {', '.join(info['scene'])}" if info["scene"] else ""
        return (f"New from Photos: {info['object']}, {info['count']:,} Gaussians trained at {info['resolution']} px "
                f"in {info['seconds']:.0f} s ({judged}){cams}; run folder {info['run_dir']}{sfm}{scene}")


classes = (GVAE_OT_new_from_photos,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)

