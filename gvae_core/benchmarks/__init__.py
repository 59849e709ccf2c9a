"""Benchmarks behind `make bench` (`python -m gvae_core.benchmarks [NAME ...]`).

Each module listed in `BENCHMARKS` defines `run(args) -> None`, which prints a table in which
every row gives the time and the error of the same run. Timings are medians of repeats; they
are never asserted on (speed goals live here, not in tests).
"""

BENCHMARKS = (
    "cli",
    "ply",
    "sog",
    "gltf",
    "render",
    "kernels",
    "capture_scale",
    "antialias",
    "blender",
    "refine",
    "superres",
    "quality",
    "scenes",
    "train",
    "compact",
)
