"""PlayCanvas's splat-transform (npm `@playcanvas/splat-transform`), installed once into a cache folder.

The test that checks files both ways against it (tests/test_splat_transform.py) and the `sog`
benchmark run the same pinned version from the same place: `$GVAE_CACHE_DIR/npm/splat-transform-VERSION`
(default ~/.cache/gvae/...), installed with `npm install --ignore-scripts` (about 215 MB; 10 s with
npm's download cache warm, 30 s without) into a temporary folder renamed into place, so that runs
side by side never see half an install.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

VERSION = "3.7.0"
PACKAGE = f"@playcanvas/splat-transform@{VERSION}"
_CLI = Path("node_modules", "@playcanvas", "splat-transform", "bin", "cli.mjs")


class Unavailable(RuntimeError):
    """node or npm is not on PATH."""


def cache_dir() -> Path:
    base = os.environ.get("GVAE_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "gvae")
    return Path(base) / "npm" / f"splat-transform-{VERSION}"


def command(*, install: bool = True) -> list[str]:
    """The command that runs splat-transform (`node .../cli.mjs`), installing it first when missing
    and `install` is true. Unavailable without node and npm (or when not installed and not to be);
    RuntimeError when npm fails."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        raise Unavailable(f"{'node' if not node else 'npm'} is not on PATH")
    root = cache_dir()
    if not (root / _CLI).exists():
        if not install:
            raise Unavailable(f"splat-transform {VERSION} is not installed in {root}")
        tmp = root.with_name(f"{root.name}.{os.getpid()}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        proc = subprocess.run([npm, "install", "--prefix", str(tmp), "--no-audit", "--no-fund", "--no-package-lock",
                               "--ignore-scripts", "--loglevel=error", PACKAGE],
                              capture_output=True, text=True, timeout=600)
        if proc.returncode != 0:
            shutil.rmtree(tmp, ignore_errors=True)
            raise RuntimeError(f"npm install {PACKAGE} failed:\n{proc.stdout}\n{proc.stderr}")
        try:
            os.replace(tmp, root)
        except OSError:  # another run installed it meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
    return [node, str(root / _CLI)]


def convert(cmd: list[str], src, dst, *options: str, timeout: float = 600) -> Path:
    """splat-transform SRC DST (overwriting, quiet, CPU only); RuntimeError with its output on failure."""
    proc = subprocess.run([*cmd, "-w", "-q", "-g", "cpu", *options, str(src), str(dst)],
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0 or not Path(dst).exists():
        raise RuntimeError(f"splat-transform {src} -> {dst} failed:\n{proc.stdout}{proc.stderr}")
    return Path(dst)
