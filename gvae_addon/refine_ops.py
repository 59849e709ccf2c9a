"""Refine and Compact: run `gvae_core.refine` / `gvae_core.compaction.compact` on the active splat
object (the add-on's splat mesh, or Blender 5.3+'s own Gaussian-splat point cloud) and write the result
back into it; and the machinery of every background job (`BackgroundJob`, `JobOperator`: New from Photos
uses them too).

Both take seconds to minutes on a capture, so the work runs as a job that keeps Blender alive:
a `CoreJob` reads the object's Gaussians on the main thread (`start`), runs the core function in a
worker thread (torch releases the GIL while it computes), reports progress (`poll`), can be
cancelled (`cancel`: the worker stops at its next progress report) and writes the result back on
the main thread (`finish`), in one change, only if the work succeeded and the object was not
changed meanwhile. Nothing in the blend file changes on cancel or failure. `RefineJob` and
`CompactJob` say only what to call and how to write its result.

The operators (`JobOperator`) drive a job two ways: `invoke` (the panel's button) starts it and
returns to Blender, which calls `modal` on a timer: progress in the status bar and the panel, Esc
cancels, one undo step on success. `execute` (scripts and `blender -b` batch runs) runs the same
job and waits for it.
"""

from __future__ import annotations

import os
import sys
import threading
import time

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy.types import Operator

from gvae_core.budget import DEFAULT_FIDELITY, parse_budget

from . import convert, nodes, runtime


class JobCancelled(Exception):
    """Raised inside the worker (from its progress report) when the job is cancelled."""


class BackgroundJob:
    """Work in a worker thread that Blender's main thread follows (the modal operator, `execute` and
    the tests drive it the same way, without a window):

    - `start()` (main thread): check and read what the work needs, start the worker thread;
    - `poll()` (main thread, any time): (done, fraction, message);
    - `cancel()`: ask the worker to stop; it does at its next progress report;
    - `finish()` (main thread, once done): write the result into the blend file and return what the
      operator reports; raises JobCancelled when cancelled, or the worker's error, leaving the blend
      file as it was.

    `key` names the job in RUNNING (one job per key). The worker reports through `_progress`, which
    raises JobCancelled once the job is cancelled."""

    label, participle = "Job", "worked on"
    #: What a cancel leaves (the operator's report says it).
    unchanged = "nothing was changed"

    def __init__(self):
        self.fraction, self.message = 0.0, "starting"
        self.result = None
        self.info: dict | None = None
        self.error: BaseException | None = None
        self._cancel = threading.Event()
        self._thread: threading.Thread | None = None
        self.started = self.ended = None

    @property
    def key(self) -> str:
        raise NotImplementedError

    def status_text(self) -> str:
        """What the status bar says while the job runs."""
        return f"{self.label} {self.key}: {100 * self.fraction:.0f}% {self.message}"

    def _launch(self, work, *args) -> None:
        """Run `work(*args)` in the worker thread; what it returns becomes `result`, what it raises `error`
        (JobCancelled: neither)."""
        self.started = time.perf_counter()
        self._thread = threading.Thread(target=self._guarded, args=(work, *args), name=f"gvae-{self.label.lower()}",
                                        daemon=True)
        self._thread.start()

    def _guarded(self, work, *args) -> None:
        try:
            self.result = work(*args)
        except JobCancelled:
            self.result = None
        except BaseException as exc:  # reported on the main thread by finish()
            self.error = exc
        finally:
            self.ended = time.perf_counter()

    def poll(self) -> tuple[bool, float, str]:
        return self.done, self.fraction, self.message

    @property
    def done(self) -> bool:
        return self._thread is not None and not self._thread.is_alive()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def cancel(self) -> None:
        self._cancel.set()
        self.message = "cancelling"

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the worker ends (True) or `timeout` seconds pass (False)."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.done

    def _check_finish(self) -> None:
        """What every `finish` does first: refuse while running; raise the worker's error, or
        JobCancelled when cancelled (or when it left no result)."""
        if not self.done:
            raise RuntimeError(f"{type(self).__name__}.finish: the job is still running")
        if self.error is not None:
            raise self.error
        if self.cancelled or self.result is None:
            raise JobCancelled(f"{self.label} cancelled")

    def _progress(self, fraction: float, message: str = "") -> None:
        """Called by the worker: records progress; raises JobCancelled once the job is cancelled."""
        if self._cancel.is_set():
            raise JobCancelled(f"{self.label} cancelled")
        self.fraction = max(self.fraction, min(1.0, float(fraction)))
        self.message = message


