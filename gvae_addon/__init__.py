"""GaussianVAE for Blender: the Blender side (operators, panels, preferences, bpy <-> core glue).

No algorithm lives here: `convert` moves Gaussians between meshes and `gvae_core.GaussianCloud`,
everything else calls `gvae_core`. Register from a source checkout with
`import gvae_addon; gvae_addon.register()`; the extension's root `__init__.py` does the same.
"""

from __future__ import annotations

import importlib

_MODULES = ("preferences", "io_ops", "refine_ops", "photos_ops", "ui", "render_setup")


def _modules():
    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULES]


def register():
    for module in _modules():
        module.register()


def unregister():
    for module in reversed(_modules()):
        module.unregister()
