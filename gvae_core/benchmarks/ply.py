"""PLY read and write of a 1M-Gaussian SH-3 cloud, beside a raw `np.fromfile` of the same file; then
the same cloud as .spz (versions 3 and 4), .splat and compressed PLY, read against read_ply.

Every row: median time of the repeats and the max abs difference between the parameters it got
and the cloud that was written (raw read: the float32 columns viewed straight from the bytes; the
lossy formats: the largest error of each parameter, their quantisation)."""

from __future__ import annotations

import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from ..cloud import GaussianCloud
from ..conventions import sigmoid
from ..examples import random_cloud
from ..formats import read_splat_file, write_compressed_ply, write_splat, write_spz
from ..ply import PlyError, read_ply, write_ply
from ..quaternions import normalize


def max_abs_diff(a: GaussianCloud, b: GaussianCloud) -> float:
    return max(float(np.max(np.abs(x - y), initial=0.0))
               for x, y in zip(a.arrays().values(), b.arrays().values()))


def _median_time(fn, repeats: int):
    times, result = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), result


def run(args) -> None:
    n = 100_000 if getattr(args, "quick", False) else 1_000_000
    repeats = 3 if getattr(args, "quick", False) else 5
    cloud = random_cloud(n)
    cloud.sh_dc[:] = np.clip(cloud.sh_dc, -1.7, 1.7)  # colours inside every format's range
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.ply"
        write_times = []
        for _ in range(repeats):  # a new file each time: replacing one also pays for freeing it
            path.unlink(missing_ok=True)
            t = time.perf_counter()
            write_ply(cloud, path)
            write_times.append(time.perf_counter() - t)
        t_write = statistics.median(write_times)
        size = path.stat().st_size
        raw_bytes = np.fromfile(path, np.uint8)
        offset = raw_bytes.tobytes().find(b"end_header\n") + len(b"end_header\n")
        t_raw, raw = _median_time(lambda: np.fromfile(path, np.uint8), repeats)
        table = raw[offset:].view("<f4").reshape(n, 62)
        raw_err = max(float(np.abs(table[:, 0:3] - cloud.means).max()),
                      float(np.abs(table[:, 58:62] - cloud.quats).max()))
        t_read, back = _median_time(lambda: read_ply(path), repeats)
        err = max_abs_diff(cloud, back)
        formats = _formats(cloud, Path(tmp), repeats)

    print(f"{n} Gaussians, SH degree 3, {size / 2**20:.0f} MiB file, median of {repeats}")
    print(f"| {'operation':<28} | {'time (s)':>9} | {'x raw read':>10} | {'max abs error':>13} |")
    print(f"|{'-' * 30}|{'-' * 10}:|{'-' * 11}:|{'-' * 14}:|")
    for name, t, e in (("np.fromfile (raw bytes)", t_raw, raw_err),
                       ("read_ply", t_read, err), ("write_ply (atomic, new file)", t_write, err)):
        print(f"| {name:<28} | {t:9.3f} | {t / t_raw:10.2f} | {e:13.3g} |")

    print(f"\n| {'format (same cloud)':<44} | {'read (s)':>8} | {'x read_ply':>10} | {'write (s)':>9} | "
          f"{'MiB':>5} | largest error of each parameter |")
    print(f"|{'-' * 46}|{'-' * 9}:|{'-' * 11}:|{'-' * 10}:|{'-' * 6}:|---|")
    for name, t_r, t_w, mib, errors in formats:
        print(f"| {name:<44} | {t_r:8.3f} | {t_read and t_r / t_read:10.2f} | {t_w:9.2f} | {mib:5.0f} | {errors} |")


def _errors(cloud: GaussianCloud, back: GaussianCloud) -> str:
    """Largest error of each parameter: quaternions normalised and sign-aligned, opacity after the sigmoid."""
    q, r = normalize(cloud.quats.astype(np.float64)), normalize(back.quats.astype(np.float64))
    o, p = (sigmoid(c.opacities.astype(np.float64)) for c in (cloud, back))
    parts = {"means": np.abs(back.means - cloud.means), "log-scales": np.abs(back.scales - cloud.scales),
             "quats": np.minimum(np.abs(q - r).max(1), np.abs(q + r).max(1)),
             "opacity": np.abs(p - o), "f_dc": np.abs(back.sh_dc - cloud.sh_dc)}
    if back.sh_degree:
        parts["f_rest"] = np.abs(back.sh_rest - cloud.sh_rest)
    return ", ".join(f"{k} {float(v.max(initial=0)):.2g}" for k, v in parts.items())


def _formats(cloud: GaussianCloud, folder: Path, repeats: int) -> list:
    """(name, median read time, write time, MiB, errors) of each splat format for `cloud`."""
    rows = []
    for name, file, write in ((".spz v3 (gzip)", "b.spz", write_spz),
                              (".spz v4 (zstd)", "b4.spz", lambda c, p: write_spz(c, p, version=4)),
                              (".splat (no SH)", "b.splat", write_splat),
                              ("compressed PLY (SuperSplat)", "b.compressed.ply", write_compressed_ply)):
        path = folder / file
        try:
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # .splat drops the SH: it says so
                write(cloud, path)
            t_write = time.perf_counter() - t
        except PlyError as exc:  # .spz v4 without zstandard
            print(f"({name}: {exc})")
            continue
        t_read, back = _median_time(lambda p=path: read_splat_file(p), repeats)
        rows.append((f"read_splat_file {name}", t_read, t_write, path.stat().st_size / 2 ** 20, _errors(cloud, back)))
    return rows