class CoreJob(BackgroundJob):
    """One run of a `gvae_core` function on a splat object (`BackgroundJob`): `start` reads the
    object's Gaussians, `finish` writes the result into it, in one change, only if the work succeeded
    and the object was not changed meanwhile (also refused when the object was deleted or its data
    replaced).

    Subclasses set `label` and define `_load()` (the core function, imported on the main thread),
    `_run(function, cloud, progress)` (in the worker) and `_write(obj)` / `_info()` (main thread).
    Only the worker thread runs torch: once the main thread has run torch's parallel loops, their
    idle OpenMP threads slow the worker's down.
    """

    unchanged = "the object is unchanged"

    def __init__(self, obj, core=None):
        super().__init__()
        self.obj_name = obj.name
        self._core = core
        self._mesh_pointer = None

    @property
    def key(self) -> str:
        return self.obj_name

    # ------------------------------------------------------------------ main thread
    def start(self) -> CoreJob:
        obj = bpy.data.objects.get(self.obj_name)
        if obj is None or not convert.is_any_splat(obj):
            raise ValueError(f"{self.obj_name!r} is not a splat object")
        function = self._core or self._load()  # imports torch: fails here, not in the worker
        self.cloud, self.old_steps = convert.cloud_from_object(obj)
        if len(self.cloud) == 0:
            raise ValueError(f"object {obj.name!r} has no Gaussians to {self.label.lower()}")
        self._mesh_pointer = obj.data.as_pointer()
        self._n_vertices = convert.splat_count(obj)
        self._launch(self._work, function)
        return self

    def finish(self) -> dict:
        if self.info is not None and self.done:
            return self.info  # written already
        self._check_finish()
        obj = bpy.data.objects.get(self.obj_name)
        if obj is None or obj.data is None or obj.data.as_pointer() != self._mesh_pointer \
                or convert.splat_count(obj) != self._n_vertices:
            raise RuntimeError(f"object {self.obj_name!r} was deleted or changed while it was being "
                               f"{self.participle}; the result was not written")
        self._write(obj)
        self.info = {"before": len(self.cloud), "seconds": self.ended - self.started, **self._info()}
        self.result = self.cloud = None  # the object holds it now
        return self.info

    def _write(self, obj) -> None:
        raise NotImplementedError

    def _info(self) -> dict:
        raise NotImplementedError

    def _replace_mesh(self, obj, cloud, steps) -> None:
        """Give the object new data of its kind holding `cloud` (with `gvae_step` marks), materials kept:
        a splat mesh, or a Gaussian-splat point cloud (Blender 5.3+), which gets the modifier that draws
        it for the scene camera (a refined one's changes per octave, the anti-aliasing: `nodes`)."""
        old = obj.data
        native = convert.is_native_splat(obj)
        new = (convert.pointcloud_from_cloud(cloud, old.name, steps=steps) if native
               else convert.mesh_from_cloud(cloud, old.name, steps=steps))
        for mat in old.materials:
            new.materials.append(mat)
        obj.data = new
        if old.users == 0:
            (bpy.data.pointclouds if native else bpy.data.meshes).remove(old)
        if native:
            nodes.add_native_modifier(obj)

    # ------------------------------------------------------------------ worker thread
    def _work(self, function):
        if self._core is None:  # the real core, not a stand-in: its CPU kernels first (compiled once)
            runtime.prepare_kernels(self._progress)
        return self._run(function, self.cloud, self._progress)

    def _load(self):
        raise NotImplementedError

    def _run(self, function, cloud, progress):
        raise NotImplementedError


