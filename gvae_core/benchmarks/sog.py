"""SOG (PlayCanvas) write and read: gvae_core beside splat-transform on a trained cloud, and at 1M.

1. The trained chair of examples/trained (SH 3), written by `write_sog` and by
   splat-transform 3.7.0 (its CPU path, `-g cpu`, from the npm cache of
   `benchmarks.splat_transform`; left out, saying why, without node and npm): the RMS and largest
   error of each attribute against the cloud (rows matched by their values: both reorder), time and
   size. Each file is read back with `read_splat_file`.
2. A random 1M-Gaussian SH-3 cloud (`examples.random_cloud`, as the `ply` benchmark): `write_sog`
   (palette of 65536 by k-means; wall and CPU time, both threads of the BLAS), `read_splat_file` of
   the .sog against `read_ply` of the same cloud (median of the repeats), the errors and the size.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..cloud import GaussianCloud
from ..conventions import sigmoid
from ..examples import random_cloud
from ..formats import read_splat_file, write_sog
from ..formats.sog import morton_order
from ..ply import read_ply, write_ply
from ..quaternions import normalize
from . import splat_transform

CHAIR = Path(__file__).resolve().parents[2] / "examples" / "trained" / "scene.ply"


def errors(cloud: GaussianCloud, back: GaussianCloud) -> dict[str, tuple[float, float]]:
    """(RMS, largest) error of each attribute of `back` against `cloud` (rows in the same order):
    quaternion components after normalising and aligning signs, opacity after the sigmoid."""
    q, r = normalize(cloud.quats.astype(np.float64)), normalize(back.quats.astype(np.float64))
    o, p = (sigmoid(c.opacities.astype(np.float64)) for c in (cloud, back))
    same_sign = (np.abs(q - r).max(1) <= np.abs(q + r).max(1))[:, None]
    parts = {"position": np.abs(back.means - cloud.means),
             "rotation": np.where(same_sign, np.abs(q - r), np.abs(q + r)),
             "log-scale": np.abs(back.scales - cloud.scales),
             "opacity": np.abs(p - o),
             "f_dc": np.abs(back.sh_dc - cloud.sh_dc), "f_rest": np.abs(back.sh_rest - cloud.sh_rest)}
    return {k: (float(np.sqrt(np.mean(v.astype(np.float64) ** 2))), float(v.max(initial=0))) for k, v in parts.items()}


def matched(cloud: GaussianCloud, back: GaussianCloud) -> GaussianCloud:
    """`cloud`'s rows in `back`'s order, matched by position, scales and colour (one to one)."""
    def features(c):
        return np.hstack([c.means / 2e-5, c.scales / 0.02, c.sh_dc / 0.02])

    _, idx = cKDTree(features(cloud)).query(features(back))
    if len(np.unique(idx)) != len(cloud):
        raise RuntimeError("the rows of the file do not match the cloud's one to one")
    return cloud.select(idx)


def _row(name: str, seconds: float, path: Path, errs: dict) -> str:
    cells = " | ".join(f"{rms:.2g} / {top:.2g}" for rms, top in errs.values())
    return f"| {name:<30} | {seconds:7.2f} | {path.stat().st_size / 1024:8.0f} | {cells} |"


def run(args) -> None:
    quick = getattr(args, "quick", False)
    header = "| writer (trained chair, 11,130 SH-3) | write (s) | KiB | " + " | ".join(
        f"{k} RMS / max" for k in ("position", "rotation", "log-scale", "opacity", "f_dc", "f_rest")) + " |"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        chair = read_ply(CHAIR).replace(extra={})
        rows = []
        t = time.perf_counter()
        ours = write_sog(chair, tmp / "ours.sog")
        t_ours = time.perf_counter() - t
        rows.append(_row("gvae_core write_sog", t_ours, ours,
                         errors(chair.select(morton_order(chair.means)), read_splat_file(ours))))
        try:
            cmd = splat_transform.command()
            src = write_ply(chair, tmp / "chair.ply")
            t = time.perf_counter()
            theirs = splat_transform.convert(cmd, src, tmp / "theirs.sog")
            t_theirs = time.perf_counter() - t
            back = read_splat_file(theirs)
            rows.append(_row(f"splat-transform {splat_transform.VERSION} (CPU)", t_theirs, theirs,
                             errors(matched(chair, back), back)))
        except (splat_transform.Unavailable, RuntimeError) as exc:
            rows.append(f"(splat-transform left out: {exc})")
        print(header)
        print("|" + "---|" * (3 + 6))
        print("\n".join(rows))

        n = 100_000 if quick else 1_000_000
        repeats = 3
        cloud = random_cloud(n)
        ply = write_ply(cloud, tmp / "big.ply")
        t, cpu = time.perf_counter(), time.process_time()
        sog = write_sog(cloud, tmp / "big.sog")
        t_write, cpu_write = time.perf_counter() - t, time.process_time() - cpu
        read_times, back = [], None
        ply_times = []
        for _ in range(repeats):
            t = time.perf_counter()
            back = read_splat_file(sog)
            read_times.append(time.perf_counter() - t)
            t = time.perf_counter()
            read_ply(ply)
            ply_times.append(time.perf_counter() - t)
        t_read, t_ply = statistics.median(read_times), statistics.median(ply_times)
        errs = errors(cloud.select(morton_order(cloud.means)), back)
        mib = sog.stat().st_size / 2 ** 20, ply.stat().st_size / 2 ** 20
    print(f"\n{n} random SH-3 Gaussians: write_sog {t_write:.1f} s ({cpu_write:.1f} s of CPU), {mib[0]:.1f} MiB "
          f"(PLY {mib[1]:.0f} MiB); read_splat_file {t_read:.2f} s = "
          f"{t_read / t_ply:.2f} x read_ply ({t_ply:.2f} s), median of {repeats}")
    print("errors (RMS / max): " + ", ".join(f"{k} {rms:.2g} / {top:.2g}" for k, (rms, top) in errs.items())
          + f" (f_rest RMS of the cloud itself: {float(np.sqrt(np.mean(cloud.sh_rest ** 2))):.2g})")
