"""glTF (KHR_gaussian_splatting) write and read of a 1M-Gaussian SH-3 cloud, beside the PLY's.

The random cloud of the `ply` benchmark (`examples.random_cloud`), written and read as a 3DGS PLY
(`write_ply`, `read_ply`), a .glb and a .gltf with its .bin (`write_gltf`, `read_splat_file`), the
formats taking turns within each repeat so that they share the machine's load alike; a new file
each time. Every row: the median wall time and its ratio to the PLY's (the goal: at most 2x
both ways), the median CPU time of the process and its ratio (steadier than wall time on a shared
machine), the file size and the largest error of each parameter against the cloud written
(quaternions normalised, opacity after the sigmoid).
"""

from __future__ import annotations

import statistics
import tempfile
import time
import warnings
from pathlib import Path

from ..examples import random_cloud
from ..formats import read_splat_file, write_gltf
from ..ply import read_ply, write_ply
from .ply import _errors


def run(args) -> None:
    quick = getattr(args, "quick", False)
    n = 100_000 if quick else 1_000_000
    repeats = 3 if quick else 7
    cloud = random_cloud(n)
    formats = {"PLY": ("bench.ply", write_ply, read_ply), ".glb": ("bench.glb", write_gltf, read_splat_file),
               ".gltf + .bin": ("bench.gltf", write_gltf, read_splat_file)}
    times = {name: {op: [] for op in ("write", "read", "write cpu", "read cpu")} for name in formats}
    sizes, backs = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for name, (file, write, read) in formats.items():
                path = Path(tmp) / file
                for old in (path, path.with_suffix(".bin")):
                    old.unlink(missing_ok=True)
                t, cpu = time.perf_counter(), time.process_time()
                write(cloud, path)
                times[name]["write"].append(time.perf_counter() - t)
                times[name]["write cpu"].append(time.process_time() - cpu)
                t, cpu = time.perf_counter(), time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # (opacities read as fully opaque say so)
                    backs[name] = read(path)
                times[name]["read"].append(time.perf_counter() - t)
                times[name]["read cpu"].append(time.process_time() - cpu)
                sizes[name] = sum(p.stat().st_size for p in (path, path.with_suffix(".bin")) if p.exists())
    med = {name: {op: statistics.median(v) for op, v in t.items()} for name, t in times.items()}
    ply = med["PLY"]
    print(f"{n} Gaussians, SH degree 3, median of {repeats} (formats in turn within each repeat); wall and CPU s")
    print(f"| {'format':<14} | {'write':>6} | {'x PLY':>5} | {'cpu':>6} | {'x PLY':>5} | {'read':>6} | {'x PLY':>5} | "
          f"{'cpu':>6} | {'x PLY':>5} | {'MiB':>4} | largest error of each parameter |")
    print("|" + "|".join(["-" * 16] + ["-" * 7 + ":", "-" * 6 + ":"] * 4 + ["-" * 5 + ":", "---"]) + "|")
    for name in formats:
        m = med[name]
        ops = ("write", "write cpu", "read", "read cpu")
        cells = " | ".join(f"{m[op]:6.3f} | {m[op] / ply[op]:5.2f}" for op in ops)
        print(f"| {name:<14} | {cells} | {sizes[name] / 2 ** 20:4.0f} | {_errors(cloud, backs[name])} |")