class RefineJob(CoreJob):
    """`gvae_core.refine` on a splat object; added Gaussians get `gvae_step` = their refine step
    (counted on from an earlier refine), the original ones keep theirs (0 at first). `refine`: a
    stand-in for the core function (tests)."""

    label, participle = "Refine", "refined"

    def __init__(self, obj, *, steps: int = 1, budget=None, model=None, seed: int = 0,
                 fidelity: float | None = DEFAULT_FIDELITY["detail"], images: str | None = None,
                 image_height: int | None = None, fit_steps: int | None = None, refine=None):
        super().__init__(obj, refine)
        self.steps, self.budget, self.model, self.seed, self.fidelity = steps, budget, model, seed, fidelity
        self.images, self.image_height, self.fit_steps = images, image_height, fit_steps

    def _load(self):
        return runtime.core_refine()

    def _run(self, refine, cloud, progress):
        if self.images:  # the capture's own images: the fit replaces the budget and the fidelity check
            fit = {"seed": self.seed, **({"steps": self.fit_steps} if self.fit_steps else {})}
            return refine(cloud, steps=self.steps, model=self.model, seed=self.seed, images=self.images,
                          image_height=self.image_height, fit=fit, progress=progress)
        return refine(cloud, steps=self.steps, budget=self.budget, model=self.model, seed=self.seed,
                      fidelity=self.fidelity, progress=progress)

    def _write(self, obj) -> None:
        r, n_in = self.result, len(self.cloud)
        marks = np.zeros(len(r.cloud), np.int32)
        if self.old_steps is not None:
            marks[:n_in] = self.old_steps
        base = 0 if self.old_steps is None else int(self.old_steps.max(initial=0))
        marks[r.added] = base + r.step
        self._replace_mesh(obj, r.cloud, marks)

    def _info(self) -> dict:
        r = self.result
        fit = getattr(r, "fit", None)
        return {"after": len(r.cloud), "added": len(r.added), "timings": dict(r.timings),
                "selected": len(getattr(r, "selected", ())), "put_back": len(getattr(r, "reverted", ())),
                "not_refined": getattr(r, "notes", {}).get("not refined"),
                "fit": None if fit is None else {"before": fit.psnr_before, "after": fit.psnr_after,
                                                 "kept": r.notes.get("kept"), "judged": fit.judged(),
                                                 "images": fit.images},
                "training_resolution": getattr(r, "notes", {}).get("training resolution")}


class CompactJob(CoreJob):
    """`gvae_core.compaction.compact` on a splat object (`keep` a fraction or `count` Gaussians):
    with the capture's photos at `images` (any capture `gvae train` reads) fine-tuned on them, as
    `gvae compact --images`; else scored from the capture's cameras: those at `cameras` (a capture,
    a transforms.json, the reference 3DGS's cameras.json) when given, else with `found_cameras`
    those its training left beside the file it was imported from, else views placed around it
    (`compaction.compaction_inputs` decides, as for `gvae compact`). Each remaining
    Gaussian keeps the `gvae_step` of the input row it stands for. `removal` None: the core's
    default (`compaction.default_method`). Paths are resolved (`//`) here, on the main thread.
    `compact`: a stand-in for the core function (tests)."""

    label, participle = "Compact", "compacted"

    def __init__(self, obj, *, keep: float | None = 0.5, count: int | None = None, removal: str | None = "merge",
                 distill: int | str = "auto", seed: int = 0, cameras: str = "", found_cameras: bool = True,
                 images: str = "", compact=None):
        super().__init__(obj, compact)
        self.keep, self.count, self.removal, self.distill, self.seed = keep, count, removal, distill, seed
        self.cameras_path = bpy.path.abspath(cameras.strip()) if cameras.strip() else ""
        self.images_path = bpy.path.abspath(images.strip()) if images.strip() else ""
        self.source = obj.get(convert.SOURCE_PROP) if found_cameras else None
        self.notes: list[str] = []

    def _load(self):
        return runtime.core_compact()

    def _run(self, compact, cloud, progress):
        # (in the worker: reading a capture's photos takes seconds)
        from gvae_core.compaction import compaction_inputs  # noqa: PLC0415

        if self.images_path:
            progress(0.0, f"reading the photos of {self.images_path}")
        given = compaction_inputs(cloud, source=self.source or None, images=self.images_path or None,
                                  cameras=None if self.images_path else self.cameras_path or None)
        self.notes = given.notes
        return compact(cloud, keep=self.keep, count=self.count, removal=self.removal, seed=self.seed,
                       cameras=given.cameras, images=given.images,
                       distill=self.distill if given.images is None else "auto",  # (photos: their fine-tuning)
                       progress=progress)

    def _write(self, obj) -> None:
        r = self.result
        marks = None if self.old_steps is None else np.asarray(self.old_steps)[r.rows]
        self._replace_mesh(obj, r.cloud, marks)

    def _info(self) -> dict:
        r = self.result
        tuned = [{k: x.get(k) for k in ("iterations", "best_at", "judged_on", "psnr_before", "psnr_after")}
                 for x in getattr(r, "rounds", ())]
        return {"after": len(r.cloud), "psnr": float(r.psnr), "timings": dict(r.timings),
                "warnings": list(getattr(r, "warnings", ())), "views": list(self.notes), "tuned": tuned}


