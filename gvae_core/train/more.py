"""Training without density control: `fine_tune` (a cloud trained more on views, the same
Gaussians: compaction's and refine's control) and `train_more` (a finished stage of a run trained
more, `gvae train RUN --more N`): the stage loop (`train.loop`) with no strategy."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..antialias import FILTER_KEY, DILATION_KEY
from ..camera import scene_extent
from ..capture import SfMPoints
from ..cloud import GaussianCloud
from ..datasets import Views
from ..ply import read_ply
from ..progress import progress_bar
from ..rendering import RenderSettings, resolve_device
from .average import ParameterAverage
from .config import TrainConfig
from .data import split_validation, training_data
from .depth import depth_targets
from .evaluation import stage_scores, training_targets
from .loop import Stage, centres_filter, run_stage
from .model import GaussianModel
from .progressive import anti_aliasing_size
from .reporting import ProgressHook, Reporter, torch_threads
from .run_folder import RunFolder

__all__ = ["fine_tune", "train_more", "MoreResult"]


def fine_tune(cloud: GaussianCloud, views: Views, iterations: int, *, config: TrainConfig | None = None,
              seed: int = 0, progress: Callable[[float, str], None] | None = None, device=None,
              should_stop: Callable[[int, GaussianCloud], bool] | None = None,
              check_every: int = 100, average: float | None = None, points: SfMPoints | None = None) -> GaussianCloud:
    """`cloud` trained on `views` (at their resolution) for `iterations` more iterations with
    the trainer's recipe and one stage's schedule (`train.loop`: its learning rates, the position
    rate decaying over the iterations, the anti-aliasing of `config.antialias`), without density
    control: the Gaussians stay the same rows, only their parameters change (how PUP 3D-GS
    fine-tunes after pruning). The SH degree is the cloud's. Returns a numpy cloud with the input's
    extra properties, its anti-aliasing size (`gvae_dilation_3D`, or `filter_3D` when
    `config.antialias` is "mip") recomputed from the views' cameras. `progress(fraction, message)`
    every 10 iterations (an exception it raises stops the fine-tune). `should_stop(iteration,
    cloud)` every `check_every` iterations, with the current cloud (torch, detached, as it is
    drawn while training): True ends the fine-tune there (for example a `gvae_core.plateau.Plateau`
    on a validation PSNR). `average` (a decay in (0, 1)): the result, and what `should_stop` sees,
    is the running average of the iterates (`ParameterAverage`) instead of the last one. `points`:
    the capture's SfM points, whose depths join the loss with `config.depth_weight` (`train.depth`)."""
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError(f"fine_tune: iterations must be >= 0, got {iterations}")
    if check_every <= 0:
        raise ValueError(f"fine_tune: check_every must be positive, got {check_every}")
    if len(views) == 0:
        raise ValueError("fine_tune: no views")
    src = cloud.numpy()
    dev = resolve_device(device)
    config = dataclasses.replace(config or TrainConfig(), resolutions=(views.cameras[0].height,),
                                 iterations=(iterations,), sh_degree=src.sh_degree)
    rng = np.random.default_rng([seed, 7_000_003])
    gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
    _, extent = scene_extent(views.cameras)
    model = GaussianModel.fresh(src.replace(extra={}), config.learning_rates(extent), extent, dev)
    mean = None if average is None else ParameterAverage(model, average)
    stage = Stage(model, views.cameras, training_targets(views, config.background).to(dev), config, iterations,
                  rng, gen, lambda it: src.sh_degree, average=mean,
                  filter_every=config.stage_schedule(0)["densify_every"],
                  depth=depth_targets(points, views, dev) if config.depth_weight > 0 else None)
    say = (lambda it: progress(it / max(iterations, 1), f"fine-tuning {it}/{iterations}")) if progress else None
    check = None
    if should_stop is not None:
        def check(it: int) -> str | None:
            current = (model.cloud() if mean is None else mean.cloud()).detach()
            if config.antialias == "mip":  # (the filter of the centres drawn)
                current = current.replace(extra={FILTER_KEY: centres_filter(current.means, views.cameras)})
            return "should_stop" if should_stop(it, current) else None
    run_stage(stage, progress=say, check=check, check_every=check_every)
    if mean is not None:
        model.load_params(mean.values)
    out = model.snapshot()
    key, size_fn = anti_aliasing_size(config)
    extra = {k: v for k, v in src.extra.items() if k not in (FILTER_KEY, DILATION_KEY)}
    return out.replace(extra={**extra, key: size_fn(out.means, views.cameras)})


@dataclass
class MoreResult:
    """A finished stage trained `iterations` more: the cloud, where it was written, and its log entry
    (PSNR/SSIM on the training, validation and held-out views at the stage's resolution, time)."""

    cloud: GaussianCloud
    path: Path
    entry: dict[str, Any]


def train_more(run_dir, iterations: int, *, stage: int | None = None, progress: bool = True,
               threads: int | None = None, device=None, on_progress: ProgressHook | None = None) -> MoreResult:
    """Train a finished stage of the run in `run_dir` (the last by default) `iterations` more
    iterations on its training views at its resolution (without the validation photos it set
    aside), the run's configuration, without density control (`fine_tune`: the same Gaussians; the
    control a refinement at the same count is judged against), ending on the average of its iterates
    as the run's last stage did (`TrainConfig.average`). Writes `stage_<s>_more_<iterations>.ply` and
    appends the entry to `more.json`, with the stage's own held-out figures before it
    (`test_psnr_before`, `test_ssim_before`). `on_progress`: as `train_progressive`'s."""
    folder = RunFolder(run_dir)
    state = folder.finished()
    config, done = state.config, state.stages_done
    stage = done - 1 if stage is None else int(stage)
    if not 0 <= stage < done:
        raise ValueError(f"{folder.path}: stage {stage} is not finished ({done} stage(s) are)")
    if state.data is None:
        raise ValueError(f"{folder.file('run.json')}: the run does not say what it was trained from (trained from "
                         "views in memory, or by a version that did not store it)")
    data = training_data(state.data, test_every=config.test_every)
    height, n = config.resolutions[stage], int(iterations)
    views, validation = split_validation(data.views("train", height), config.validation_views)
    cloud = read_ply(folder.stage_path(stage))
    report = Reporter(on_progress, stage, done, n, lambda: len(cloud))
    bar = progress_bar(n, f"stage {stage + 1} +{n}", enabled=progress)
    last = [0]

    def advance(fraction: float, message: str) -> None:
        now = int(round(fraction * n))
        bar.update(now - last[0])
        last[0] = now
        report(now, f"stage {stage + 1}: {message}")

    t0 = time.perf_counter()
    try:
        with torch_threads(threads):
            tuned = fine_tune(cloud, views, n, config=config, seed=config.seed, progress=advance, device=device,
                              average=config.average, points=data.points)
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    tuned = tuned.replace(background=config.background)
    scores = stage_scores(tuned.to_torch(device=resolve_device(device)), config, tuned.sh_degree,
                          RenderSettings(antialias=config.antialias), views, validation, data.views("test", height))
    before = next((e for e in folder.log() if e.get("stage") == stage), {})
    entry = {"stage": stage, "resolution": height, "more": n, "seconds": round(seconds, 3),
             "n_gaussians": len(tuned), **scores, "test_psnr_before": before.get("test_psnr"),
             "test_ssim_before": before.get("test_ssim")}
    path = folder.save_more(stage, n, tuned, entry)
    entry["file"] = path.name
    report(n, f"stage {stage + 1}: {n} more iterations done", **scores)
    return MoreResult(tuned, path, entry)
