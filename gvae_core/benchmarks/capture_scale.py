"""The compiled core at capture scale, each row beside its goal, in one run:
- forward + backward of 100k Gaussians at 800x800 (`kernels.renderer_rows`) against the C
  reference's forward pass of the same run; error: the largest gradient difference from the
  torch path, relative to its largest value; and the compositing's time per pixel-Gaussian pair,
  forward and backward (`pair_costs`);
- the Hessian scores of 1M Gaussians, default views (`kernels.hessian_rows`); error: the largest
  score difference from the torch path, relative;
- `gvae refine` (detail model) and `gvae compact --keep 0.5` of a 1M-Gaussian PLY as whole
  commands, each in a fresh process as a user runs them (start-up, reading and writing
  included), median of three; what each says of its own result beside it.
Torch uses all cores (2 on the CI machine); the load average is printed beside every row."""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from ..examples import example_cloud
from ..ply import write_ply
from ..rendering import compiled
from . import kernels as kernel_rows
from .render import benchmark_camera, benchmark_scene

#: The goals: forward + backward in times the C forward; seconds for the rest.
GOALS = {"fwd_bwd": 4.0, "hessian": 3.0, "refine": 8.0, "compact": 10.0}


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _verdict(value: float, goal: float) -> str:
    return "met" if value <= goal else "**not met**"


#: `python -m gvae_core ARGS` in a child that prints its own peak RSS (bytes) last, on stderr.
_CHILD = ("import resource, runpy, sys\n"
          "sys.argv = ['gvae'] + sys.argv[1:]\n"
          "try:\n"
          "    runpy.run_module('gvae_core', run_name='__main__')\n"
          "finally:\n"
          "    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == 'darwin' else 1024)\n"
          "    try:  # this process's own high-water mark (ru_maxrss keeps the forking parent's)\n"
          "        status = open('/proc/self/status').read().split('VmHWM:')[1].split()\n"
          "        peak = int(status[0]) * 1024\n"
          "    except (OSError, IndexError, ValueError):\n"
          "        pass\n"
          "    print(f'peak-rss {peak}', file=sys.stderr)\n")


def command_row(args: list[str], repeats: int = 3) -> dict:
    """Seconds (median of `repeats` fresh processes) of `python -m gvae_core ARGS` (what `gvae` runs),
    the last line it printed, the load before and after and its largest peak RSS."""
    seconds, cpu, peaks, load0, said = [], [], [], _load(), ""
    for _ in range(repeats):
        t, c = time.perf_counter(), _children_cpu()
        done = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True, text=True)
        seconds.append(time.perf_counter() - t)
        cpu.append(_children_cpu() - c)
        errors = done.stderr.strip().splitlines()
        if done.returncode != 0:
            return {"failed": (errors[-2:-1] or [str(done.returncode)])[-1]}
        peaks.append(int(errors[-1].split()[-1]))
        lines = [line for line in done.stdout.strip().splitlines() if line.strip()]
        said = lines[-1] if lines else ""
    return {"seconds": statistics.median(seconds), "all": seconds, "cpu": statistics.median(cpu), "said": said,
            "load": f"{load0} -> {_load()}", "peak": max(peaks)}


