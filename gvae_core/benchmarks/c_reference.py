"""The C/OpenMP reference rasteriser (`reference_rasteriser.c`), compiled by the benchmark when a C
compiler is at hand: what a plain compiled implementation of the same forward pass does on this
machine, timed beside the renderer in one run."""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import quaternions
from ..camera import Camera
from ..cloud import GaussianCloud
from ..rendering.projection import fov_limits

SOURCE = Path(__file__).with_name("reference_rasteriser.c")
#: Compiled with these flags, then linked without -ffast-math: linked with it, gcc adds start-up code
#: that sets flush-to-zero for the whole process that loads the library (the renderer's too).
FLAGS = ["-O3", "-march=native", "-ffast-math", "-fopenmp", "-fPIC"]


@dataclass
class CReference:
    """The loaded library (`build`), or why there is none (`reason`)."""

    lib: ctypes.CDLL | None
    reason: str = ""
    command: str = ""

    def render(self, cloud: GaussianCloud, camera: Camera, *, tile_size: int = 8, threads: int = 1,
               background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, dict]:
        """(image (H, W, 3) float32, {"project", "bin", "composite", "total": seconds, "pairs"})."""
        c = cloud.numpy()
        n = len(c)
        means = np.ascontiguousarray(c.means, np.float64)
        scales = np.ascontiguousarray(c.scales, np.float32)
        quats = np.ascontiguousarray(c.quats, np.float32)
        logits = np.ascontiguousarray(c.opacities, np.float32)
        k = c.sh_rest.shape[1]
        sh = np.ascontiguousarray(np.concatenate([c.sh_dc[:, None, :], c.sh_rest], 1), np.float32)
        q = quaternions.from_rotmat(camera.rotation)
        cam = np.concatenate([camera.rotation.reshape(-1), camera.center, [camera.fx, camera.fy, camera.cx, camera.cy],
                              fov_limits(camera), q]).astype(np.float64)
        image = np.zeros((camera.height, camera.width, 3), np.float32)
        times = np.zeros(3, np.float64)
        bg = np.asarray(background, np.float32)

        def ptr(a, t):
            return a.ctypes.data_as(ctypes.POINTER(t))

        f, d = ctypes.c_float, ctypes.c_double
        pairs = self.lib.render(n, ptr(means, d), ptr(scales, f), ptr(quats, f), ptr(logits, f), ptr(sh, f), k,
                                c.sh_degree, ptr(cam, d), camera.width, camera.height, tile_size, ptr(bg, f), threads,
                                ptr(image, f), ptr(times, d))
        parts = dict(zip(("project", "bin", "composite"), times.tolist()))
        return image, {**parts, "total": float(times.sum()), "pairs": int(pairs)}


def build(out_dir: str | os.PathLike | None = None) -> CReference:
    """Compile `reference_rasteriser.c` with the C compiler ($CC, else cc or gcc) into `out_dir` (a
    temporary folder by default) and load it; without a compiler or OpenMP, say why."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        return CReference(None, "no C compiler (cc, gcc or $CC) on this machine")
    out = Path(out_dir or tempfile.mkdtemp(prefix="gvae-cref-"))
    lib_path, obj = out / "reference_rasteriser.so", out / "reference_rasteriser.o"
    cmds = [[cc, *FLAGS, "-c", str(SOURCE), "-o", str(obj)], [cc, "-shared", "-fopenmp", str(obj), "-o", str(lib_path),
                                                                "-lm"]]
    command = " && ".join(" ".join(c) for c in cmds)
    for cmd in cmds:
        try:
            run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired) as exc:
            return CReference(None, f"{cc} failed to run: {exc}", command)
        if run.returncode != 0:
            last = (run.stderr.strip().splitlines() or ["no message"])[-1]
            return CReference(None, f"{cc} could not build it: {last}", command)
    lib = ctypes.CDLL(str(lib_path))
    lib.render.restype = ctypes.c_int64
    i = ctypes.c_int
    fp, dp = ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_double)
    lib.render.argtypes = [i, dp, fp, fp, fp, fp, i, i, dp, i, i, i, fp, i, fp, dp]
    return CReference(lib, "", command)
