"""The paper's experiment on the project's benchmark scenes (the refinement benchmark of issue 6
and `gvae report`).

Per scene: progressive 3DGS with lineage up to the training resolution, continued with the real
higher-resolution images (the 1.5x and 2x baselines, the paper's 700p/800p columns); then, from
the training-resolution stage and its lineage only, refinement +1..+4 by Ours (every Gaussian),
Ours-∇² (the Hessian budget) and two controls at Ours-∇²'s budget: random selection, and the
plain 3DGS split of the selected Gaussians without the model; Ours-∇² with the model's appearance
at every step (the ablation of `carry_appearance`); and a Hessian budget sweep. Each
cloud is scored by Chamfer distance to the ground-truth mesh, PSNR/SSIM against ground-truth
test views at 1x, 1.5x and 2x the training resolution, NIQE of its 2x renders, its Gaussian
count and refine time. Scenes and training runs are cached and reused.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .controls import split_control
from .datasets import load_nerf_synthetic
from .hessian import hessian_scores
from .lineage import Lineage
from .metrics.geometry import MeshDistance, chamfer, read_mesh_ply
from .metrics.image import image_scores
from .ply import read_ply
from .refinement import RefineResult, refine_steps
from .rendering import render
from .rendering.reference import render_reference
from .scenes import cache_dir, make_scene
from .train import TrainConfig, train_progressive
from .vae import GaussianVAE, default_model_dir

#: Methods in results rows: the 3DGS baselines, the model, and the controls.
BASELINE, OURS, OURS_H, RANDOM, SPLIT, SWEEP = "3dgs", "ours", "ours_h", "random", "split", "sweep"
OURS_H_MODEL_APP = "ours_h_app"  # ablation: the model's appearance at every step (`carry_appearance=False`)
SCALES = ("1x", "1.5x", "2x")


@dataclass(frozen=True)
class Protocol:
    """One experiment profile: which scenes at which render profile, the training stages (the
    last is the training resolution) and the real-image stages above it (1.5x and 2x), how far
    to refine and what to evaluate."""

    name: str
    scene_profile: str
    scenes: tuple[str, ...]
    resolutions: tuple[int, ...]
    iterations: tuple[int, ...]
    higher: tuple[int, ...]
    higher_iterations: tuple[int, ...]
    train_overrides: dict = field(default_factory=dict)
    steps: int = 4
    budget: Any = "auto"
    sweep: tuple[float, ...] = (0.01, 0.03, 0.1, 0.3)
    sweep_steps: int = 2
    test_views: int | None = None
    hessian_views: int = 8
    hessian_probes: int = 4
    seed: int = 0

    def train_config(self):
        return TrainConfig.profile("default", resolutions=self.resolutions + self.higher,
                                   iterations=self.iterations + self.higher_iterations, seed=self.seed,
                                   **self.train_overrides)

    @property
    def train_stage(self) -> int:
        """Index of the training-resolution stage in the run."""
        return len(self.resolutions) - 1

    def run_key(self) -> str:
        """Hash of what a scene's training run depends on."""
        blob = json.dumps({"scene_profile": self.scene_profile, "config": self.train_config().to_dict()},
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


PROTOCOLS: dict[str, Protocol] = {p.name: p for p in [
    # Within 20 minutes on 2 cores from nothing (5.3 min measured): the two held-out scenes, small renders.
    Protocol("quick", scene_profile="small", scenes=("chair", "tableware"),
             resolutions=(50, 75, 100), iterations=(300, 200, 200), higher=(150, 200),
             higher_iterations=(200, 200),
             train_overrides=dict(init_count=4000, max_gaussians=20_000), test_views=8),
    # All six scenes at the benchmark profile (hours on 2 cores).
    Protocol("full", scene_profile="default", scenes=("plant", "crate", "materials", "bricks", "chair", "tableware"),
             resolutions=(100, 150, 200), iterations=(600, 400, 400), higher=(300, 400),
             higher_iterations=(400, 400), test_views=10),
]}


# ----------------------------------------------------------------------------- per scene

@dataclass
class SceneRun:
    """A scene prepared for the experiment: its folder, its training run (all stages), and what
    evaluation needs."""

    name: str
    scene_dir: Path
    run_dir: Path
    protocol: Protocol
    seconds: dict[str, float]

    def lineage(self, stages: int | None = None):
        lin = Lineage.load(self.run_dir / "lineage.npz")
        return lin if stages is None else lin.prefix(stages)

    def stage_cloud(self, stage: int):
        return read_ply(self.run_dir / f"stage_{stage}.ply")

    def log(self) -> list[dict]:
        return json.loads((self.run_dir / "log.json").read_text())


def runs_dir(cache=None) -> Path:
    return cache_dir(cache) / "runs"


def prepare_scene(name: str, protocol: Protocol, *, cache=None, threads: int = 1,
                  say: Callable[[str], None] = print) -> SceneRun:
    """Render the scene (cached) and train its run through every stage (cached, resumable)."""
    t0 = time.perf_counter()
    scene_dir = make_scene(name, profile=protocol.scene_profile, seed=protocol.seed, cache=cache)
    t1 = time.perf_counter()
    run_dir = runs_dir(cache) / f"{protocol.name}-{protocol.run_key()}" / name
    config = protocol.train_config()
    done = _stages_done(run_dir)
    if done < len(config.resolutions):
        say(f"[{name}] training {len(config.resolutions)} stages {config.resolutions} px "
            f"({done} done) into {run_dir}")
        train_progressive(scene_dir, config, out_dir=run_dir, progress=False, threads=threads)
    return SceneRun(name, scene_dir, run_dir, protocol,
                    {"scene": t1 - t0, "train": time.perf_counter() - t1})


def _stages_done(run_dir: Path) -> int:
    try:
        return int(json.loads((run_dir / "run.json").read_text())["stages_done"])
    except (OSError, ValueError, KeyError):
        return 0


class Evaluator:
    """Scores clouds of one scene: Chamfer against its mesh, PSNR/SSIM against its test views
    at each scale, NIQE of the 2x renders."""

    def __init__(self, run: SceneRun, background=(1.0, 1.0, 1.0)):
        p = run.protocol
        self.background = background
        self.mesh = MeshDistance(*read_mesh_ply(run.scene_dir / "mesh.ply"))
        self.surface = np.load(run.scene_dir / "gt_points.npy")
        heights = (p.resolutions[-1],) + tuple(p.higher)
        self.views = {}
        for label, h in zip(SCALES, heights):
            v = load_nerf_synthetic(run.scene_dir, "test", resolution=h)
            if p.test_views is not None and p.test_views < len(v):
                pick = np.linspace(0, len(v) - 1, p.test_views).round().astype(int)
                v = type(v)([v.cameras[i] for i in pick], v.images[pick], v.alphas[pick],
                            [v.names[i] for i in pick])
            self.views[label] = v

    def __call__(self, cloud, *, scales=SCALES, no_reference: bool = True) -> dict[str, float]:
        c = chamfer(cloud.means, self.surface, self.mesh)
        row = {"chamfer": c.chamfer, "accuracy": c.accuracy, "completeness": c.completeness,
               "n_gaussians": len(cloud)}
        for label in scales:
            s = image_scores(cloud, self.views[label], self.background,
                             no_reference=no_reference and label == SCALES[-1])
            row[f"psnr_{label}"] = s.psnr
            row[f"ssim_{label}"] = s.ssim
            if label == SCALES[-1] and no_reference:
                row["niqe"] = s.niqe
        return row


def hessian_cameras(run: SceneRun, count: int):
    """`count` training cameras, evenly spaced, at the training resolution."""
    views = load_nerf_synthetic(run.scene_dir, "train", resolution=run.protocol.resolutions[-1])
    pick = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    return [views.cameras[i] for i in pick]


def render_timing(cloud, camera, repeats: int = 3, samples: int = 64, seed: int = 0) -> dict:
    """Seconds per forward render (median of `repeats`) and the largest difference from the
    float64 reference renderer on `samples` random pixels of the same image."""
    tc = cloud.to_torch()
    times = []
    with torch.no_grad():
        render(tc, camera, background=(1.0, 1.0, 1.0))  # warm-up: first-call costs are not the renderer's
        for _ in range(repeats):
            t0 = time.perf_counter()
            image = render(tc, camera, background=(1.0, 1.0, 1.0)).image.numpy()
            times.append(time.perf_counter() - t0)
    rng = np.random.default_rng(seed)
    pix = np.stack([rng.integers(0, camera.height, samples), rng.integers(0, camera.width, samples)], 1)
    ref = render_reference(cloud, camera, background=(1.0, 1.0, 1.0), pixels=pix)[0]
    error = float(np.abs(image[pix[:, 0], pix[:, 1]] - ref).max())
    return {"render_s": statistics.median(times), "render_error": error, "n_gaussians": len(cloud),
            "height": camera.height}


def run_scene(run: SceneRun, model, *, say: Callable[[str], None] = print) -> list[dict]:
    """Every method and step on one prepared scene; one row per (method, step, budget)."""
    p = run.protocol
    k = p.train_stage
    evaluate = Evaluator(run)
    lineage = run.lineage(k + 1)
    base = run.stage_cloud(k)
    rows: list[dict] = []

    def add(method: str, step: int, cloud, **info) -> None:
        t0 = time.perf_counter()
        row = {"scene": run.name, "method": method, "step": step, **info, **evaluate(cloud)}
        row["eval_s"] = time.perf_counter() - t0
        rows.append(row)
        say(f"[{run.name}] {method:7s} {'+' + str(step) if step else '':3s} {_brief(row)}")

    log = run.log()
    for i, label in enumerate(SCALES):
        entry = log[k + i]
        add(BASELINE, 0, run.stage_cloud(k + i), resolution=entry["resolution"], scale=label,
            train_s=sum(e["seconds"] for e in log[:k + i + 1]))

    t0 = time.perf_counter()
    scores = hessian_scores(base, hessian_cameras(run, p.hessian_views), probes=p.hessian_probes,
                            seed=p.seed).numpy()
    hessian_s = time.perf_counter() - t0
    common = dict(steps=p.steps, model=model, lineage=lineage, seed=p.seed)

    largest = base

    def refined(method: str, results, budget) -> list[RefineResult]:
        nonlocal largest
        out = []
        for step, r in enumerate(results, 1):
            out.append(r)
            largest = r.cloud if len(r.cloud) > len(largest) else largest
            add(method, step, r.cloud, budget=str(budget), selected=len(r.selected), added=len(r.added),
                refine_s=r.timings["total"] - r.timings.get("hessian", 0.0) - r.timings.get("load", 0.0),
                hessian_s=hessian_s if method != OURS else 0.0)
        return out

    refined(OURS, refine_steps(base, budget="all", **common), "all")
    ours_h = refined(OURS_H, refine_steps(base, budget=p.budget, scores=scores, **common), p.budget)
    count = len(ours_h[0].selected)
    refined(OURS_H_MODEL_APP, refine_steps(base, budget=p.budget, scores=scores, carry_appearance=False, **common),
            p.budget)
    noise = np.random.default_rng(p.seed + 1).random(len(base)).astype(np.float32)
    refined(RANDOM, refine_steps(base, budget=count, scores=noise, **common), count)
    refined(SPLIT, split_control(base, scores, [len(r.added) for r in ours_h], seed=p.seed), count)
    for b in p.sweep:
        sweep = refine_steps(base, budget=b, scores=scores, **{**common, "steps": min(p.steps, p.sweep_steps)})
        for step, r in enumerate(sweep, 1):
            t0 = time.perf_counter()
            row = {"scene": run.name, "method": SWEEP, "step": step, "budget": str(b), "selected": len(r.selected),
                   "added": len(r.added), "refine_s": r.timings["total"] - r.timings["hessian"] - r.timings["load"],
                   "hessian_s": hessian_s, **evaluate(r.cloud, scales=(SCALES[-1],), no_reference=False)}
            row["eval_s"] = time.perf_counter() - t0
            rows.append(row)
        say(f"[{run.name}] sweep   {b}: {_brief(rows[-1])}")
    for cloud, of in ((base, BASELINE), (largest, "largest refined")):
        for label in SCALES:
            rows.append({"scene": run.name, "method": "render", "of": of, "scale": label,
                         **render_timing(cloud, evaluate.views[label].cameras[0])})
    return rows


def _brief(row: dict) -> str:
    parts = [f"n={row['n_gaussians']}", f"CD={row['chamfer']:.5f}"]
    parts += [f"PSNR{s}={row[f'psnr_{s}']:.2f}" for s in SCALES if f"psnr_{s}" in row]
    if "niqe" in row and row["niqe"] == row["niqe"]:
        parts.append(f"NIQE={row['niqe']:.2f}")
    return " ".join(parts)


def run_experiment(protocol: Protocol | str, *, model=None, scenes=None, cache=None, jobs: int | None = None,
                   say: Callable[[str], None] = print) -> dict:
    """The whole experiment: every scene prepared and evaluated, `jobs` scenes at a time in
    worker processes of one torch thread each (default: one per core); returns the results
    document (protocol, model, per-scene run logs and timings, rows)."""
    p = PROTOCOLS[protocol] if isinstance(protocol, str) else protocol
    model_dir = Path(model) if model is not None else default_model_dir()
    loaded = GaussianVAE.load(model_dir)
    names = list(scenes or p.scenes)
    jobs = _job_count(jobs, len(names))
    started = time.time()
    t0 = time.perf_counter()
    doc = {"protocol": {**asdict(p), "train_config": p.train_config().to_dict()},
           "model": {"dir": str(model_dir), "sizes": loaded.sizes(),
                     "train_scenes": loaded.meta.get("train_scenes", []),
                     "held_out_scenes": loaded.meta.get("held_out_scenes", [])},
           "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(started)), "scenes": {}, "rows": [],
           "jobs": jobs}
    if jobs == 1:
        results = [scene_job(name, p, model_dir, cache, say) for name in names]
    else:
        with _pool(jobs) as pool:
            futures = [pool.submit(scene_job, name, p, model_dir, cache, None) for name in names]
            results = [f.result() for f in futures]
    for name, (rows, info) in zip(names, results):
        doc["rows"] += rows
        doc["scenes"][name] = info
    doc["seconds"] = time.perf_counter() - t0
    return _finite(doc)


def prepare_scenes(names, protocol: Protocol, *, cache=None, jobs: int | None = None,
                   say: Callable[[str], None] = print) -> dict[str, SceneRun]:
    """`prepare_scene` for several scenes, `jobs` at a time in worker processes of one torch
    thread each (default: one per core)."""
    names = list(names)
    jobs = _job_count(jobs, len(names))
    if jobs == 1:
        return {name: prepare_scene(name, protocol, cache=cache, say=say) for name in names}
    with _pool(jobs) as pool:
        futures = {name: pool.submit(prepare_scene, name, protocol, cache=cache, say=_print) for name in names}
        return {name: f.result() for name, f in futures.items()}


def _job_count(jobs: int | None, tasks: int) -> int:
    """Worker processes for `tasks` scenes: `jobs`, or one per core, and no more than the tasks."""
    return max(1, min(jobs or os.cpu_count() or 1, tasks))


def _pool(jobs: int):
    # spawn: a forked torch process can hang in its thread pools.
    return ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_one_thread)


def _print(msg: str) -> None:
    print(msg, flush=True)


def _one_thread() -> None:
    torch.set_num_threads(1)


def scene_job(name: str, protocol: Protocol, model_dir, cache=None, say: Callable[[str], None] | None = None):
    """One scene from start to end (a worker process's job): rows and the scene's record."""
    say = say or _print
    run = prepare_scene(name, protocol, cache=cache, threads=1, say=say)
    t1 = time.perf_counter()
    rows = run_scene(run, GaussianVAE.load(model_dir), say=say)
    return rows, {"scene_dir": str(run.scene_dir), "run_dir": str(run.run_dir), "log": run.log(),
                  "seconds": {**run.seconds, "evaluate": time.perf_counter() - t1}}


def _finite(obj):
    """JSON-safe copy: NaN and infinities become None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
