"""PlayCanvas's splat-transform (npm `@playcanvas/splat-transform`), installed once into a cache folder.

The test that checks files both ways against it (tests/test_splat_transform.py) and the `sog`
benchmark run the same pinned version from the same place: `$GVAE_CACHE_DIR/npm/splat-transform-VERSION`
(default ~/.cache/gvae/...), installed by `npm.installed` (about 215 MB; 10 s with npm's download
cache warm, 30 s without).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from .npm import Unavailable, cache_root, installed, node

__all__ = ["VERSION", "PACKAGE", "Unavailable", "cache_dir", "command", "convert"]

VERSION = "3.7.0"
PACKAGE = f"@playcanvas/splat-transform@{VERSION}"
_CLI = Path("node_modules", "@playcanvas", "splat-transform", "bin", "cli.mjs")


def cache_dir() -> Path:
    return cache_root() / f"splat-transform-{VERSION}"


def command(*, install: bool = True) -> list[str]:
    """The command that runs splat-transform (`node .../cli.mjs`), installing it first when missing
    and `install` is true. Unavailable without node and npm (or when not installed and not to be);
    RuntimeError when npm fails."""
    return [node(), str(installed(PACKAGE, cache_dir(), _CLI, install=install) / _CLI)]


def convert(cmd: list[str], src, dst, *options: str, timeout: float = 600) -> Path:
    """splat-transform SRC DST (overwriting, quiet, CPU only); RuntimeError with its output on failure."""
    proc = subprocess.run([*cmd, "-w", "-q", "-g", "cpu", *options, str(src), str(dst)],
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0 or not Path(dst).exists():
        raise RuntimeError(f"splat-transform {src} -> {dst} failed:\n{proc.stdout}{proc.stderr}")
    return Path(dst)
