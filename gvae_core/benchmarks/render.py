"""Renderer benchmark: forward and forward+backward time against Gaussian count and resolution,
with the error against the float64 reference on sampled pixels, pixel-Gaussian evaluations per
second and peak memory. Each configuration runs in a fresh subprocess (clean peak-memory figures).

`--modes` (`python -m gvae_core.benchmarks.render --modes`): every anti-aliasing mode on the same
scene in the same process, repeats interleaved (classic, mip, matched, classic, ...) so that load
from other work hits all modes alike; the cloud carries both anti-aliasing sizes of the benchmark
camera (a cloud trained at the rendered resolution), and each mode's error is against the
reference in that mode.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import resource
import statistics
import time

import numpy as np
import torch

from ..antialias import with_dilation_3d, with_filter_3d
from ..camera import Camera
from ..cloud import GaussianCloud
from ..rendering import RenderSettings, render
from ..rendering.reference import render_reference

#: (Gaussians, image height, torch threads). The 2-core machine is shared: with other work on it,
#: two OpenMP threads stall on each other, so every size runs on one thread and the headline
#: sizes on two as well.
SIZES_FULL = tuple((n, h, 1) for n in (10_000, 100_000, 1_000_000) for h in (200, 400, 800)) + (
    (100_000, 800, 2), (1_000_000, 800, 2))
SIZES_QUICK = ((10_000, 200, 1), (10_000, 400, 1), (100_000, 400, 1), (100_000, 400, 2))
#: The sizes of the anti-aliasing comparison (the goal: filtered modes <= 10% over classic).
SIZES_MODES = ((100_000, 800, 1), (1_000_000, 800, 1))
MODES = ("classic", "mip", "matched")


def benchmark_scene(n: int, seed: int = 0):
    """A surface-like random scene: 70% of the Gaussians on a unit sphere, 30% on a ground plane
    that fills the frame behind it; flat, randomly oriented, sized so that their area covers the
    surfaces about twice (about 2 px wide at 800 px for 100k), SH degree 3, mixed opacities."""
    rng = np.random.default_rng(seed)
    n_sphere = int(0.7 * n)
    d = rng.normal(size=(n_sphere, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    plane = np.concatenate([rng.uniform(-2.5, 2.5, (n - n_sphere, 2)), np.full((n - n_sphere, 1), -1.0)], 1)
    means = np.concatenate([d, plane], 0)
    area = 4 * math.pi + 25.0
    sigma = math.sqrt(2.0 * area / n / math.pi)
    log_s = np.log(sigma) + rng.normal(0, 0.3, (n, 3))
    log_s[:, 2] -= 1.5  # flat
    return GaussianCloud(
        means=means.astype(np.float32), scales=log_s.astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.normal(1.0, 1.5, n).astype(np.float32),
        sh_dc=rng.normal(0, 0.8, (n, 3)).astype(np.float32),
        sh_rest=rng.normal(0, 0.15, (n, 15, 3)).astype(np.float32))


def benchmark_camera(height: int):
    return Camera.look_at((2.6, 1.2, 1.3), (0.0, 0.0, -0.2), width=height, height=height, fov_x=math.radians(50.0))


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _one(n: int, height: int, threads: int, repeats: int, samples: int, queue) -> None:
    torch.set_num_threads(threads)

    cloud = benchmark_scene(n)
    cam = benchmark_camera(height)
    tc = cloud.to_torch()
    base = _current_rss_mb()
    fwd, fwd_cpu = [], []
    with torch.no_grad():
        for _ in range(repeats):
            t, c = time.perf_counter(), time.process_time()
            out = render(tc, cam, background=(0.2, 0.3, 0.4))
            fwd.append(time.perf_counter() - t)
            fwd_cpu.append(time.process_time() - c)
    peak_fwd = _rss_mb() - base
    evals = out.num_evaluations
    image = out.image.numpy()
    coverage = float((out.alpha > 0.5).float().mean())
    params = [getattr(tc, f).requires_grad_() for f in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")]
    weights = torch.rand(height, height, 3, generator=torch.Generator().manual_seed(0))
    both, both_cpu = [], []
    for _ in range(repeats):
        for p in params:
            p.grad = None
        t, c = time.perf_counter(), time.process_time()
        out = render(tc, cam, background=(0.2, 0.3, 0.4))
        (out.image * weights).sum().backward()
        both.append(time.perf_counter() - t)
        both_cpu.append(time.process_time() - c)
    peak_both = _rss_mb() - base
    finite = all(bool(torch.isfinite(p.grad).all()) for p in params)
    rng = np.random.default_rng(1)
    pix = np.stack([rng.integers(0, height, samples), rng.integers(0, height, samples)], 1)
    ref, _, _ = render_reference(cloud, cam, background=(0.2, 0.3, 0.4), pixels=pix)
    err = np.abs(image[pix[:, 0], pix[:, 1]] - ref)
    queue.put(dict(n=n, height=height, fwd=statistics.median(fwd), both=statistics.median(both),
                   fwd_cpu=statistics.median(fwd_cpu), both_cpu=statistics.median(both_cpu),
                   evals=evals, pairs=out.num_pairs, coverage=coverage, err_max=float(err.max()),
                   err_frac=float((err > 1e-4).mean()), peak_fwd=peak_fwd, peak_both=peak_both,
                   finite=finite, threads=torch.get_num_threads()))


def _modes(n: int, height: int, threads: int, repeats: int, samples: int, queue) -> None:
    """Every mode of MODES on one scene, repeats interleaved; one result per mode."""
    torch.set_num_threads(threads)
    cam = benchmark_camera(height)
    cloud = with_dilation_3d(with_filter_3d(benchmark_scene(n), [cam]), [cam])
    tc = cloud.to_torch()
    names = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
    params = [getattr(tc, f).requires_grad_() for f in names]
    weights = torch.rand(height, height, 3, generator=torch.Generator().manual_seed(0))
    times = {m: {"fwd": [], "both": [], "fwd_cpu": [], "both_cpu": []} for m in MODES}
    images, info = {}, {}
    for _ in range(repeats):
        for mode in MODES:
            settings = RenderSettings(antialias=mode)
            with torch.no_grad():
                t, c = time.perf_counter(), time.process_time()
                out = render(tc, cam, background=(0.2, 0.3, 0.4), settings=settings)
                times[mode]["fwd"].append(time.perf_counter() - t)
                times[mode]["fwd_cpu"].append(time.process_time() - c)
            images[mode] = out.image.numpy()
            info[mode] = dict(pairs=out.num_pairs, evals=out.num_evaluations,
                              coverage=float((out.alpha > 0.5).float().mean()))
            for p in params:
                p.grad = None
            t, c = time.perf_counter(), time.process_time()
            out = render(tc, cam, background=(0.2, 0.3, 0.4), settings=settings)
            (out.image * weights).sum().backward()
            times[mode]["both"].append(time.perf_counter() - t)
            times[mode]["both_cpu"].append(time.process_time() - c)
            info[mode]["finite"] = all(bool(torch.isfinite(p.grad).all()) for p in params)
    rng = np.random.default_rng(1)
    pix = np.stack([rng.integers(0, height, samples), rng.integers(0, height, samples)], 1)
    rows = []
    for mode in MODES:
        ref, _, _ = render_reference(cloud, cam, background=(0.2, 0.3, 0.4), pixels=pix, antialias=mode)
        err = np.abs(images[mode][pix[:, 0], pix[:, 1]] - ref)
        rows.append(dict(mode=mode, n=n, height=height, threads=threads, err_max=float(err.max()),
                         **{k: statistics.median(v) for k, v in times[mode].items()}, **info[mode]))
    queue.put(rows)


def run_modes(repeats: int = 5) -> None:
    """The anti-aliasing comparison (SIZES_MODES, one fresh process per size)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    print("anti-aliasing modes on the same scene and camera, repeats interleaved; times are medians of "
          f"{repeats}, wall-clock and process CPU; ratio = the mode's median / classic's; err = |fast - float64 "
          "reference in the same mode| on sampled pixels; load = 1-min load average at the start of the row")
    print("| Gaussians | image | threads | mode | fwd s | fwd+bwd s | fwd CPU s | fwd+bwd CPU s | fwd ratio | "
          "fwd+bwd ratio | CPU ratios | tile pairs | alpha>0.5 | max err | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ctx = mp.get_context("spawn")
    for n, h, threads in SIZES_MODES:
        queue = ctx.Queue()
        load = os.getloadavg()[0]
        proc = ctx.Process(target=_modes, args=(n, h, threads, repeats, 64 if n >= 1_000_000 else 200, queue))
        proc.start()
        rows = queue.get()
        proc.join()
        base = rows[0]
        for r in rows:
            print(f"| {n:,} | {h}x{h} | {threads} | {r['mode']} | {r['fwd']:.3f} | {r['both']:.3f} | "
                  f"{r['fwd_cpu']:.3f} | {r['both_cpu']:.3f} | {r['fwd'] / base['fwd']:.3f} | "
                  f"{r['both'] / base['both']:.3f} | {r['fwd_cpu'] / base['fwd_cpu']:.3f} / "
                  f"{r['both_cpu'] / base['both_cpu']:.3f} | {r['pairs']:,} | {r['coverage']:.0%} | "
                  f"{r['err_max']:.2g} | {load:.1f} |", flush=True)
            if not r["finite"]:
                print("  WARNING: non-finite gradient")


def run(args) -> None:
    sizes = SIZES_QUICK if getattr(args, "quick", False) else SIZES_FULL
    # Idle OpenMP threads must yield, not spin: on a shared 2-core machine spinning threads
    # stall each other (20x slower). Children inherit this before they import torch.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    print(f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}; each row in a fresh process; times are "
          "medians, wall-clock and process CPU; evals = pixel-Gaussian alpha evaluations of one "
          "forward pass; err = |fast - float64 reference| on sampled pixels; load = 1-min load average")
    ctx = mp.get_context("spawn")
    print("| Gaussians | image | threads | fwd s | fwd+bwd s | fwd CPU s | fwd+bwd CPU s | tile pairs | evals | "
          "evals/s (fwd) | alpha>0.5 | max err (sampled px) | err>1e-4 | peak MB fwd | peak MB fwd+bwd | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n, h, threads in sizes:
        repeats = 3 if n * h < 400_000_000 else 2
        samples = 64 if n >= 1_000_000 else 200
        queue = ctx.Queue()
        load = os.getloadavg()[0]
        proc = ctx.Process(target=_one, args=(n, h, threads, repeats, samples, queue))
        proc.start()
        r = queue.get()
        proc.join()
        print(f"| {n:,} | {h}x{h} | {threads} | {r['fwd']:.3f} | {r['both']:.3f} | {r['fwd_cpu']:.3f} | "
              f"{r['both_cpu']:.3f} | {r['pairs']:,} | "
              f"{r['evals']:.3g} | {r['evals'] / r['fwd']:.3g} | {r['coverage']:.0%} | {r['err_max']:.2g} | "
              f"{r['err_frac']:.2%} | {r['peak_fwd']:.0f} | {r['peak_both']:.0f} | {load:.1f} |", flush=True)
        if not r["finite"]:
            print("  WARNING: non-finite gradient")
    if not getattr(args, "quick", False):
        print()
        run_modes()


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.render")
    parser.add_argument("--quick", action="store_true", help="smaller sizes")
    parser.add_argument("--modes", action="store_true", help="the anti-aliasing comparison only")
    parser.add_argument("--repeats", type=int, default=5, help="--modes: repeats per mode")
    cli = parser.parse_args()
    if cli.modes:
        run_modes(cli.repeats)
    else:
        run(cli)