def _children_cpu() -> float:
    """CPU seconds (user + system) of the finished child processes so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def pair_costs(n: int = 100_000, height: int = 800, repeats: int = 7) -> dict:
    """Nanoseconds per evaluated pixel-Gaussian pair of the compiled compositing, forward and backward
    (medians; all threads), of `benchmark_scene(n)` seen by `benchmark_camera(height)`."""
    cloud, cam = benchmark_scene(n), benchmark_camera(height)
    tc = cloud.to_torch()
    proj, table = compiled.project(tc.means, tc.scales, tc.quats, tc.opacities, tc.sh_dc, tc.sh_rest, cam, 3)
    binning = compiled.bin_gaussians(table, proj.footprint, proj.visible, cam.width, cam.height, 8)
    grad = None
    forward, backward = [], []
    for _ in range(repeats):
        t = time.perf_counter()
        acc = compiled.composite_forward(table, binning)
        forward.append(time.perf_counter() - t)
        grad = torch.rand_like(acc) if grad is None else grad
        t = time.perf_counter()
        compiled.composite_backward(table, binning, acc, grad)
        backward.append(time.perf_counter() - t)
    evals = binning.evaluations
    return {"forward": 1e9 * statistics.median(forward) / evals, "backward": 1e9 * statistics.median(backward) / evals,
            "evaluations": evals, "load": _load()}


def run(args) -> None:
    if not kernel_rows.ready():
        return
    quick = getattr(args, "quick", False)
    n = 100_000 if quick else 1_000_000
    threads = torch.get_num_threads()
    compiled.compile_kernels()
    print(f"torch threads {threads}; load average (1, 5, 15 min) at start: {_load()}")
    print("\n| row | goal | this run | verdict | error of the same run | load |")
    print("|---|---|---|---|---|---|")
    commands = getattr(args, "commands", None)
    if not commands:
        _core_rows(n, threads, quick)
    _command_rows(n, quick, commands or ("refine", "compact"))


def _core_rows(n: int, threads: int, quick: bool) -> None:
    """The renderer's, the compositing's and the Hessian's rows."""
    rows, cref = kernel_rows.renderer_rows(((100_000, 800),), threads_list=(threads,), repeats=3 if quick else 7,
                                           torch_repeats=1)
    r = rows[0]
    if cref.lib is None:
        print(f"| forward + backward, 100k @ 800x800 | <= {GOALS['fwd_bwd']:.0f}x the C forward | "
              f"{1000 * r['both']:.0f} ms (C reference skipped: {cref.reason}) | - | grad rel. diff "
              f"{r['grad_err']:.1g} | {r['load']} |", flush=True)
    else:
        ratio = r["both"] / r["c"]
        print(f"| forward + backward, 100k @ 800x800 | <= {GOALS['fwd_bwd']:.0f}x the C forward | "
              f"{1000 * r['both']:.0f} ms = **{ratio:.2f}x** the C forward's {1000 * r['c']:.0f} ms (compiled forward "
              f"{1000 * r['fwd']:.0f} ms) | {_verdict(ratio, GOALS['fwd_bwd'])} | grad rel. diff {r['grad_err']:.1g}, "
              f"image {r['err']:.1g} vs float64 | {r['load']} |", flush=True)

    p = pair_costs(repeats=3 if quick else 7)
    print(f"| compositing per pixel-Gaussian pair, 100k @ 800x800 | backward at the forward's cost | forward "
          f"{p['forward']:.2f} ns, backward **{p['backward']:.2f} ns** ({p['backward'] / p['forward']:.2f}x; "
          f"{p['evaluations']:,} pairs) | - | (the same kernels as the row above) | {p['load']} |", flush=True)

    h = kernel_rows.hessian_rows((n,), repeats=1 if quick else 3, with_torch=True)[0]
    print(f"| Hessian scores, {n:,}, default views | <= {GOALS['hessian']:.0f} s | **{h['total']:.2f} s** (process "
          f"CPU {h['cpu']:.1f} s) | {_verdict(h['total'], GOALS['hessian'])} | score rel. diff {h.get('diff', 0):.1g} "
          f"vs torch | {h['load']} |", flush=True)


def _command_rows(n: int, quick: bool, names) -> None:
    """`gvae refine` and `gvae compact --keep 0.5` of an n-Gaussian PLY (those of `names`) as whole commands."""
    with tempfile.TemporaryDirectory(prefix="gvae-capture-scale-") as tmp:
        src = Path(tmp) / f"cloud_{n}.ply"
        write_ply(example_cloud(n, seed=1), src)
        for name, cmd in (("refine", ["refine", str(src), str(Path(tmp) / "refined.ply")]),
                          ("compact", ["compact", str(src), str(Path(tmp) / "compact.ply"), "--keep", "0.5"])):
            if name not in names:
                continue
            c = command_row(cmd, repeats=1 if quick else 3)
            c["said"] = c.get("said", "").replace(f"{tmp}/", "")  # no machine paths in the table
            label = f"`gvae {' '.join(cmd[:1] + cmd[3:])}` {n:,}, whole command"
            if "failed" in c:
                print(f"| {label} | <= {GOALS[name]:.0f} s | failed: {c['failed']} | - | - | {_load()} |", flush=True)
                continue
            runs = ", ".join(f"{s:.1f}" for s in c["all"])
            print(f"| {label} | <= {GOALS[name]:.0f} s | **{c['seconds']:.1f} s** ({runs}; CPU {c['cpu']:.1f} s; peak "
                  f"{c['peak'] / 2 ** 30:.2f} GiB) | {_verdict(c['seconds'], GOALS[name])} | it said: {c['said']} | "
                  f"{c['load']} |", flush=True)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.capture_scale")
    parser.add_argument("--quick", action="store_true", help="100k Gaussians for every row")
    parser.add_argument("--commands", nargs="+", choices=("refine", "compact"), default=None,
                        help="only these whole-command rows (default: every row)")
    run(parser.parse_args())
