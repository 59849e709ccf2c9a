"""npm packages the cross-checks run with node (splat-transform, Khronos's glTF validator), each
installed once into a cache folder: `$GVAE_CACHE_DIR/npm/NAME-VERSION` (default ~/.cache/gvae/...),
with `npm install --ignore-scripts` into a temporary folder renamed into place, so that runs side
by side never see half an install."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path


class Unavailable(RuntimeError):
    """node or npm is not on PATH (or the package is not installed and is not to be)."""


def cache_root() -> Path:
    base = os.environ.get("GVAE_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "gvae")
    return Path(base) / "npm"


def node() -> str:
    """The node executable; Unavailable without node and npm."""
    found, npm = shutil.which("node"), shutil.which("npm")
    if not found or not npm:
        raise Unavailable(f"{'node' if not found else 'npm'} is not on PATH")
    return found


def installed(package: str, root: Path, marker: Path, *, install: bool = True) -> Path:
    """`root` holding `package` (an npm spec, NAME@VERSION), installed there first when `root / marker`
    is missing and `install` is true. Unavailable without node and npm (or when missing and not to
    be installed); RuntimeError when npm fails."""
    node()
    if (root / marker).exists():
        return root
    if not install:
        raise Unavailable(f"{package} is not installed in {root}")
    tmp = root.with_name(f"{root.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    proc = subprocess.run([shutil.which("npm"), "install", "--prefix", str(tmp), "--no-audit", "--no-fund",
                           "--no-package-lock", "--ignore-scripts", "--loglevel=error", package],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        raise RuntimeError(f"npm install {package} failed:\n{proc.stdout}\n{proc.stderr}")
    try:
        os.replace(tmp, root)
    except OSError:  # another run installed it meanwhile
        shutil.rmtree(tmp, ignore_errors=True)
    return root
