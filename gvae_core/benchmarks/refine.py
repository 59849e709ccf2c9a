"""Refinement speed and quality: the detail model (refine's default: its size, ms per refine
against Gaussian count and budget), the lineage VAEs (ms per model step, sizes, reconstruction
error on held-out transitions), the Hessian blocks against their definition, and whole refines at
capture scale with each method (100k to 3M Gaussians: seconds per part, peak memory, selected and
added counts)."""

from __future__ import annotations

import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from ..antialias import with_dilation_3d
from ..camera import Camera
from ..capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS, default_views, load_cameras
from ..detail import DetailModel, default_detail_dir, load_detail
from ..examples import example_cloud
from ..experiment import PROTOCOLS, runs_dir
from ..hessian import hessian_blocks, hessian_blocks_reference, hessian_scores
from ..octaves import octave_fields
from ..ply import read_ply
from ..refinement import DEFAULT_BUDGETS, refine
from ..rendering import RenderSettings
from ..resources import estimate_refine_memory
from ..scenes import cache_dir, scene_key
from ..vae import (GaussianVAE, copy_parent_baseline, default_model_dir, evaluate, load_model, load_runs,
                   synthetic_transitions)


def _load_model():
    directory = default_model_dir()
    if (directory / "config.json").is_file():
        return load_model(directory), str(directory)
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
                # the model step alone (the fidelity check's renders are timed in _capture_scale)
                r = refine(cloud, steps=1, budget=budget, model=model, scores=scores, seed=rep, fidelity=None)
                cpu_ms.append((time.process_time() - c0) * 1e3)
                model_ms.append(r.timings["model"] * 1e3)
                rest_ms.append((r.timings["total"] - r.timings["hessian"] - r.timings["load"]) * 1e3)
            nonfinite = len(r.cloud.validate().nonfinite_rows)
            unsel = np.setdiff1d(np.arange(n), r.selected)
            changed = int((r.cloud.means[unsel] != cloud.means[unsel]).any(1).sum())
            print(f"| {n} | {budget} | {len(r.selected)} | {len(r.added)} | {statistics.median(model_ms[1:]):.1f} "
                  f"| {statistics.median(rest_ms[1:]):.1f}; {rest_ms[0]:.1f} | {statistics.median(cpu_ms[1:]):.1f} "
                  f"| {nonfinite} / {changed} |")

    _exactness()
    if not quick:
        _view_choice()
    _detail_speed([10_000] if quick else [10_000, 100_000], repeats)
    for method in ("detail", "vae"):
        _capture_scale([100_000] if quick else [100_000, 1_000_000, 3_000_000], repeats=1 if quick else 3,
                       method=method)
    if math.isfinite(os.getloadavg()[0]):
        print(f"(load average at the end: {os.getloadavg()[0]:.2f})")


def _exactness() -> None:
    """The Hessian blocks against their definition (one backward pass per pixel and channel
    through the renderer) on a small cloud: the error of the fast path that the speed rows use."""
    cloud = example_cloud(40, seed=3)
    cams = [Camera.look_at((3.0, 0.5, 1.5), (0, 0, 0), width=14, height=12),
            Camera.look_at((-1.0, 2.5, 2.0), (0, 0, 0), width=12, height=12)]
    print("\nHessian blocks against their definition (40 Gaussians, two 12-14 px views; max over Gaussians of "
          "|H - H_def| / |H_def|):")
    for dtype in (torch.float64, torch.float32):
        s = RenderSettings(backward="autograd", dtype=dtype, tile_size=4)
        t0 = time.perf_counter()
        ref = hessian_blocks_reference(cloud, cams, s)
        t1 = time.perf_counter()
        fast = hessian_blocks(cloud, cams, views=0, render_settings=s)
        t2 = time.perf_counter()
        seen = ref.norm(dim=(1, 2)) > 0
        err = ((fast - ref).norm(dim=(1, 2))[seen] / ref.norm(dim=(1, 2))[seen]).max().item()
        print(f"  {str(dtype).replace('torch.', '')}: {err:.1e} ({int(seen.sum())} Gaussians seen; definition "
              f"{(t1 - t0) * 1e3:.0f} ms, fast path {(t2 - t1) * 1e3:.0f} ms)")


