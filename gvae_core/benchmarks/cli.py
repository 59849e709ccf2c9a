"""Start-up of the `gvae` command: `gvae --help` and `gvae info` of a 150k-Gaussian compressed PLY (the
size of PlayCanvas's biker scan), beside splat-transform reading the same file and writing a PLY, and
beside a bare `python -c pass` and `import numpy` (the floor). Each command runs 7 times (3 with
`--quick`) in a fresh process, after one untimed run; wall and CPU seconds (user + system of the
process) are medians, with the load average before and after. The file: `example_cloud(152_746)`
(SH 3) written as a PLY and turned into a compressed PLY by splat-transform 3.7.0 (by
`write_compressed_ply` where node is missing).

`python -m gvae_core.benchmarks cli` (`--quick`: 3 repeats).
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..examples import example_cloud
from ..formats import write_compressed_ply
from ..ply import write_ply
from .splat_transform import Unavailable, command, convert

#: Gaussians of the benchmark's file (PlayCanvas's biker scan has 152,746).
COUNT = 152_746


def timed(argv: list[str], repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of `argv`, each run in a fresh process, after one run that is not
    timed (Python writes its bytecode then, as it does on a user's machine: PYTHONDONTWRITEBYTECODE is
    dropped)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    walls, cpus = [], []
    for k in range(repeats + 1):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300, env=env)
        if not k:
            continue
        walls.append(time.perf_counter() - t0)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return statistics.median(walls), statistics.median(cpus)


def run(args) -> None:
    repeats = 3 if getattr(args, "quick", False) else 7
    gvae = [sys.executable, "-m", "gvae_core"]
    with tempfile.TemporaryDirectory() as tmp:
        ply = write_ply(example_cloud(COUNT, seed=0), Path(tmp) / "scene.ply")
        packed = Path(tmp) / "scene.compressed.ply"
        try:
            st = command()
            convert(st, ply, packed)
            made = "splat-transform 3.7.0"
        except (Unavailable, RuntimeError) as exc:
            st = None
            write_compressed_ply(example_cloud(COUNT, seed=0), packed)
            made = f"write_compressed_ply (splat-transform unavailable: {exc})"
        rows = [("python -c pass", [sys.executable, "-c", "pass"]),
                ("python -c 'import numpy'", [sys.executable, "-c", "import numpy"]),
                ("gvae --help", [*gvae, "--help"]),
                ("gvae info FILE", [*gvae, "info", str(packed)])]
        if st is not None:
            rows.append(("splat-transform FILE out.ply", [*st, "-w", "-q", "-g", "cpu", str(packed),
                                                          str(Path(tmp) / "out.ply")]))
        print(f"{COUNT:,} Gaussians (SH 3), compressed PLY of {packed.stat().st_size / 1e6:.1f} MB made by {made}; "
              f"medians of {repeats} runs, each a fresh process; {os.cpu_count()} cores\n")
        print("| command | wall s | CPU s | load before-after |\n|---|---:|---:|---|")
        for label, argv in rows:
            load0 = os.getloadavg()[0]
            wall, cpu = timed(argv, repeats)
            print(f"| `{label}` | {wall:.3f} | {cpu:.3f} | {load0:.1f}-{os.getloadavg()[0]:.1f} |", flush=True)
