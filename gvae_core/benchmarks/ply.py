"""PLY read and write of a 1M-Gaussian SH-3 cloud, beside a raw `np.fromfile` of the same file.

Every row: median time of the repeats and the max abs difference between the parameters it got
and the cloud that was written (raw read: the float32 columns viewed straight from the bytes)."""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from ..cloud import GaussianCloud
from ..examples import random_cloud
from ..ply import read_ply, write_ply


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

    print(f"{n} Gaussians, SH degree 3, {size / 2**20:.0f} MiB file, median of {repeats}")
    print(f"| {'operation':<28} | {'time (s)':>9} | {'x raw read':>10} | {'max abs error':>13} |")
    print(f"|{'-' * 30}|{'-' * 10}:|{'-' * 11}:|{'-' * 14}:|")
    for name, t, e in (("np.fromfile (raw bytes)", t_raw, raw_err),
                       ("read_ply", t_read, err), ("write_ply (atomic, new file)", t_write, err)):
        print(f"| {name:<28} | {t:9.3f} | {t / t_raw:10.2f} | {e:13.3g} |")
