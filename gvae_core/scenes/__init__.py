"""Benchmark scenes made with Blender, in the NeRF-Synthetic format.

`make_scene(name, out_dir, profile=, seed=)` renders one of the procedural scenes of
`list_scenes()` with Cycles (in a fresh Python subprocess, since Blender's state is global to a
process) into a folder with transforms_train.json / transforms_test.json, train/ and test/ RGBA
PNGs, mesh.ply (the ground-truth triangles in world coordinates) and gt_points.npy (surface
points that the test cameras see). Results are cached by (name, profile, seed, generator
version) under `cache_dir()`, so a second call returns at once. Only the generation needs bpy;
importing this package does not.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from .blender import INSTALL_HINT, BlenderNotAvailable
from .library import SCENES, SPLITS

# Bump when the scenes, cameras or render settings change: it invalidates cached scenes.
GENERATOR_VERSION = 1
MARKER = "scene.json"


@dataclass(frozen=True)
class Profile:
    """How much to render: image size (square), view counts, Cycles samples per pixel (then
    denoised) and how many candidate surface points are tested for visibility."""

    name: str
    resolution: int
    n_train: int
    n_test: int
    samples: int
    gt_candidates: int


PROFILES: dict[str, Profile] = {p.name: p for p in [
    Profile("tiny", 64, 8, 4, 16, 20_000),
    Profile("small", 200, 24, 8, 16, 50_000),
    Profile("default", 400, 60, 20, 16, 100_000),
    Profile("full", 800, 100, 200, 16, 400_000),
]}


def list_scenes() -> list[str]:
    """Names of the procedural scenes."""
    return list(SCENES)


def describe_scenes() -> dict[str, str]:
    """Scene name -> what it stresses."""
    return {name: spec.stresses for name, spec in SCENES.items()}


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """Where generated scenes are kept: `path`, else $GVAE_CACHE_DIR, else ~/.cache/gvae."""
    if path is None:
        path = os.environ.get("GVAE_CACHE_DIR") or Path.home() / ".cache" / "gvae"
    return Path(path).expanduser()


def _check(name: str, profile: str, seed: int) -> Profile:
    scenes = list_scenes()
    if name not in scenes:
        raise ValueError(f"unknown scene {name!r}; available: {', '.join(scenes)}")
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; available: {', '.join(PROFILES)}")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return PROFILES[profile]


def scene_key(name: str, profile: str = "tiny", seed: int = 0) -> str:
    """Hash of everything that determines a generated scene."""
    prof = _check(name, profile, seed)
    blob = json.dumps({"name": name, "profile": asdict(prof), "seed": seed, "version": GENERATOR_VERSION},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _read_marker(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None


def _publish(tmp: Path, final: Path) -> None:
    """Move a finished temporary folder into place; if another process got there first with the
    same scene, keep theirs."""
    if not final.exists():
        try:
            os.replace(tmp, final)
        except OSError:  # lost a race with another process writing the same scene
            pass
    if tmp.exists():
        shutil.rmtree(tmp, ignore_errors=True)
    if _read_marker(final) is None:
        raise RuntimeError(f"could not move the generated scene into {final}")


def make_scene(name: str, out_dir: str | os.PathLike | None = None, *, profile: str = "tiny", seed: int = 0,
               cache: str | os.PathLike | None = None, threads: int | None = None, verbose: bool = False) -> Path:
    """Generate (or find cached) the scene `name` and return its NeRF-Synthetic folder: the cache
    folder itself, or `out_dir` (a copy of it) when given. `cache` overrides `cache_dir()`;
    `threads` is the Cycles thread count (default: all cores); `verbose` streams progress."""
    _check(name, profile, seed)
    key = scene_key(name, profile, seed)
    root = cache_dir(cache) / "scenes"
    cached = root / f"{name}-{profile}-s{seed}-{key}"
    if _read_marker(cached) is None:
        _generate(name, profile, seed, cached, threads, verbose)
    if out_dir is None:
        return cached
    return _export(cached, Path(out_dir), key)


def bpy_available() -> bool:
    """Whether the bpy module can be imported (without importing it)."""
    return importlib.util.find_spec("bpy") is not None


def _generate(name: str, profile: str, seed: int, final: Path, threads: int | None, verbose: bool) -> None:
    if not bpy_available():
        raise BlenderNotAvailable(f"generating scene {name!r} needs Blender's Python module bpy: {INSTALL_HINT}")
    final.parent.mkdir(parents=True, exist_ok=True)
    if final.exists():  # a folder without a marker is a leftover of a crash: replace it
        shutil.rmtree(final)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    cmd = [sys.executable, "-m", "gvae_core.scenes.build", name, str(tmp), "--profile", profile, "--seed", str(seed)]
    if threads:
        cmd += ["--threads", str(int(threads))]
    try:
        proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=None if verbose else subprocess.PIPE,
                              text=True)
        if proc.returncode != 0:
            tail = "" if verbose else "\n" + "\n".join((proc.stderr or "").strip().splitlines()[-15:])
            raise RuntimeError(f"generating scene {name!r} (profile {profile}, seed {seed}) failed "
                               f"with exit code {proc.returncode}{tail}")
        _publish(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _export(cached: Path, out: Path, key: str) -> Path:
    """Copy a cached scene to `out` (through a temporary sibling, so nothing is half-written).
    An existing `out` is replaced only when it is a scene folder this package wrote."""
    if out.exists():
        marker = _read_marker(out)
        if marker is not None and marker.get("key") == key:
            return out
        if marker is None and (not out.is_dir() or any(out.iterdir())):
            raise ValueError(f"{out} exists and is not a generated scene; choose an empty or new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        shutil.copytree(cached, tmp, dirs_exist_ok=True)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


__all__ = ["GENERATOR_VERSION", "PROFILES", "SPLITS", "Profile", "BlenderNotAvailable", "list_scenes",
           "describe_scenes", "make_scene", "scene_key", "cache_dir"]
