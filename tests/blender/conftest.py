"""Fixtures of the Blender tests: the extension zip, built once per session, and scenarios run
in fresh Blender processes (`_scenarios.py`; add a `scenario_NAME(bpy, args)` function there)."""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = Path(__file__).with_name("_scenarios.py")
#: The Python (with a bpy module) that runs Blender: this one, or GVAE_BLENDER_PYTHON, a venv with
#: another Blender version (`make test-blender-versions`).
BLENDER_PYTHON = os.path.abspath(os.environ.get("GVAE_BLENDER_PYTHON") or sys.executable)


@functools.cache
def blender_versions() -> tuple[tuple[int, int], tuple[int, ...]]:
    """((major, minor) of the Python that runs Blender, the bpy module's version), without
    starting Blender."""
    code = "import sys, importlib.metadata as m; print(*sys.version_info[:2]); print(m.version('bpy'))"
    py, bpy = subprocess.run([BLENDER_PYTHON, "-c", code], capture_output=True, text=True,
                             check=True).stdout.split("\n")[:2]
    return tuple(int(v) for v in py.split()), tuple(int(v) for v in bpy.split("."))


@functools.cache
def blender_python_has(module: str) -> bool:
    """Whether `module` is importable in the Python that runs Blender (found, not imported)."""
    code = f"import importlib.util, sys; sys.exit(importlib.util.find_spec({module!r}) is None)"
    return subprocess.run([BLENDER_PYTHON, "-c", code]).returncode == 0


def requires_blender_torch() -> None:
    """Skip, saying why, where Blender's Python has no PyTorch (`make test-blender-versions` installs
    the CPU build from local disk for Python 3.11; for the Python 3.13 of Blender 5.1+ the package
    index has only the CUDA build of Linux torch, over 0.5 GB before the CUDA libraries)."""
    if not blender_python_has("torch"):
        major, minor = blender_versions()[0]
        pytest.skip(f"no PyTorch in the Python {major}.{minor} that runs Blender ({BLENDER_PYTHON}): "
                    + ("no CPU torch wheel for cp313 is available here (PyPI's Linux torch is the CUDA build)"
                       if (major, minor) >= (3, 13) else "install torch==2.13.0 (CPU) there"))


def blender_ext() -> Path:
    origin = Path(importlib.util.find_spec("bpy").origin).parent
    return next(origin.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory) -> Path:
    """The extension built by the same script as `make extension`, into a temporary dist/."""
    base = tmp_path_factory.mktemp("ext")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "build_extension.py"), "--output-dir", str(base / "dist"),
         "--staging-dir", str(base / "stage"), "--wheel-cache", str(ROOT / "build" / "wheels")],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return Path(proc.stdout.strip().splitlines()[-1])


def run_scenario(name: str, tmp_path: Path, zip_path: Path | None, *, timeout: float = 150, **args) -> dict:
    args = {"home": str(tmp_path / "home"), "zip": str(zip_path), "out": str(tmp_path / f"{name}.json"),
            **args}
    args_path = tmp_path / f"{name}.args.json"
    args_path.write_text(json.dumps(args))
    proc = subprocess.run([BLENDER_PYTHON, str(SCENARIOS), name, str(args_path)],
                          capture_output=True, text=True, timeout=timeout, cwd=tmp_path)
    assert proc.returncode == 0, f"scenario {name} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    res = json.loads(Path(args["out"]).read_text())
    res["_output"] = proc.stdout + proc.stderr
    return res
