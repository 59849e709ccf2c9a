"""Refine: run `gvae_core.refine` on the active splat object and write the result back into it."""

from __future__ import annotations

import os
import sys
import time

import bpy
import numpy as np
from bpy.props import IntProperty, StringProperty
from bpy.types import Operator

from gvae_core.budget import parse_budget

from . import convert, runtime


def refine_object(obj, *, steps: int = 1, budget="auto", model=None, seed: int = 0,
                  progress=None) -> dict:
    """Refine a splat object in place: its mesh is replaced by one holding the refined cloud with a
    `gvae_step` attribute (0 for the original Gaussians, the refine step for added ones, counted on
    from an earlier refine). Nothing in the blend file changes unless the whole run succeeds.
    Returns counts and timings for the report."""
    refine = runtime.core_refine()
    cloud, old_steps = convert.cloud_from_object(obj)
    n_in = len(cloud)
    if n_in == 0:
        raise ValueError(f"object {obj.name!r} has no Gaussians to refine")
    result = refine(cloud, steps=steps, budget=budget, model=model, seed=seed, progress=progress)
    out = result.cloud
    marks = np.zeros(len(out), np.int32)
    base = 0
    if old_steps is not None:
        marks[:n_in] = old_steps
        base = int(old_steps.max(initial=0))
    marks[result.added] = base + result.step

    old = obj.data
    new = convert.mesh_from_cloud(out, old.name, steps=marks)
    for mat in old.materials:
        new.materials.append(mat)
    obj.data = new
    if old.users == 0:
        bpy.data.meshes.remove(old)
    return {"before": n_in, "after": len(out), "added": len(result.added), "timings": dict(result.timings)}


class GVAE_OT_refine(Operator):
    """Add detail to the active splat object with GaussianVAE (needs PyTorch)"""

    bl_idname = "gvae.refine"
    bl_label = "Refine"
    bl_options = {"REGISTER", "UNDO"}

    steps: IntProperty(name="Steps", default=1, min=1, max=4,
                       description="Resolution steps to extrapolate past the trained one")
    budget: StringProperty(name="Budget", default="auto",
                           description="'auto' (the Hessian score decides), 'all', a fraction of the "
                           "Gaussians such as 0.25, or a count")
    model: StringProperty(name="Model", default="", subtype="DIR_PATH",
                          description="Model folder (config.json + weights); empty for the bundled model")
    seed: IntProperty(name="Seed", default=0, min=0, description="Random seed (repeatable runs)")

    @classmethod
    def poll(cls, context):
        return convert.is_splat(context.active_object)

    def execute(self, context):
        obj = context.active_object
        wm = context.window_manager
        background = bpy.app.background

        def progress(fraction: float, message: str = "") -> None:
            wm.progress_update(max(0.0, min(1.0, float(fraction))))
            if background:
                print(f"gvae.refine: {100 * fraction:5.1f}% {message}", file=sys.stderr)

        start = time.perf_counter()
        wm.progress_begin(0.0, 1.0)
        try:
            budget = parse_budget(self.budget)
            model = None
            if self.model:
                model = bpy.path.abspath(self.model)
                if os.path.isfile(model):  # a file picked inside the model folder
                    model = os.path.dirname(model)
            info = refine_object(obj, steps=self.steps, budget=budget, model=model, seed=self.seed,
                                 progress=progress)
        except Exception as exc:
            self.report({"ERROR"}, f"Refine failed: {exc}")
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        parts = ", ".join(f"{k} {v:.2f} s" for k, v in info["timings"].items()
                          if isinstance(v, (int, float)) and k != "total")
        self.report({"INFO"}, f"Refine: {info['before']} -> {info['after']} Gaussians "
                    f"(+{info['added']}) in {time.perf_counter() - start:.2f} s"
                    + (f" ({parts})" if parts else ""))
        return {"FINISHED"}


classes = (GVAE_OT_refine,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
