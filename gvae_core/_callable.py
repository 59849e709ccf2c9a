"""Modules that are also their main function (`gvae_core.render`, `gvae_core.refine`)."""

import sys
import types


def make_module_callable(module_name: str, function_name: str) -> None:
    """Make the module callable as its function `function_name`.

    `gvae_core.render` names both a module and the function in it: once the module has been
    imported (which sets the package attribute to the module), `gvae_core.render(...)` must
    still call the function."""
    module = sys.modules[module_name]

    class CallableModule(types.ModuleType):
        def __call__(self, *args, **kwargs):
            return getattr(self, function_name)(*args, **kwargs)

    CallableModule.__doc__ = module.__doc__
    module.__class__ = CallableModule
