"""Fixtures of the Blender tests: the extension zip, built once per session, and scenarios run
in fresh Blender processes (`_scenarios.py`; add a `scenario_NAME(bpy, args)` function there)."""

from __future__ import annotations

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


def run_scenario(name: str, tmp_path: Path, zip_path: Path | None, **args) -> dict:
    args = {"home": str(tmp_path / "home"), "zip": str(zip_path), "out": str(tmp_path / f"{name}.json"),
            **args}
    args_path = tmp_path / f"{name}.args.json"
    args_path.write_text(json.dumps(args))
    proc = subprocess.run([BLENDER_PYTHON, str(SCENARIOS), name, str(args_path)],
                          capture_output=True, text=True, timeout=150, cwd=tmp_path)
    assert proc.returncode == 0, f"scenario {name} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    res = json.loads(Path(args["out"]).read_text())
    res["_output"] = proc.stdout + proc.stderr
    return res
