"""Progressive (coarse-to-fine) 3DGS training with lineage tracking: `train_progressive`.

Each stage trains at one image height (`train.loop`), starting from the previous stage's
Gaussians, with densification as its strategy (`train.strategy`) and, for the last stage of a run
that converges, its validation photos deciding when to stop (`train.validation`); a stage's result
keeps only the Gaussians some training photo of the stage draws (`train.unseen`). Every Gaussian
carries a persistent id and the id of its nearest ancestor alive at the previous stage boundary; at
each boundary every live Gaussian is snapshotted into a `Lineage`. With an output folder, each
finished stage is written there (`train.run_folder`) and an interrupted run resumes after its last
finished stage; stages are seeded independently, so a resumed run gives the same result as an
uninterrupted one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..antialias import DILATION_KEY, FILTER_KEY, dilation_3d, filter_3d
from ..camera import scene_extent
from ..cloud import GaussianCloud
from ..datasets import Views
from ..initialization import coverage, initial_cloud, start_points
from ..lineage import Lineage
from ..progress import progress_bar, say
from ..rendering import RenderSettings, resolve_device
from ..resources import check_train_memory, current_rss_mb, estimate_train_memory, peak_rss_mb, reset_peak_rss
from .average import ParameterAverage
from .config import TrainConfig
from .data import TrainingData, split_validation, training_data
from .depth import depth_targets
from .evaluation import stage_scores, training_targets
from .loop import Stage, StageOutcome, run_stage
from .model import GaussianModel
from .reporting import ProgressHook, Reporter, torch_threads
from .run_folder import RunFolder
from .strategy import DensifyStrategy, gaussian_limit
from .unseen import seen_by_any
from .validation import Validation

__all__ = ["train_progressive", "TrainResult", "anti_aliasing_size"]


@dataclass
class TrainResult:
    """The final cloud (numpy, with int64 extras `gvae_id`, `gvae_parent` and the float32
    anti-aliasing size of the last stage's training cameras), the lineage of every stage,
    the per-stage log, and where things were written (None without `out_dir`)."""

    cloud: GaussianCloud
    lineage: Lineage
    log: list[dict[str, Any]]
    out_dir: Path | None = None
    stage_paths: list[Path] = field(default_factory=list)


def anti_aliasing_size(config: TrainConfig):
    """(extra property, function of centres and cameras) of the size each snapshot stores for
    rendering above its resolution (`gvae_core.antialias`): the Mip filter of a run trained with
    it, else the classic dilation in world units."""
    return (FILTER_KEY, filter_3d) if config.antialias == "mip" else (DILATION_KEY, dilation_3d)


@dataclass
class _Run:
    """A run's state across its stages."""

    data: TrainingData
    config: TrainConfig
    folder: RunFolder | None
    device: torch.device
    progress: bool
    hook: ProgressHook | None
    init_points: Any
    lineage: Lineage
    log: list[dict[str, Any]]
    next_id: int
    started: float  # time.perf_counter() when the call began (the time budget counts from there)
    stage_paths: list[Path] = field(default_factory=list)
    carried: dict | None = None  # Adam's state at the end of the previous stage
    final_size: np.ndarray | None = None

    def say(self, message: str) -> None:
        if self.progress:
            say(message)


def train_progressive(data, config: TrainConfig | None = None, *, out_dir=None, test=None,
                      init_points=None, resume: bool = True, progress: bool = True,
                      threads: int | None = None, device=None, on_progress: ProgressHook | None = None) -> TrainResult:
    """Train 3DGS coarse-to-fine over `config.resolutions`, recording lineages.

    `data`: a capture (a COLMAP model with its images, a transforms.json, a NeRF-Synthetic folder;
    `training_data`), in-memory views (cameras, images, alphas; with optional `test` views), or a
    function (split, height) -> views. `init_points`: optional (N,3)/(N,6) initial points instead of
    `config.init`'s (`gvae_core.initialization`). With `out_dir`, stage PLYs, lineage.npz,
    log.json and run.json are written there after every stage and an interrupted run resumes
    (unless `resume` is False, which starts over). `progress`: say what it does (a bar on a
    terminal, periodic lines elsewhere). `threads`: torch CPU threads while training (restored
    afterwards); on a busy machine 1 is often much faster than oversubscribing. `device`: the torch
    device to train on (default the CPU; "cuda" with a CUDA build of torch and a GPU); the random
    draws are the CPU's on any device. `on_progress` (`ProgressHook`): about every 10 iterations,
    at every validation and at every stage's end; an exception it raises stops the run cleanly
    (what `out_dir` holds resumes)."""
    config, started = config or TrainConfig(), time.perf_counter()
    with torch_threads(threads):
        run = _begin(training_data(data, test, config.test_every), config, out_dir, init_points, resume, progress,
                     resolve_device(device), on_progress, started)
        for s in range(run.lineage.n_stages, len(config.resolutions)):
            _train_stage(run, s)
        return _result(run)


def _begin(data: TrainingData, config: TrainConfig, out_dir, init_points, resume: bool, progress: bool,
           device: torch.device, hook: ProgressHook | None, started: float) -> _Run:
    folder = RunFolder(out_dir) if out_dir is not None else None
    if folder is not None:
        folder.start(restart=not resume)
    state = folder.resume(config) if folder is not None else None
    lineage, log, next_id = state if state else (Lineage(), [], 0)
    run = _Run(data, config, folder, device, progress, hook, init_points, lineage, log, next_id, started)
    if folder is not None:
        run.stage_paths = [folder.stage_path(s) for s in range(lineage.n_stages)]
    run.say(data.description)
    return run


def _start(run: _Run, views: Views, validation: Views | None) -> tuple[GaussianCloud, np.ndarray, np.ndarray, dict]:
    """The first stage's Gaussians (`gvae_core.initialization`), their ids and parents, and what the
    log says of the start."""
    config = run.config
    if validation is not None:
        run.say(f"validation: {len(validation)} of the {len(views) + len(validation)} training photos set aside "
                "(never trained on) to judge when training stops helping")
    init_rng = np.random.default_rng([config.seed, 1_000_003])
    if run.init_points is None:
        run.init_points, what = start_points(views, config, init_rng, run.data.points)
    else:
        what = f"{len(run.init_points)} points given"
    cloud = initial_cloud(config, run.init_points)
    covered = coverage(cloud, views)
    start = {"start": what, "start_coverage": round(float(covered.mean()), 6),
             "start_coverage_min": round(float(covered.mean((1, 2)).min()), 6)}
    run.say(f"start: {what}; it covers {covered.mean():.2%} of the training pixels (the least covered view "
            f"{start['start_coverage_min']:.2%})")
    run.next_id = len(cloud)
    return cloud, np.arange(len(cloud), dtype=np.int64), np.full(len(cloud), -1, np.int64), start


def _stage_model(run: _Run, s: int, views: Views, validation: Views | None) -> tuple[GaussianModel, dict]:
    """Stage `s`'s trainable Gaussians (from the start or the previous stage, Adam's state carried
    when the configuration says so) and what the log says of its start."""
    config = run.config
    _, extent = scene_extent(views.cameras)
    start: dict = {}
    if s == 0:
        cloud, ids, parents, start = _start(run, views, validation)
    else:
        snap = run.lineage.snapshots[-1]
        cloud, ids, parents = snap.cloud, snap.ids, snap.ids  # survivors are their own anchors
    model = GaussianModel(cloud, ids, parents, config.learning_rates(extent), extent, run.next_id, run.device)
    if s > 0 and config.carry_optimizer:
        if run.carried is None and run.folder is not None:  # resumed
            run.carried = run.folder.adam()
        model.load_optimizer_state(run.carried or {})
    return model, start


def _train_stage(run: _Run, s: int) -> None:
    config, n_stages, height = run.config, len(run.config.resolutions), run.config.resolutions[s]
    all_views = run.data.views("train", height)
    if all_views is None or len(all_views) == 0:
        raise ValueError("train_progressive: no training views")
    views, validation = split_validation(all_views, config.validation_views)
    if s == run.lineage.n_stages:  # the first stage this call trains: will the last one fit?
        last = views.cameras[0].scaled(config.resolutions[-1])
        check_train_memory(gaussian_limit(config, len(all_views), last)[0], len(all_views), last.height, last.width,
                           config.sh_degree)
    rng = np.random.default_rng([config.seed, s])
    gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
    model, start = _stage_model(run, s, views, validation)
    cam0 = views.cameras[0]
    limit, why = gaussian_limit(config, len(views), cam0)
    need = estimate_train_memory(len(model), len(views), cam0.height, cam0.width, config.sh_degree)
    run.say(f"stage {s + 1}: {len(views)} views of {cam0.width}x{cam0.height}, {len(model)} Gaussians; memory "
            f"about {need / 2**30:.2f} GiB now, at most {limit} Gaussians ({why})")
    planned = config.iterations[s]
    converging = config.converge and s == n_stages - 1 and validation is not None
    n_max = max(config.max_iterations, planned) if converging else planned
    first = sum(config.iterations[:s])
    strategy = DensifyStrategy.for_stage(config, s, limit, last=n_max)
    averaged = config.average is not None and s == n_stages - 1  # (from the end of densification: the same rows)
    stage = Stage(model, views.cameras, training_targets(views, config.background).to(run.device), config, n_max,
                  rng, gen, lambda it: config.sh_degree_at(first + it - 1),
                  lr_window=(first, sum(config.iterations)) if config.lr_schedule == "run" else (0, planned),
                  strategy=strategy, average_from=strategy.stop + 1 if averaged else None,
                  average_decay=config.average or 0.99, filter_every=config.stage_schedule(s)["densify_every"],
                  depth=depth_targets(run.data.points, views, run.device) if config.depth_weight > 0 else None)
    watch = None if validation is None else Validation(
        config, validation, views.cameras, stage.settings, run.started, planned, converging, run.say,
        run.data.views("test", height) if converging else None)
    report = Reporter(run.hook, s, n_stages, n_max, lambda: len(model))
    outcome, seconds, cpu_seconds, memory = _optimise(run, stage, watch, report, s, converging)
    if watch is not None and watch.best_params is not None and converging:
        model.load_params(watch.best_params)  # the state the validation photos liked best
    elif stage.average is not None:
        model.load_params(stage.average.values)
    cooled = {}
    if converging and config.cool_down > 0:
        t0, c0 = time.perf_counter(), time.process_time()
        cooled = _cool_down(stage, watch, outcome.iterations, report)
        seconds, cpu_seconds = seconds + time.perf_counter() - t0, cpu_seconds + time.process_time() - c0
    seen = seen_by_any(stage.drawn(), views.cameras, stage.settings).to(model.device)
    unseen = int((~seen).sum())
    if unseen:  # no photo of the stage draws them: nothing trained them (`train.unseen`)
        model.keep(seen)
    run.carried = model.optimizer_state() if config.carry_optimizer and s < n_stages - 1 else None
    iterations = outcome.iterations + cooled.get("cool_down", 0)
    timing = {"iterations": iterations, "seconds": round(seconds, 3),
              "seconds_per_iteration": round(seconds / max(iterations, 1), 5),
              "cpu_seconds": round(cpu_seconds, 3)}
    _finish_stage(run, s, model, (views, validation),
                  (timing, {"gaussian_limit": limit, **start, **memory, **cooled, "unseen_removed": unseen}),
                  outcome, watch, converging, report)


def _cool_down(stage: Stage, watch: Validation, done: int, report: Reporter) -> dict:
    """After a converged stage (`done` iterations, its best state loaded): `config.cool_down` more
    iterations of its model with Adam afresh and the position learning rate decaying again from its
    start over them, ending on their running average (as `gvae train RUN --more` trains); kept when
    the validation photos like the average better than the stage's best, else the best again. What
    the log says of it."""
    config, model = stage.config, stage.model
    n, degree = config.cool_down, stage.degree_at(done)
    model.reset_optimizer_state()
    cool = Stage(model, stage.cameras, stage.targets, config, n, stage.rng, stage.generator, lambda it: degree,
                 average=ParameterAverage(model, config.average or 0.99), filter_every=stage.filter_every,
                 depth=stage.depth)
    run_stage(cool, progress=lambda it: report(done + it, f"cool-down: step {it}/{n}"))
    kept = watch.judge(cool.average.values, done + n, degree)
    model.load_params(watch.best_params)
    return {"cool_down": n, "cool_down_kept": kept}


def _optimise(run: _Run, stage: Stage, watch: Validation | None, report: Reporter, s: int,
              converging: bool) -> tuple[StageOutcome, float, float, dict]:
    """Run the stage's steps with its bar, reports and validation checks; (outcome, seconds, CPU
    seconds, what the log says of its memory)."""
    n_stages, height = len(run.config.resolutions), run.config.resolutions[s]
    views = len(stage.cameras)
    reset_ok = reset_peak_rss()
    rss_before, rss_start = peak_rss_mb(), current_rss_mb()
    bar = progress_bar(stage.iterations if not converging else run.config.iterations[s],
                       f"stage {s + 1}/{n_stages} {height}px", enabled=run.progress)
    report(0, f"stage {s + 1}/{n_stages} at {height} px: {views} photos, {len(stage.model)} Gaussians")
    check = None
    if watch is not None:
        def check(it: int) -> str | None:
            return watch.check(stage.result_params(), it, stage.degree_at(it), report)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        outcome = run_stage(stage, bar=bar, progress=lambda it: report(it, f"stage {s + 1}/{n_stages}: step {it}"),
                            check=check, check_every=run.config.validation_every)
    finally:
        bar.close()
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    peak = peak_rss_mb() if reset_ok else max(peak_rss_mb(), rss_before)
    memory = {"peak_rss_mb": round(peak, 1), "rss_start_mb": round(rss_start, 1), "peak_rss_exact": reset_ok}
    return outcome, seconds, cpu_seconds, memory


def _finish_stage(run: _Run, s: int, model: GaussianModel, photos: tuple[Views, Views | None],
                  said: tuple[dict, dict], outcome: StageOutcome, watch: Validation | None, converging: bool,
                  report: Reporter) -> None:
    """Snapshot stage `s` into the lineage, score it on its `photos` (training, validation), log it
    with what `said` of its run (timing; budget, start and memory), write it."""
    config, n_stages, height = run.config, len(run.config.resolutions), run.config.resolutions[s]
    (views, validation), (timing, setting) = photos, said
    settings = RenderSettings(antialias=config.antialias)
    size_key, size_fn = anti_aliasing_size(config)
    snap = model.snapshot().replace(background=config.background)
    ids, parents = snap.extra["gvae_id"], snap.extra["gvae_parent"]
    run.final_size = size_fn(snap.means, views.cameras)  # the stage's training cameras
    snap = snap.replace(extra={**snap.extra, size_key: run.final_size})
    run.lineage.add_stage(snap.replace(extra={}), ids, parents, height)
    run.lineage.set_normalization(*snap.normalization())
    run.next_id = model.next_id
    degree = config.sh_degree_at(sum(config.iterations[:s + 1]))
    t1 = time.perf_counter()
    scores = stage_scores(snap.replace(extra={size_key: run.final_size}).to_torch(device=run.device), config,
                          degree, settings, views, validation, run.data.views("test", height))
    entry = {"stage": s, "resolution": height, **timing, "n_gaussians": len(snap), "train_psnr": scores["train_psnr"],
             "test_psnr": scores["test_psnr"], "test_ssim": scores["test_ssim"], **setting, "sh_degree": degree,
             "eval_seconds": round(time.perf_counter() - t1, 3), "next_id": run.next_id, "cloned": outcome.cloned,
             "split": outcome.split, "pruned": outcome.pruned}
    if watch is not None:
        entry.update(validation_views=len(validation), validation_psnr=scores["validation_psnr"],
                     **watch.summary(outcome.stopped if converging else None, outcome.iterations))
    run.log.append(entry)
    if converging:
        _say_converged(run, s, entry, scores, len(snap))
    report(outcome.iterations, f"stage {s + 1}/{n_stages} done: {len(snap)} Gaussians", **scores)
    if run.folder is not None:
        run.stage_paths.append(run.folder.save_stage(s, snap, run.lineage, run.log, config, run.next_id,
                                                     run.data.source, run.carried))


def _say_converged(run: _Run, s: int, entry: dict, scores: dict, count: int) -> None:
    said, test = entry.get("test_psnr_at_planned"), scores["test_psnr"]
    held = "" if test is None else f", held-out {test:.2f} dB"
    if said and test is not None:
        held += f" (at step {said[0]}: {said[1]:.2f})"
    val = scores["validation_psnr"]
    run.say(f"stage {s + 1}: {entry['stopped']}; kept step {entry['best_step']}: validation {val:.2f} dB{held}, "
            f"{count} Gaussians")


def _result(run: _Run) -> TrainResult:
    config = run.config
    size_key, size_fn = anti_aliasing_size(config)
    last = run.lineage.n_stages - 1
    final = run.lineage.stage_cloud(last)
    if run.final_size is None:  # every stage was done already: the size is in the last stage's PLY
        saved = run.folder.stage_size(last, size_key, len(final)) if run.folder is not None else None
        if saved is None:  # (a run from before the size was stored: from the stage's training cameras)
            views, _ = split_validation(run.data.views("train", config.resolutions[last]), config.validation_views)
            saved = size_fn(final.means, views.cameras)
        run.final_size = saved
    final = final.replace(extra={**final.extra, size_key: run.final_size}, background=config.background)
    return TrainResult(final, run.lineage, run.log, run.folder.path if run.folder is not None else None,
                       run.stage_paths)
