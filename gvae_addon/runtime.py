"""Where the add-on's optional runtime (PyTorch, `gvae_core.refine`) comes from.

Import and export need only numpy; Refine needs torch. Blender's Python can get torch two ways:
an offline build of the extension that bundles the wheels (for each Python it is meant for: Blender
installs the ones for its own), or the preferences button that pip-installs the pinned CPU build,
for the running Python, into the extension's own user directory, one folder per Python version
(Blender 4.2 to 5.0 run Python 3.11, 5.1 and later 3.13: a torch built for one does not load in the
other, and a user directory copied from an older Blender must not pass for an installed torch).
That directory is put on `sys.path` (appended, so it never shadows Blender's own modules) when the
add-on registers.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import os
import sys

import bpy

#: What Refine needs beyond Blender's own Python, pinned as in pyproject.toml: torch, safetensors
#: for the model weights, and numba for the compiled CPU renderer (without it the renderer runs its
#: torch code, several times slower). The preferences button installs all three.
TORCH_REQUIREMENT = "torch==2.13.0"
REFINE_REQUIREMENTS = (TORCH_REQUIREMENT, "safetensors==0.8.0", "numba==0.68.1")

#: What structure from motion needs (New from Photos on a folder of photos without a model), pinned as in
#: pyproject.toml; installed on demand by the same button, into the same directory.
SFM_REQUIREMENTS = ("pycolmap==4.2.1",)

#: Root package of the installed extension (e.g. "bl_ext.user_default.gaussian_vae"), or
#: "gvae_addon" when the add-on is registered straight from a source checkout.
ADDON_ID = __package__.rpartition(".")[0] or __package__


#: The running Python, as the folder the install button uses names it (python3.11, python3.13).
PYTHON = "python{}.{}".format(*sys.version_info[:2])


def torch_dir(create: bool = False) -> str:
    """The directory the preferences button installs torch into, for the running Python."""
    sub = os.path.join("lib", PYTHON, "site-packages")
    try:
        return bpy.utils.extension_path_user(ADDON_ID, path=sub, create=create)
    except ValueError:  # not running as an extension (source checkout): a config sub-directory
        path = os.path.join(bpy.utils.user_resource("CONFIG"), "gvae_addon", sub)
        if create:
            os.makedirs(path, exist_ok=True)
        return path


def add_torch_dir() -> None:
    """Make a previously installed torch importable."""
    path = torch_dir()
    if os.path.isdir(path) and path not in sys.path:
        sys.path.append(path)
        importlib.invalidate_caches()


def remove_torch_dir() -> None:
    path = torch_dir()
    if path in sys.path:
        sys.path.remove(path)


def _has_module(name: str) -> bool:
    if name in sys.modules:
        return sys.modules[name] is not None
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def torch_available() -> bool:
    """Whether `import torch` can work (checked without importing it: draw code calls this)."""
    return _has_module("torch")


def runtime_installed() -> bool:
    """torch and safetensors are importable (what the install button provides)."""
    return torch_available() and _has_module("safetensors")


def refine_status(module: str = "gvae_core.refinement", label: str = "Refine") -> tuple[bool, str]:
    """(available, message) for Refine (or the job `label` that `module` runs), without importing torch."""
    if not _has_module(module):
        return False, f"{label} is not in this build: {module} is missing"
    if not torch_available():
        return False, f"{label} needs PyTorch: install it in the add-on preferences"
    if not _has_module("safetensors"):
        return False, f"{label} needs safetensors: use Install PyTorch in the add-on preferences"
    return True, f"{label} is ready"


#: The core module Compact runs (what `refine_status(COMPACT_MODULE, "Compact")` looks for).
COMPACT_MODULE = "gvae_core.compaction"


def core_refine():
    """`gvae_core.refinement.refine`, imported on first use (this imports torch). Raises RuntimeError
    with a user-facing message when it cannot be imported."""
    return _core("gvae_core.refinement", "refine", "Refine")


def core_compact():
    """`gvae_core.compaction.compact`, imported on first use (this imports torch), as `core_refine`."""
    return _core(COMPACT_MODULE, "compact", "Compact")


def _core(module_name: str, function: str, label: str):
    ok, message = refine_status(module_name, label)
    if not ok:
        raise RuntimeError(message)
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise RuntimeError(f"{label} could not be loaded: {exc}") from exc
    return getattr(module, function)


def _stamp(folder: str):
    """What changes when a folder's contents do (its own and its images/ and sparse/ folders' times)."""
    stamps = []
    for sub in ("", "images", "sparse", os.path.join("sparse", "0")):
        try:
            stamps.append(os.stat(os.path.join(folder, sub)).st_mtime_ns)
        except OSError:
            stamps.append(None)
    return tuple(stamps)


#: What New from Photos calls the work of `gvae_core.capture.sfm.pending_work` (its progress says it).
PYCOLMAP_WORK = {"structure from motion": "structure from motion", "triangulation": "points for the photos' poses"}


@functools.lru_cache(maxsize=16)
def _pycolmap_work(folder: str, stamp) -> str | None:
    from gvae_core.capture.sfm import pending_work  # noqa: PLC0415 - pycolmap is imported only when SfM runs

    try:
        work = pending_work(folder, points=True)
    except (ValueError, OSError):
        return None  # (not a capture: the job says what is wrong)
    return PYCOLMAP_WORK.get(work)


def pycolmap_work(folder: str) -> str | None:
    """What New from Photos needs pycolmap for in `folder`, as `gvae train` does it first
    (`gvae_core.capture.sfm.pending_work`): "structure from motion" for photos without cameras,
    "points for the photos' poses" (triangulation) for a capture of photos with poses and no points, or
    None. Remembered per folder until its contents change (the panel asks at every redraw)."""
    return _pycolmap_work(folder, _stamp(folder)) if folder and os.path.isdir(folder) else None


def photos_missing(folder: str) -> list[tuple[str, tuple[str, ...]]]:
    """What New from Photos needs that this Blender lacks, as (what, pinned requirements) pairs, said
    before the job starts: PyTorch (training), and pycolmap where `folder` needs it (`pycolmap_work`)."""
    missing = []
    if not torch_available():
        missing.append(("PyTorch (training)", REFINE_REQUIREMENTS))
    work = pycolmap_work(folder)
    if work is not None and not _has_module("pycolmap"):
        missing.append((f"pycolmap ({work})", SFM_REQUIREMENTS))
    return missing


def prepare_kernels(progress) -> None:
    """Load the core's compiled CPU kernels (renderer, detail model, compaction), or compile them the
    first time (a minute or two), saying so through progress(fraction, message); nothing without
    numba (the torch and numpy code run)."""
    importlib.import_module("gvae_core.warmup").compile_kernels(progress)


def pip_install_command(target: str, requirements: tuple[str, ...] = REFINE_REQUIREMENTS,
                        extra_args: tuple[str, ...] | None = None) -> list[str]:
    """The pip command line that installs `requirements` into `target` with Blender's Python: pip
    picks the wheels built for it (cp311 or cp313), binary wheels only (nothing is compiled).

    On Linux and Windows the CPU wheels come from the PyTorch index (PyPI's Linux wheels pull in
    CUDA); macOS wheels on PyPI are CPU builds already."""
    if extra_args is None:
        extra_args = (() if sys.platform == "darwin"
                      else ("--index-url", "https://download.pytorch.org/whl/cpu",
                            "--extra-index-url", "https://pypi.org/simple"))
    return [sys.executable, "-m", "pip", "install", "--upgrade", "--disable-pip-version-check",
            "--no-warn-script-location", "--only-binary=:all:", "--target", target, *extra_args, *requirements]
