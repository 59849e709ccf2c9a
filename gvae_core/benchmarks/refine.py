"""Refinement speed and quality: ms per model step against Gaussian count and budget, Hessian
scoring timed on its own, model sizes, and the model's reconstruction error on held-out
transitions (what the refinement quality rests on)."""

from __future__ import annotations

import math
import os
import statistics
import time

import numpy as np
import torch

from ..examples import example_cloud
from ..experiment import PROTOCOLS, runs_dir
from ..hessian import hessian_scores
from ..refinement import refine
from ..vae import GaussianVAE, copy_parent_baseline, default_model_dir, evaluate, load_runs, synthetic_transitions


def _load_model():
    directory = default_model_dir()
    if (directory / "config.json").is_file():
        return GaussianVAE.load(directory), str(directory)
    return GaussianVAE.create(seed=0), "untrained (no bundled model)"


def _heldout_transitions(model):
    """Transitions of the model's held-out scenes from the cached `full` experiment runs (what
    `make train-model` evaluated), when they are on disk; else synthetic ones."""
    p = PROTOCOLS["full"]
    folder = runs_dir() / f"{p.name}-{p.run_key()}"
    runs = [folder / s for s in model.meta.get("held_out_scenes", []) if (folder / s / "lineage.npz").is_file()]
    if runs:
        return load_runs(runs, model.slots), ", ".join(f"{r.name} (full runs)" for r in runs)
    return synthetic_transitions(512, 4, seed=123), "synthetic lineages (seed 123)"


def run(args) -> None:
    quick = bool(getattr(args, "quick", False))
    model, source = _load_model()
    sizes = model.sizes()
    print(f"model: {source}; torch threads {torch.get_num_threads()}, load {os.getloadavg()[0]:.2f}")
    # The paper's model table: size, training time, inference time (here: 10k three-node lineages,
    # one densifying step, median of 5; the paper's figures are per scene on a GPU).

    lineages = synthetic_transitions(10_000, 3, seed=7)[1].subset(np.arange(10_000))  # two-node lineages
    flags = torch.ones(len(lineages), dtype=torch.bool)
    trained = model.meta.get("seconds")
    print("\n| model | parameters | size (MB, float32) | training (both models together) | inference, 10k lineages "
          "| config |")
    print("|---|---:|---:|---|---:|---|")
    for name, vae, nodes in (("geometry", model.geometry, lineages.history_geometry),
                             ("appearance", model.appearance, lineages.history_appearance)):
        c = vae.config
        params = sum(p.numel() for p in vae.parameters())
        x = torch.from_numpy(nodes)
        times = []
        with torch.no_grad():
            for _ in range(5):
                t0 = time.perf_counter()
                vae(x, flags, sample=False)
                times.append(time.perf_counter() - t0)
        print(f"| {name} | {params} | {sizes[name] / 1e6:.2f} | "
              f"{f'{trained / 60:.1f} min' if trained else '?'} ({model.meta.get('steps', '?')} steps) | "
              f"{statistics.median(times) * 1e3:.1f} ms | d_model {c.d_model}, {c.layers} layers, {c.heads} heads, "
              f"latent {c.latent}, {c.slots} slots, flow {c.flow_layers} couplings |")

    t0 = time.perf_counter()
    data, where = _heldout_transitions(model)
    ev = evaluate(model, data)
    print(f"\nreconstruction on held-out transitions ({where}; {sum(len(d) for d in data)} lineages, "
          f"{time.perf_counter() - t0:.1f} s):")
    print(f"  child-centre RMSE {ev['position_rmse']:.3f} parent sizes, existence accuracy {ev['exist_accuracy']:.3f}, "
          f"child-count error {ev['count_error']:.3f}, appearance MSE {ev['mse']:.4f}, "
          f"log-scale/rotation error {ev['state']:.3f}, Chamfer {ev['chamfer']:.3f}")
    base = copy_parent_baseline(data)
    print(f"  yardstick 'copy the parent': child-centre RMSE {base['position_rmse']:.3f}, "
          f"child-count error {base['count_error']:.3f}, appearance MSE {base['mse']:.4f}")

    counts = [10_000] if quick else [10_000, 100_000]
    budgets = [0.1, "all"] if not quick else [0.1]
    repeats = 3 if quick else 5
    print("\n| Gaussians | budget | selected | added | model ms/step (median) | refine ms excl. Hessian "
          "(median; first call) | process CPU ms | error: non-finite out / changed unselected rows |")
    print("|---:|---|---:|---:|---:|---:|---:|---|")
    clouds = {}
    for n in counts:
        cloud = example_cloud(n, seed=1)
        clouds[n] = cloud
        scores = np.random.default_rng(0).gamma(1.0, 1.0, n).astype(np.float32)
        for budget in budgets:
            model_ms, rest_ms, cpu_ms, r = [], [], [], None
            for rep in range(repeats + 1):  # the first call (memory for a new size) is reported apart
                c0 = time.process_time()
                r = refine(cloud, steps=1, budget=budget, model=model, scores=scores, seed=rep)
                cpu_ms.append((time.process_time() - c0) * 1e3)
                model_ms.append(r.timings["model"] * 1e3)
                rest_ms.append((r.timings["total"] - r.timings["hessian"] - r.timings["load"]) * 1e3)
            nonfinite = len(r.cloud.validate().nonfinite_rows)
            unsel = np.setdiff1d(np.arange(n), r.selected)
            changed = int((r.cloud.means[unsel] != cloud.means[unsel]).any(1).sum())
            print(f"| {n} | {budget} | {len(r.selected)} | {len(r.added)} | {statistics.median(model_ms[1:]):.1f} "
                  f"| {statistics.median(rest_ms[1:]):.1f}; {rest_ms[0]:.1f} | {statistics.median(cpu_ms[1:]):.1f} "
                  f"| {nonfinite} / {changed} |")

    print("\n| Gaussians | views x probes | resolution | Hessian ms | process CPU ms | error: non-finite / "
          "negative scores | top-10% share of score mass |")
    print("|---:|---|---:|---:|---:|---|---:|")
    for n in counts:
        cloud = clouds[n]
        views, probes, res = (2, 2, 64) if quick or n > 20_000 else (4, 4, 96)
        times, cpu, s = [], [], None
        for rep in range(1 if n > 20_000 else 2):
            t0, c0 = time.perf_counter(), time.process_time()
            s = hessian_scores(cloud, views=views, probes=probes, resolution=res, seed=rep).numpy()
            times.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        top = np.sort(s)[::-1][: max(1, n // 10)].sum() / max(s.sum(), 1e-30)
        print(f"| {n} | {views} x {probes} | {res} | {statistics.median(times):.0f} | {statistics.median(cpu):.0f} "
              f"| {int((~np.isfinite(s)).sum())} / {int((s < 0).sum())} | {top:.2f} |")
    if math.isfinite(os.getloadavg()[0]):
        print(f"(load average at the end: {os.getloadavg()[0]:.2f})")