#: Jobs running now, by `key` (the object's name; the panel shows their progress; one job per key).
RUNNING: dict[str, BackgroundJob] = {}


def _timing_text(info: dict) -> str:
    parts = ", ".join(f"{k} {v:.2f} s" for k, v in info["timings"].items()
                      if isinstance(v, (int, float)) and k != "total")
    return f" ({parts})" if parts else ""


def _redraw(context) -> None:
    screen = getattr(context, "screen", None)
    for area in (screen.areas if screen is not None else ()):
        if area.type in ("VIEW_3D", "STATUSBAR"):
            area.tag_redraw()


class JobOperator:
    """What the job operators share (mixed in before `bpy.types.Operator`): `execute` runs the job
    to the end (scripts, `blender -b`), `invoke` starts it and `modal` follows it (progress in the
    status bar, Esc cancels, one undo step). Subclasses define `_job(context)` and `_report_text`."""

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return convert.is_any_splat(obj) and obj.name not in RUNNING

    def _job(self, context) -> CoreJob:
        raise NotImplementedError

    def _report_text(self, info: dict) -> str:
        raise NotImplementedError

    def execute(self, context):
        """Blocking: scripts and batch runs (`blender -b`)."""
        wm = context.window_manager
        try:
            job = self._job(context).start()
        except Exception as exc:
            self.report({"ERROR"}, f"{self.bl_label} failed: {exc}")
            return {"CANCELLED"}
        RUNNING[job.key] = job
        wm.progress_begin(0.0, 1.0)
        shown = None
        try:
            while not job.wait(0.25):
                wm.progress_update(job.fraction)
                if bpy.app.background and job.message != shown:
                    shown = job.message
                    print(f"{self.bl_idname}: {100 * job.fraction:5.1f}% {job.message}", file=sys.stderr)
            info = job.finish()
        except Exception as exc:
            self.report({"ERROR"}, f"{self.bl_label} failed: {exc}")
            return {"CANCELLED"}
        finally:
            RUNNING.pop(job.key, None)
            wm.progress_end()
        self.report({"INFO"}, self._report_text(info))
        for warning in info.get("warnings", ()):  # (Compact's: its views missed part of the object)
            self.report({"WARNING"}, f"{self.bl_label}: {warning}")
        return {"FINISHED"}

    def invoke(self, context, event):
        """The panel's button: start the job and keep Blender responsive while it runs (without a
        user interface, `blender -b` or the bpy module, nothing would drive it: run it to the end)."""
        if bpy.app.background or context.window is None:
            return self.execute(context)
        try:
            self._running = self._job(context).start()
        except Exception as exc:
            self.report({"ERROR"}, f"{self.bl_label} failed: {exc}")
            return {"CANCELLED"}
        RUNNING[self._running.key] = self._running
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0.0, 1.0)
        self._status(context)
        return {"RUNNING_MODAL"}

    def _status(self, context) -> None:
        job = self._running
        context.workspace.status_text_set(f"GaussianVAE {job.status_text()}   (Esc: cancel)")
        context.window_manager.progress_update(job.fraction)
        _redraw(context)

    def _end(self, context) -> None:
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)
        RUNNING.pop(self._running.key, None)
        _redraw(context)

    def modal(self, context, event):
        job = self._running
        if event.type == "ESC" and not job.cancelled:
            job.cancel()
        if event.type != "TIMER" and not job.done:
            return {"PASS_THROUGH"}  # the rest of Blender keeps working
        if not job.done:
            self._status(context)
            return {"PASS_THROUGH"}
        self._end(context)
        try:
            info = job.finish()
        except JobCancelled:
            self.report({"WARNING"}, f"{job.label} cancelled; {job.unchanged}")
            return {"CANCELLED"}
        except Exception as exc:
            self.report({"ERROR"}, f"{job.label} failed: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, self._report_text(info))
        for warning in info.get("warnings", ()):  # (Compact's: its views missed part of the object)
            self.report({"WARNING"}, f"{self.bl_label}: {warning}")
        return {"FINISHED"}

    def cancel(self, context):  # Blender closes the window or the file while the job runs
        self._running.cancel()
        self._end(context)


#: The Refine settings for the capture's images (the operator's and the panel's).
IMAGES_DESCRIPTION = ("The capture's folder (a NeRF-Synthetic folder with transforms_train.json, or a COLMAP capture: "
                      "sparse model and images/): fit the detail to its training images (multi-view "
                      "super-resolution; checked against the splat first). Empty: the detail model alone")
IMAGE_HEIGHT_DESCRIPTION = ("Height in pixels of the images the splat was trained on (0: what its anti-aliasing "
                            "size says against the capture's cameras)")


class GVAE_OT_refine(JobOperator, Operator):
    """Add detail to the active splat object with GaussianVAE (needs PyTorch). Runs in the
    background: progress in the status bar, Esc cancels"""

    bl_idname = "gvae.refine"
    bl_label = "Refine"
    bl_options = {"REGISTER", "UNDO"}

    steps: IntProperty(name="Octaves", default=1, min=1, max=4,
                       description="Resolution doublings above the trained one that the refined Gaussians "
                       "get detail for")
    budget: StringProperty(name="Budget", default="",
                           description="Which Gaussians to refine: empty for the model's default (all), 'auto' "
                           "(the Hessian score decides), 'all', a fraction such as 0.25, or a count")
    model: StringProperty(name="Model", default="", subtype="DIR_PATH",
                          description="Model folder (config.json + weights); empty for the bundled model")
    seed: IntProperty(name="Seed", default=0, min=0, description="Random seed (repeatable runs)")
    fidelity_check: BoolProperty(name="Fidelity Check", default=True,
                                 description="Put back what the models did wherever it changes the picture at the "
                                 "training resolution (off: keep everything, which measurably lowers quality)")
    fidelity: FloatProperty(name="Tolerance", default=DEFAULT_FIDELITY["detail"], min=0.0, max=1.0, precision=4,
                            description="Largest colour change (0..1) a refined Gaussian may make at the "
                            "training resolution")
    images: StringProperty(name="Images", default="", subtype="DIR_PATH", description=IMAGES_DESCRIPTION)
    image_height: IntProperty(name="Image Height", default=0, min=0, description=IMAGE_HEIGHT_DESCRIPTION)
    fit_steps: IntProperty(name="Fit Steps", default=0, min=0,
                           description="With Images: optimiser steps per octave (0: the default; more is slower "
                           "and usually sharper)")

    def _job(self, context) -> RefineJob:
        budget = parse_budget(self.budget) if self.budget.strip() else None
        model = None
        if self.model:
            model = bpy.path.abspath(self.model)
            if os.path.isfile(model):  # a file picked inside the model folder
                model = os.path.dirname(model)
        images = bpy.path.abspath(self.images) if self.images.strip() else None
        return RefineJob(context.active_object, steps=self.steps, budget=budget, model=model, seed=self.seed,
                         fidelity=self.fidelity if self.fidelity_check else None, images=images,
                         image_height=self.image_height or None, fit_steps=self.fit_steps or None)

    def _report_text(self, info: dict) -> str:
        back = (f"; {info['put_back']} of {info['selected']} refined Gaussians put back by the fidelity check"
                if info.get("put_back") else "")
        if info.get("not_refined"):
            return f"Refine: left as it is: {info['not_refined']}"
        fit = info.get("fit")
        if fit:
            added = f"; {info['added']} Gaussians added above the training resolution" if info["added"] else ""
            if fit["kept"]:  # what was kept instead of the fit
                added += f"; the fit was no better than {fit['kept']}: not kept, {fit['kept']} instead"
            return (f"Refine: fitted to {fit['images']} training images ({info['training_resolution']}) in "
                    f"{info['seconds']:.1f} s: drawn at 2x and averaged down they are reproduced at "
                    f"{fit['before']:.2f} -> {fit['after']:.2f} dB ({fit['after'] - fit['before']:+.2f} dB); judged "
                    f"on {fit['judged']}{added}" + _timing_text(info))
        if info["added"] == 0 and info["selected"]:  # the detail model: changes per octave, no Gaussian added
            return (f"Refine: {info['selected'] - info['put_back']} of {info['before']} Gaussians given detail above "
                    f"their training resolution in {info['seconds']:.2f} s" + back + _timing_text(info))
        return (f"Refine: {info['before']} -> {info['after']} Gaussians (+{info['added']}) in "
                f"{info['seconds']:.2f} s" + back + _timing_text(info))


#: Compact's removal choices and what its fine-tuning does (the operator and the panel's settings).
REMOVAL_ITEMS = (("AUTO", "Auto", "Merge; with Photos, what the photos set aside chose: LightGaussian's prune "
                  "keeping 30% or more, the merge below"),
                 ("MERGE", "Merge", "Merge Gaussians into their neighbours (moments kept)"),
                 ("PRUNE", "Prune", "Drop the Gaussians with the lowest scores"))
COMPACT_IMAGES_DESCRIPTION = ("The capture's photos (a COLMAP capture, a transforms.json with its images, a "
                              "NeRF-Synthetic folder): remove, then fine-tune on them until the photos set aside stop "
                              "improving (minutes), as gvae compact --images; empty: without")
CAMERAS_DESCRIPTION = ("The capture's cameras to score from (a COLMAP capture folder, a transforms.json, the reference "
                       "3DGS's cameras.json); empty: the training cameras found beside the imported file, else views "
                       "placed around the object")
FOUND_CAMERAS_DESCRIPTION = ("Without Cameras: score from the cameras the splat's training left beside the file it "
                             "was imported from (the reference 3DGS's cameras.json two folders up, a gvae train "
                             "run's capture) when they see it; off: views placed around it")
DISTILL_DESCRIPTION = ("Fine-tune the result against the object's own renders for at most this many iterations, "
                       "stopping sooner when renders set aside stop improving (-1: automatic, at most 1000 for "
                       "objects of up to 50,000 Gaussians, stopped after about 3 minutes, none for larger ones; 0: "
                       "drop and merge only; slower, keeps the picture closer)")


class GVAE_OT_compact(JobOperator, Operator):
    """Remove the Gaussians the active splat object's picture does not need: merge them into their
    neighbours, the Hessian choosing which (needs PyTorch). Runs in the background: progress in
    the status bar, Esc cancels"""

    bl_idname = "gvae.compact"
    bl_label = "Compact"
    bl_options = {"REGISTER", "UNDO"}

    keep: FloatProperty(name="Keep", default=0.5, min=0.0001, max=1.0, subtype="FACTOR",
                        description="Fraction of the Gaussians to keep")
    count: IntProperty(name="Count", default=0, min=0,
                       description="Number of Gaussians to keep (0: use Keep)")
    removal: EnumProperty(name="Removal", default="AUTO", items=REMOVAL_ITEMS)
    distill: IntProperty(name="Fine-Tune Iterations", default=-1, min=-1, description=DISTILL_DESCRIPTION)
    seed: IntProperty(name="Seed", default=0, min=0, description="Random seed (repeatable runs)")
    cameras: StringProperty(name="Cameras", subtype="FILE_PATH", default="", description=CAMERAS_DESCRIPTION)
    found_cameras: BoolProperty(name="Training Cameras", default=True, description=FOUND_CAMERAS_DESCRIPTION)
    images: StringProperty(name="Photos", subtype="DIR_PATH", default="", description=COMPACT_IMAGES_DESCRIPTION)

    def _job(self, context) -> CompactJob:
        return CompactJob(context.active_object, keep=None if self.count else self.keep, count=self.count or None,
                          removal=None if self.removal == "AUTO" else self.removal.lower(),
                          distill="auto" if self.distill < 0 else self.distill, seed=self.seed, cameras=self.cameras,
                          found_cameras=self.found_cameras, images=self.images)

    def _report_text(self, info: dict) -> str:
        return (f"Compact: {info['before']} -> {info['after']} Gaussians ({info['after'] / max(info['before'], 1):.0%})"
                f" in {info['seconds']:.2f} s; PSNR against the input's render {info['psnr']:.2f} dB"
                + "".join(f"; {note}" for note in info.get("views", ()))
                + "".join(f"; fine-tuned {t['iterations']} iterations (best at {t['best_at']}), PSNR on "
                          f"{t['judged_on']} {t['psnr_before']:.2f} -> {t['psnr_after']:.2f} dB"
                          for t in info.get("tuned", ()))
                + _timing_text(info))


classes = (GVAE_OT_refine, GVAE_OT_compact)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for job in list(RUNNING.values()):
        job.cancel()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
