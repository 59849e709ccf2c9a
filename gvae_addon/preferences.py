"""Add-on preferences: PyTorch status and the button that installs the pinned CPU build."""

from __future__ import annotations

import importlib
import shlex
import subprocess

import bpy
from bpy.props import StringProperty
from bpy.types import AddonPreferences, Operator

from . import runtime


class GVAE_OT_install_torch(Operator):
    """Download and install the pinned CPU build of PyTorch (and safetensors) into this extension's
    user directory (needs internet access, about 200 MB)"""

    bl_idname = "gvae.install_torch"
    bl_label = "Install PyTorch"
    bl_options = {"REGISTER", "INTERNAL"}

    requirement: StringProperty(name="Requirements", default=" ".join(runtime.REFINE_REQUIREMENTS),
                                options={"HIDDEN", "SKIP_SAVE"},
                                description="Space-separated pinned requirements to install")
    pip_args: StringProperty(name="pip Options", default="", options={"HIDDEN", "SKIP_SAVE"},
                             description="Replace the index options (e.g. a mirror, or "
                             "'--no-index --find-links DIR' for a folder of wheels)")

    _proc = None
    _timer = None

    def _command(self) -> list[str]:
        extra = tuple(shlex.split(self.pip_args)) if self.pip_args.strip() else None
        return runtime.pip_install_command(runtime.torch_dir(create=True), tuple(self.requirement.split()),
                                           extra)

    def _finish(self, code: int, output: str):
        runtime.add_torch_dir()
        importlib.invalidate_caches()
        if code != 0:
            tail = output.strip().splitlines()[-3:]
            self.report({"ERROR"}, f"Installing {self.requirement} failed (pip exit {code}): "
                        + " | ".join(tail))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Installed {self.requirement} into {runtime.torch_dir()}")
        return {"FINISHED"}

    def execute(self, context):
        # Headless (batch) runs wait; the UI polls a background process so Blender stays responsive.
        cmd = self._command()
        if bpy.app.background or context.window is None:
            proc = subprocess.run(cmd, capture_output=True, text=True)
            return self._finish(proc.returncode, proc.stdout + proc.stderr)
        self._proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._timer = context.window_manager.event_timer_add(0.5, window=context.window)
        context.window_manager.modal_handler_add(self)
        self.report({"INFO"}, f"Installing {self.requirement} into {runtime.torch_dir()} ...")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER" or self._proc.poll() is None:
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        output = self._proc.stdout.read() if self._proc.stdout else ""
        return self._finish(self._proc.returncode, output)


class GVAE_AddonPreferences(AddonPreferences):
    bl_idname = runtime.ADDON_ID

    def draw(self, context):
        layout = self.layout
        box = layout.box()
        ok, message = runtime.refine_status()
        box.label(text=message if not ok else "PyTorch is available: Refine can run",
                  icon="CHECKMARK" if ok else "ERROR")
        if not runtime.runtime_installed():
            box.label(text="Import and Export work without it")
            box.operator(GVAE_OT_install_torch.bl_idname,
                         text=f"Install PyTorch ({runtime.TORCH_REQUIREMENT}, CPU, for {runtime.PYTHON})",
                         icon="IMPORT")
        box.label(text=f"Install directory: {runtime.torch_dir()}")


classes = (GVAE_OT_install_torch, GVAE_AddonPreferences)


def register():
    runtime.add_torch_dir()
    for cls in classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
    runtime.remove_torch_dir()