def _view_choice() -> None:
    """How many views, how large: the top 10% of the score from a few views against the top 10% of
    the score from all training views (the `quick` experiment's training-resolution clouds and
    their scenes' training cameras, when both are cached)."""
    p = PROTOCOLS["quick"]
    folder = runs_dir() / f"{p.name}-{p.run_key()}"
    stage = f"stage_{p.train_stage}.ply"
    found = []
    for run in sorted(folder.iterdir()) if folder.is_dir() else []:
        scene = cache_dir() / "scenes" / f"{run.name}-{p.scene_profile}-s0-{scene_key(run.name, p.scene_profile, 0)}"
        if (run / stage).is_file() and (scene / "transforms_train.json").is_file():
            found.append((run.name, read_ply(run / stage), load_cameras(scene / "transforms_train.json")))
    if not found:
        print(f"\n(view choice: no cached `quick` runs with their scenes under {folder}; `make report` makes them)")
        return
    print("\nView choice: recall of the top 10% of the score from all training cameras (`quick` runs, training "
          "resolution), and the rank correlation (Spearman) with it:")
    print("\n| scene (Gaussians, cameras) | views | recall@10% | Spearman | seconds |")
    print("|---|---|---:|---:|---:|")
    configs = [("capture", 2, 256), ("capture", 4, 128), ("capture", 4, 256), ("capture", 8, 256),
               ("default", 2, 256), ("default", 3, 256), ("default", 4, 96), ("default", 4, 256), ("default", 8, 256)]
    for name, cloud, cams in found[:3]:
        ref = hessian_scores(cloud, cams, views=0, resolution=max(c.height for c in cams)).numpy()
        top = set(np.argsort(-ref)[: len(ref) // 10])
        for kind, views, res in configs:
            t0 = time.perf_counter()
            s = hessian_scores(cloud, cams if kind == "capture" else None, views=views, resolution=res).numpy()
            seconds = time.perf_counter() - t0
            recall = len(top & set(np.argsort(-s)[: len(s) // 10])) / max(len(top), 1)
            rank = np.corrcoef(np.argsort(np.argsort(s)), np.argsort(np.argsort(ref)))[0, 1]
            print(f"| {name} ({len(cloud):,}, {len(cams)} x {cams[0].height} px) | {kind} {views} x {res} px | "
                  f"{recall:.2f} | {rank:.3f} | {seconds:.1f} |", flush=True)


def _detail_speed(counts, repeats: int) -> None:
    """The detail model: its size, and a refine of `example_cloud` with precomputed scores (no
    Hessian, no fidelity check) against count and budget: inputs (neighbours) and model ms."""
    model = load_detail() if (default_detail_dir() / "detail.json").is_file() else DetailModel()
    params = sum(p.numel() for p in model.parameters())
    print(f"\nDetail model: {params:,} parameters, {model.size_bytes() / 1e3:.1f} kB (float32), "
          f"{model.meta.get('steps', '?')} steps, {model.meta.get('seconds', '?')} s of training")
    print("\n| Gaussians | budget | changed | inputs ms (median) | model ms (median) | refine ms excl. Hessian "
          "(median; first call) | error: non-finite out / changed parameters |")
    print("|---:|---|---:|---:|---:|---:|---|")
    for n in counts:
        cloud = example_cloud(n, seed=1)
        cloud = with_dilation_3d(cloud, default_views(cloud, 4, 512))
        scores = np.random.default_rng(0).gamma(1.0, 1.0, n).astype(np.float32)
        for budget in (0.1, "all"):
            feats, mod, rest, r = [], [], [], None
            for _ in range(repeats + 1):
                r = refine(cloud, budget=budget, model=model, scores=scores, fidelity=None)
                feats.append(r.timings["features"] * 1e3)
                mod.append(r.timings["model"] * 1e3)
                rest.append((r.timings["total"] - r.timings["hessian"] - r.timings["load"]) * 1e3)
            bad = len(r.cloud.validate().nonfinite_rows) + sum(int((~np.isfinite(v)).sum())
                                                               for v in octave_fields(r.cloud).values())
            changed = int((r.cloud.scales != cloud.scales).sum())
            print(f"| {n:,} | {budget} | {len(r.selected):,} | {statistics.median(feats[1:]):.1f} | "
                  f"{statistics.median(mod[1:]):.1f} | {statistics.median(rest[1:]):.1f}; {rest[0]:.1f} | "
                  f"{bad} / {changed} |", flush=True)


def _capture_scale(counts, repeats: int, method: str = "detail") -> None:
    """A whole +1 refine (the method's default budget: detail "all", vae "auto" with the default 4
    Hessian views at 256 px; fidelity check on) of example clouds of 100k to 3M SH-3 Gaussians, each
    size in a fresh process (its peak memory is its own)."""
    threads = os.environ.get("OMP_NUM_THREADS") or torch.get_num_threads()
    print(f"\nWhole +1 refine, method {method}, budget {DEFAULT_BUDGETS[method]}, default Hessian views "
          f"({DEFAULT_VIEWS} x {DEFAULT_RESOLUTION} px), `example_cloud(N)` (SH 3), torch threads {threads}; each "
          f"size in a fresh process, median of {repeats} (3M: 1); seconds:")
    print("\n| Gaussians | Hessian (project / bin / composite / sweep / moments / blocks / score) | features | model "
          "| assemble | fidelity check | refine total (process CPU) | peak RSS (estimate) | selected | kept | added "
          "| error: non-finite scores / out rows, changed unselected | load |")
    print("|---:|---|---:|---:|---:|---:|---|---|---:|---:|---:|---|---:|")
    for n in counts:
        runs = 1 if n > 1_500_000 else repeats
        load0 = os.getloadavg()[0]
        proc = subprocess.run([sys.executable, "-m", "gvae_core.benchmarks.refine", "--one", str(n), "--repeats",
                               str(runs), "--method", method], capture_output=True, text=True, timeout=3600)
        if proc.returncode != 0:
            why = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode
            print(f"| {n:,} | failed: {why} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        h = r["hessian_parts"]
        parts = " / ".join(f"{h.get(k, 0.0):.2f}" for k in ("project", "bin", "composite", "sweep", "moments",
                                                               "blocks", "score"))
        print(f"| {n:,} | **{r['hessian']:.2f}** ({parts}) | {r['features']:.2f} | {r['model']:.2f} | "
              f"{r['assemble']:.2f} | {r['fidelity']:.2f} | **{r['total']:.2f}** ({r['cpu']:.1f}) | "
              f"{r['peak'] / 2 ** 30:.2f} GiB ({r['estimate'] / 2 ** 30:.2f}) | {r['selected']:,} | "
              f"{r['selected'] - r['reverted']:,} | {r['added']:,} | {r['bad_scores']} / "
              f"{r['bad_rows']}, {r['changed']} | {load0:.1f}-{os.getloadavg()[0]:.1f} |", flush=True)


#: Timed parts of a whole refine (RefineResult.timings).
PARTS = ("hessian", "features", "model", "assemble", "fidelity", "total")


def _one(n: int, repeats: int, method: str = "detail") -> dict:
    """The child of `_capture_scale`: refine example_cloud(n) `repeats` times; medians."""
    model = _load_model()[0] if method == "vae" else None
    cloud = example_cloud(n, seed=1)
    rows: list[dict] = []
    for _ in range(repeats):
        parts: dict = {}
        c0 = resource.getrusage(resource.RUSAGE_SELF)
        r = refine(cloud, steps=1, method=method, model=model, seed=0, hessian_options={"timings": parts})
        c1 = resource.getrusage(resource.RUSAGE_SELF)
        rows.append({**{k: r.timings.get(k, 0.0) for k in PARTS},
                     "cpu": c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime, "hessian_parts": parts})
    med = {k: statistics.median(row[k] for row in rows) for k in PARTS + ("cpu",)}
    med["hessian_parts"] = {k: statistics.median(row["hessian_parts"].get(k, 0.0) for row in rows)
                            for k in rows[0]["hessian_parts"]}
    unsel = np.setdiff1d(np.arange(n), r.selected)
    changed = int((r.cloud.means[unsel] != cloud.means[unsel]).any(1).sum())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    return {**med, "selected": len(r.selected), "reverted": len(r.reverted), "added": len(r.added), "peak": peak,
            "estimate": estimate_refine_memory(n, cloud.sh_degree, selected=len(r.selected)),
            "bad_scores": int((~np.isfinite(r.scores)).sum() + (r.scores < 0).sum()),
            "bad_rows": len(r.cloud.validate().nonfinite_rows), "changed": changed}


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("--one", type=int, required=True)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--method", default="detail")
    a = parser.parse_args()
    print(json.dumps(_one(a.one, a.repeats, a.method)))
