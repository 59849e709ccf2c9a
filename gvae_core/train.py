"""Progressive (coarse-to-fine) 3DGS training on the CPU with densification and lineage tracking.

Each stage trains at one image height, starting from the previous stage's Gaussians, with the
reference 3DGS recipe scaled to the stage's iteration budget: Adam with the reference learning
rates (positions decaying exponentially, proportional to the scene extent), loss
0.8·L1 + 0.2·(1 − SSIM), SH degree raised over time, and adaptive density control (clone small
Gaussians with a large view-space positional gradient, split large ones, prune transparent and
oversized ones, reset opacities periodically). Every Gaussian carries a persistent id and the id
of its nearest ancestor alive at the previous stage boundary; at each boundary every live
Gaussian is snapshotted into a `Lineage`.

Output directory: stage_<s>.ply (with int64 extras `gvae_id`, `gvae_parent` and the float32
anti-aliasing size of the stage's training cameras, `gvae_dilation_3D` or, trained with the Mip
filters, `filter_3D`: `gvae_core.antialias`), lineage.npz,
log.json (one object per stage) and run.json (configuration and resume state). A run that was
interrupted resumes after its last finished stage; stages are seeded independently, so a resumed
run gives the same result as an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from .antialias import DILATION_KEY, FILTER_KEY, dilation_3d, filter_3d
from .atomic import atomic_write, atomic_write_text
from .camera import Camera, look_target
from .capture import Capture, SfMPoints, read_capture
from .cloud import GaussianCloud
from .conventions import SH_REST_COUNTS
from .datasets import Views
from .densify import DensifyStrategy, GaussianModel
from .initialization import INIT_MODES, coverage, initial_cloud, start_points
from .lineage import Lineage
from .losses import photometric_loss, psnr, ssim
from .plateau import Plateau
from .ply import read_ply, write_ply
from .rendering import RenderSettings, render, resolve_device
from .resources import current_rss_mb, estimate_train_memory, peak_rss_mb, reset_peak_rss, train_cap

#: Profiles: overrides of the `TrainConfig` defaults. `default` is the benchmark profile.
PROFILES: dict[str, dict[str, Any]] = {
    # a quick look (and the tests'): fixed counts, no training on until convergence
    "tiny": dict(resolutions=(32, 48, 64), iterations=(200, 150, 150), init_count=2000,
                 max_gaussians=10_000, sh_degree=1, converge=False),
    "default": dict(),
    # the default before issue 50: fixed iterations, no validation photos, no budget
    "legacy": dict(iterations=(600, 400, 400), validation_views=0, converge=False, gaussians_per_pixel=None,
                   lr_schedule="stage", carry_optimizer=False, opacity_resets=True),
    "full": dict(resolutions=(100, 200, 400, 800), iterations=(7000, 7000, 7000, 30000),
                 init="random", init_count=100_000, max_gaussians=None),
}


@dataclass
class TrainConfig:
    """Everything a progressive run depends on (JSON-serialisable; stored in run.json).

    Schedules given in `reference_iterations` units (the reference 30k-iteration run) are scaled
    to each stage's budget (see `stage_schedule`). `init`: where the first stage starts
    (`gvae_core.initialization`): "sfm" (the capture's SfM points, the reference's start for a
    COLMAP capture), "hull" (random points inside the visual hull of the training alpha masks),
    "random" (random points along the training rays, `init_count` of them), or "auto" (the
    default: sfm, else hull for images with transparent pixels, else random). `max_gaussians`:
    a cap on the count (None, the default: none but what memory allows, `resources.train_cap`;
    the reference has none, densification stops by its schedule). `test_every`: hold out every
    n-th image of a capture, sorted by name, as a test view (LLFF / Mip-NeRF 360: 8; None: a
    NeRF-Synthetic folder's test split, or none).
    `max_screen_fraction` (None) would prune Gaussians whose radius exceeds that fraction of the
    image height; the reference code's screen-size test never fires, so it is off by default.
    `antialias`: how stages render while they train: "classic" (the reference 3DGS) or "mip"
    (Mip-Splatting: the 3D filter of the stage's training cameras, recomputed every densification
    interval, and the 2D Mip filter). Every stage's snapshot PLY carries the size its render mode
    needs above the stage's resolution, from the stage's training cameras (`gvae_core.antialias`):
    `gvae_dilation_3D` for "classic" (rendered "matched"), `filter_3D` for "mip".

    Validation and convergence: `validation_views` of the training photos (at most one in eight;
    `split_validation`) are set aside, never trained on, and drawn every `validation_every`
    iterations (log.json's `validation_curve`). With `converge`, the last stage's
    `iterations` is its planned count (densification and the position learning rate's decay follow
    it as in any stage); past it, the stage trains on until the validation PSNR has not risen by
    `min_gain` dB for `patience` iterations (`gvae_core.plateau.Plateau`), `max_minutes` after the
    run began, or `max_iterations`, whichever comes first, and keeps the state its validation
    photos liked best (log.json: `stopped`, `best_step`). Without validation photos (too few
    photos, or `validation_views=0`) every count is fixed. `gaussians_per_pixel`: a budget of that
    many Gaussians per pixel of one training photo of the stage (beside `max_gaussians`)."""

    resolutions: tuple[int, ...] = (100, 150, 200)
    iterations: tuple[int, ...] = (300, 300, 1000)
    # Learning rates of the reference 3DGS (positions: times the scene extent).
    position_lr_init: float = 1.6e-4
    position_lr_final: float = 1.6e-6
    feature_lr: float = 2.5e-3
    feature_rest_lr: float = 2.5e-3 / 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    lambda_dssim: float = 0.2
    # Spherical harmonics: degree raised by one every `sh_interval` reference iterations.
    sh_degree: int = 3
    sh_interval: int = 1000
    # Density control (reference values).
    reference_iterations: int = 30_000
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    opacity_reset_every: int = 3000
    min_densify_every: int = 25
    min_opacity_reset_every: int = 300
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_world_size: float = 0.1
    max_screen_fraction: float | None = None
    reset_opacity_value: float = 0.01
    max_gaussians: int | None = None
    # Data, initialisation, evaluation.
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    init: str = "auto"
    init_count: int = 10_000
    init_opacity: float = 0.1
    train_eval_views: int = 10
    test_eval_views: int | None = None
    seed: int = 0
    antialias: str = "classic"
    test_every: int | None = None
    # Validation photos and convergence (`CONVERGENCE_FIELDS`: see the class docstring).
    validation_views: int = 8
    converge: bool = True
    max_iterations: int = 30_000
    validation_every: int = 100
    patience: int = 600
    min_gain: float = 0.05
    max_minutes: float | None = None
    # A budget that follows the photos: on the plush at 1/16, 1 per pixel (45k Gaussians) held out
    # 29.6 dB where no budget grew to 189k for 28.6 (docs/benchmarks/training.md).
    gaussians_per_pixel: float | None = 1.0
    # Across stages: the position learning rate decays over the whole run ("run") or afresh in each
    # stage ("stage"); Adam's moments carry from a stage to the next (the same rows) or restart.
    lr_schedule: str = "run"
    carry_optimizer: bool = True
    # The reference's periodic opacity reset (`opacity_reset_every`): off, the plush held out 0.1 dB
    # more in less time without it (docs/benchmarks/training.md).
    opacity_resets: bool = False

    def __post_init__(self):
        self.resolutions = tuple(int(r) for r in np.atleast_1d(self.resolutions))
        its = tuple(int(i) for i in np.atleast_1d(self.iterations))
        if len(its) == 1 and len(self.resolutions) > 1:
            its = its * len(self.resolutions)
        self.iterations = its
        self.background = tuple(float(b) for b in self.background)
        if not self.resolutions or any(r <= 0 for r in self.resolutions):
            raise ValueError(f"TrainConfig.resolutions must be positive image heights, got {self.resolutions}")
        if len(self.iterations) != len(self.resolutions) or any(i < 0 for i in self.iterations):
            raise ValueError(f"TrainConfig.iterations must be one count >= 0 or one per stage "
                             f"({len(self.resolutions)}), got {self.iterations}")
        if self.sh_degree not in SH_REST_COUNTS:
            raise ValueError(f"TrainConfig.sh_degree must be 0..3, got {self.sh_degree}")
        if self.init not in INIT_MODES:
            raise ValueError(f"TrainConfig.init must be one of {', '.join(INIT_MODES)}, got {self.init!r}")
        if self.test_every is not None and int(self.test_every) < 2:
            raise ValueError(f"TrainConfig.test_every must be 2 or more, got {self.test_every}")
        if len(self.background) != 3:
            raise ValueError(f"TrainConfig.background must be 3 values, got {self.background}")
        if self.antialias not in ("classic", "mip"):
            raise ValueError(f"TrainConfig.antialias must be 'classic' or 'mip', got {self.antialias!r}")
        if self.validation_views < 0 or self.validation_every <= 0 or self.patience <= 0 or self.min_gain < 0:
            raise ValueError("TrainConfig: validation_views must be >= 0, validation_every and patience positive, "
                             f"min_gain >= 0 (got {self.validation_views}, {self.validation_every}, {self.patience}, "
                             f"{self.min_gain})")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ValueError(f"TrainConfig.max_minutes must be positive or None, got {self.max_minutes}")
        if self.lr_schedule not in ("run", "stage"):
            raise ValueError(f"TrainConfig.lr_schedule must be 'run' or 'stage', got {self.lr_schedule!r}")
        if self.gaussians_per_pixel is not None and not self.gaussians_per_pixel > 0:
            raise ValueError("TrainConfig.gaussians_per_pixel must be positive or None, got "
                             f"{self.gaussians_per_pixel}")

    @classmethod
    def profile(cls, name: str = "default", **overrides) -> TrainConfig:
        """A named profile (`PROFILES`) with some fields overridden (None: the profile's)."""
        if name not in PROFILES:
            raise ValueError(f"unknown training profile {name!r}; choose from {sorted(PROFILES)}")
        values = {**PROFILES[name], **{k: v for k, v in overrides.items() if v is not None}}
        return cls(**values)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """A configuration `to_dict` wrote (a run.json's), the fields it leaves out at their
        `ADDED_FIELDS` values (a run from before they existed trained that way)."""
        return cls(**{**ADDED_FIELDS, **d})

    def learning_rates(self, extent: float) -> dict[str, float]:
        """Initial learning rate per parameter (positions relative to the scene extent)."""
        return {"means": self.position_lr_init * extent, "sh_dc": self.feature_lr, "sh_rest": self.feature_rest_lr,
                "opacities": self.opacity_lr, "scales": self.scaling_lr, "quats": self.rotation_lr}

    def densify_strategy(self) -> DensifyStrategy:
        return DensifyStrategy(grad_threshold=self.densify_grad_threshold, percent_dense=self.percent_dense,
                               prune_opacity=self.prune_opacity, max_world_size=self.max_world_size,
                               max_screen_fraction=self.max_screen_fraction, max_gaussians=self.max_gaussians)

    def to_dict(self) -> dict[str, Any]:
        """The configuration as JSON values. Fields added after run directories and experiment
        cache keys were first derived from this (`ADDED_FIELDS`) appear only when they differ from
        the value that trains as before they existed, so that a configuration that trains as before
        keeps its key (and its runs resume), and one that does not gets a new one."""
        d = json.loads(json.dumps(dataclasses.asdict(self)))
        for name, before in ADDED_FIELDS.items():
            if d[name] == json.loads(json.dumps(before)):
                del d[name]
        return d

    def sh_degree_at(self, iteration: int) -> int:
        """Active SH degree at an iteration of the whole run: one more every `sh_interval`
        reference iterations, scaled like the other schedules (to the whole run's budget)."""
        every = max(1, round(self.sh_interval * sum(self.iterations) / self.reference_iterations))
        return min(self.sh_degree, iteration // every)

    def stage_schedule(self, stage: int) -> dict[str, int]:
        """Iteration schedule of one stage: the reference schedule times iterations/30000, with
        floors on the densification and opacity-reset intervals (a too-short interval would
        leave no time to average gradients or to recover from a reset)."""
        n = self.iterations[stage]
        f = n / self.reference_iterations
        every = max(self.min_densify_every, round(self.densify_every * f))
        return dict(
            iterations=n,
            densify_every=every,
            densify_from=max(every, round(self.densify_from * f)),
            densify_until=round(self.densify_until * f),
            opacity_reset_every=max(self.min_opacity_reset_every, round(self.opacity_reset_every * f)),
        )


#: The file of a run directory with Adam's state at the end of its last finished stage (when
#: `carry_optimizer`), so that a resumed run carries it as an uninterrupted one does.
ADAM_FILE = "adam.npz"


#: `TrainConfig` fields added after run directories and experiment cache keys were first derived
#: from `to_dict`, with the value that trains as before they existed: `to_dict` writes them only
#: when they differ from it, `from_dict` fills them in with it.
ADDED_FIELDS: dict[str, Any] = {
    "antialias": "classic", "test_every": None,
    # issue 50: validation photos, a last stage that trains until they stop improving, a budget
    "validation_views": 0, "converge": False, "max_iterations": 30_000, "validation_every": 100, "patience": 600,
    "min_gain": 0.05, "max_minutes": None, "gaussians_per_pixel": None, "lr_schedule": "stage",
    "carry_optimizer": False, "opacity_resets": True,
}


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


# ------------------------------------------------------------------ data

@dataclass
class TrainingData:
    """What a run trains from: `views(split, height)` -> the split's views at that image height, or
    None when there is no such split; the capture's SfM points (None without); a line saying what
    it is; the capture's path (None for views in memory)."""

    views: Callable[[str, int], Views | None]
    points: SfMPoints | None = None
    description: str = "views given in memory"
    source: str | None = None


def training_data(data, test=None, test_every: int | None = None) -> TrainingData:
    """`data` as TrainingData: a capture (a path `capture.read_capture` reads: COLMAP, a
    transforms.json, a NeRF-Synthetic folder; or a `Capture`) with every `test_every`-th image held
    out, a (split, height) -> views function, or in-memory views (resampled to each height; `test`
    views likewise)."""
    if isinstance(data, TrainingData):
        return data
    if isinstance(data, (str, os.PathLike, Capture)):
        capture = (data if isinstance(data, Capture) else read_capture(data)).held_out(test_every)

        def views(split: str, height: int):
            return capture.load(split, height) if len(capture.indices(split)) else None

        return TrainingData(views, capture.points, capture.summary(), str(capture.source))
    if callable(data):
        return TrainingData(data)
    if not isinstance(data, Views) or not (test is None or isinstance(test, Views)):
        raise ValueError("train_progressive: data must be a capture (a COLMAP model, a transforms.json, a "
                         "NeRF-Synthetic folder), a (split, height) -> views function or gvae_core.datasets.Views")
    splits = {"train": data, "test": test}

    def source(split: str, height: int):
        v = splits.get(split)
        return None if v is None else v.at_resolution(height)

    return TrainingData(source)


# ------------------------------------------------------------------ geometry helpers

def scene_extent(cameras: list[Camera]) -> tuple[np.ndarray, float]:
    """The reference's camera normalisation: centre of the camera centres and 1.1 x the largest
    distance from it (the scale of positional learning rates and of densification)."""
    centers = np.stack([c.center for c in cameras])
    mid = centers.mean(0)
    radius = 1.1 * float(np.linalg.norm(centers - mid, axis=1).max())
    if radius < 1e-9:  # one camera: use its distance to the point it looks at
        radius = 1.1 * float(np.linalg.norm(look_target(cameras) - centers[0])) or 1.0
    return mid, radius


def position_lr(config: TrainConfig, extent: float, step: int, total: int) -> float:
    """Exponential (log-linear) decay from position_lr_init to position_lr_final, times extent."""
    t = min(max(step / max(total, 1), 0.0), 1.0)
    lr0, lr1 = config.position_lr_init, config.position_lr_final
    return extent * math.exp((1 - t) * math.log(lr0) + t * math.log(lr1))


# ------------------------------------------------------------------ training

def training_targets(views, background) -> torch.Tensor:
    """The views' photos composited on `background`, as the trainer's (N, H, W, 3) float tensor."""
    return torch.from_numpy(np.ascontiguousarray(views.composite(background)))


def evaluate_views(cloud: GaussianCloud, views, background, sh_degree: int, max_views: int | None = None,
                   settings: RenderSettings | None = None, *, with_ssim: bool = True) -> tuple[float, float]:
    """Mean PSNR and SSIM (NaN without `with_ssim`) over (up to `max_views` evenly spaced) views,
    images composited on background; NaN, NaN without views."""
    if views is None or len(views) == 0:
        return float("nan"), float("nan")
    n = len(views)
    pick = range(n) if max_views is None or max_views >= n else np.linspace(0, n - 1, max_views).round().astype(int)
    targets = torch.from_numpy(views.composite(background))
    psnrs, ssims = [], []
    with torch.no_grad():
        for i in pick:
            out = render(cloud, views.cameras[i], background=background, sh_degree=sh_degree, settings=settings)
            image = out.image.clamp(0, 1).cpu()
            psnrs.append(min(psnr(image, targets[i]), 100.0))
            if with_ssim:
                ssims.append(float(ssim(image, targets[i])))
    return float(np.mean(psnrs)), float(np.mean(ssims)) if ssims else float("nan")


def evaluate_psnr(cloud: GaussianCloud, views, background, sh_degree: int, max_views: int | None = None,
                  settings: RenderSettings | None = None) -> float:
    """Mean PSNR over (up to `max_views` evenly spaced) views, images composited on background."""
    return evaluate_views(cloud, views, background, sh_degree, max_views, settings, with_ssim=False)[0]


def _write_json(path: Path, obj) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2))


def _load_resume(out_dir: Path, config: TrainConfig):
    """(lineage, log, next_id) of the finished stages of an earlier run in `out_dir`, or None."""
    run_path = out_dir / "run.json"
    if not run_path.is_file():
        return None
    try:
        run = json.loads(run_path.read_text(encoding="utf-8"))
        saved_config, done, next_id = run["config"], int(run["stages_done"]), int(run["next_id"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{run_path}: not a training run state file ({exc})") from None
    if saved_config != config.to_dict():
        diff = sorted(k for k in set(saved_config) | set(config.to_dict())
                      if saved_config.get(k) != config.to_dict().get(k))
        raise ValueError(f"{out_dir}: holds a run with a different configuration ({', '.join(diff)}); "
                         "use another output directory or resume=False")
    if done == 0:
        return None
    lineage = Lineage.load(out_dir / "lineage.npz")
    log = json.loads((out_dir / "log.json").read_text(encoding="utf-8"))
    if lineage.n_stages < done or len(log) < done:
        raise ValueError(f"{out_dir}: run.json says {done} stage(s) are done but lineage.npz has "
                         f"{lineage.n_stages} and log.json {len(log)}")
    trimmed = Lineage(lineage.center, lineage.scale)
    for s in range(done):
        snap = lineage.snapshots[s]
        trimmed.add_stage(snap.cloud, snap.ids, snap.parents, lineage.resolutions[s])
    return trimmed, log[:done], next_id


def split_validation(views: Views, count: int) -> tuple[Views, Views | None]:
    """(training views, validation views): `count` of `views` (at most one in eight, evenly spaced,
    none of the first or last) set aside to judge convergence and choices, never trained on; the
    same photos at every image height. (views, None) when none is set aside."""
    n = len(views)
    k = min(int(count), n // 8)
    if k <= 0:
        return views, None
    pick = np.unique(np.round((np.arange(k) + 0.5) * n / k).astype(int).clip(0, n - 1))
    rest = np.setdiff1d(np.arange(n), pick)
    return _select(views, rest), _select(views, pick)


def _select(views: Views, rows: np.ndarray) -> Views:
    return Views([views.cameras[i] for i in rows], views.images[rows],
                 None if views.alphas is None else views.alphas[rows],
                 None if views.names is None else [views.names[i] for i in rows])


#: Called by `train_progressive` and `train_more` with a progress report (a dict: `PROGRESS_KEYS` and,
#: when just measured, "validation_psnr", "train_psnr", "test_psnr", "test_ssim"); an exception it
#: raises stops training (the finished stages stay on disk and a later call resumes after them).
ProgressHook = Callable[[dict[str, Any]], None]
#: The keys of every progress report: stage (0-based) of stages, step (iterations done in the stage)
#: of steps (its planned count; while the last stage trains until it converges, the most it may
#: take), n_gaussians, and a message for people.
PROGRESS_KEYS = ("stage", "stages", "step", "steps", "n_gaussians", "message")


def train_progressive(data, config: TrainConfig | None = None, *, out_dir=None, test=None,
                      init_points=None, resume: bool = True, progress: bool = True,
                      threads: int | None = None, device=None, on_progress: ProgressHook | None = None) -> TrainResult:
    """Train 3DGS coarse-to-fine over `config.resolutions`, recording lineages.

    `data`: a capture (a COLMAP model with its images, a transforms.json, a NeRF-Synthetic folder;
    `training_data`), in-memory views (cameras, images, alphas; with optional `test` views), or a
    function (split, height) -> views. `init_points`: optional (N,3)/(N,6) initial points instead of
    `config.init`'s (`gvae_core.initialization`). With `out_dir`, stage PLYs, lineage.npz,
    log.json and run.json are written there after every stage and an interrupted run resumes
    (unless `resume` is False, which starts over). `threads`: torch CPU threads while training
    (restored afterwards); on a busy machine 1 is often much faster than oversubscribing. `device`:
    the torch device to train on (default the CPU; "cuda" with a CUDA build of torch and a GPU);
    the random draws are the CPU's on any device. `on_progress` (`ProgressHook`): about every 10
    iterations, at every validation and at every stage's end; an exception it raises stops the run
    cleanly (what `out_dir` holds resumes)."""
    previous_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    try:
        return _train(data, config or TrainConfig(), out_dir, test, init_points, resume, progress,
                      resolve_device(device), on_progress)
    finally:
        torch.set_num_threads(previous_threads)


def _train(data, config: TrainConfig, out_dir, test, init_points, resume: bool, progress: bool,
           device: torch.device, on_progress: ProgressHook | None) -> TrainResult:
    started = time.perf_counter()
    data = training_data(data, test, config.test_every)
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        if not resume and (out / "run.json").exists():
            (out / "run.json").unlink()

    state = _load_resume(out, config) if out is not None else None
    lineage, log, next_id = state if state else (Lineage(), [], 0)
    first_stage = lineage.n_stages
    stage_paths = [out / f"stage_{s}.ply" for s in range(first_stage)] if out is not None else []
    bg = config.background
    model: GaussianModel | None = None
    say = tqdm.write if progress else (lambda message: None)
    say(data.description)
    settings = RenderSettings(antialias=config.antialias)
    # What every snapshot stores for rendering above its resolution (`gvae_core.antialias`): the
    # Mip filter of a run trained with it, else the classic dilation in world units.
    size_key, size_fn = (FILTER_KEY, filter_3d) if config.antialias == "mip" else (DILATION_KEY, dilation_3d)
    final_size = None
    global_iter = sum(config.iterations[:first_stage])
    n_stages = len(config.resolutions)
    carried = None  # Adam's state at the end of the previous stage

    for s in range(first_stage, n_stages):
        height = config.resolutions[s]
        all_views = data.views("train", height)
        if all_views is None or len(all_views) == 0:
            raise ValueError("train_progressive: no training views")
        train_views, val_views = split_validation(all_views, config.validation_views)
        _, extent = scene_extent(train_views.cameras)
        rng = np.random.default_rng([config.seed, s])
        gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        start = {}
        if s == 0:
            if val_views is not None:
                say(f"validation: {len(val_views)} of the {len(all_views)} training photos set aside (never "
                    "trained on) to judge when training stops helping")
            init_rng = np.random.default_rng([config.seed, 1_000_003])
            if init_points is None:
                init_points, what = start_points(train_views, config, init_rng, data.points)
            else:
                what = f"{len(init_points)} points given"
            cloud = initial_cloud(config, init_points)
            covered = coverage(cloud, train_views)
            start = {"start": what, "start_coverage": round(float(covered.mean()), 6),
                     "start_coverage_min": round(float(covered.mean((1, 2)).min()), 6)}
            say(f"start: {what}; it covers {covered.mean():.2%} of the training pixels (the least covered view "
                f"{start['start_coverage_min']:.2%})")
            ids, parents = np.arange(len(cloud), dtype=np.int64), np.full(len(cloud), -1, np.int64)
            next_id = len(cloud)
        else:
            snap = lineage.snapshots[-1]
            cloud, ids, parents = snap.cloud, snap.ids, snap.ids  # survivors are their own anchors
        model = GaussianModel(cloud, ids, parents, config.learning_rates(extent), extent, next_id, device)
        if s > 0 and config.carry_optimizer:
            if carried is None and out is not None and (out / ADAM_FILE).is_file():  # resumed
                with np.load(out / ADAM_FILE) as z:
                    carried = dict(z)
            model.load_optimizer_state(carried or {})
        cam0 = train_views.cameras[0]
        limit, why = _gaussian_limit(config, len(train_views), cam0)
        strategy = dataclasses.replace(config.densify_strategy(), max_gaussians=limit)
        need = estimate_train_memory(len(cloud), len(train_views), cam0.height, cam0.width, config.sh_degree)
        say(f"stage {s + 1}: {len(train_views)} views of {cam0.width}x{cam0.height}, {len(cloud)} Gaussians; memory "
            f"about {need / 2**30:.2f} GiB now, at most {limit} Gaussians ({why})")
        sched = config.stage_schedule(s)
        converging = config.converge and s == n_stages - 1 and val_views is not None
        if converging:
            sched["iterations"] = max(config.max_iterations, sched["iterations"])
        targets = training_targets(train_views, bg).to(device)
        cams = train_views.cameras
        planned = config.iterations[s]
        n_max = sched["iterations"]
        test_views = data.views("test", height) if converging else None
        watch = None if val_views is None else _Watch(config, val_views, cams, bg, settings, started, planned,
                                                      converging, say, test_views)
        report = _reporter(on_progress, s, n_stages, n_max, model)
        reset_ok = reset_peak_rss()
        rss_before = peak_rss_mb()
        rss_start = current_rss_mb()
        bar = _progress_bar(n_max if not converging else planned, f"stage {s + 1}/{n_stages} {height}px", progress)
        report(0, f"stage {s + 1}/{n_stages} at {height} px: {len(train_views)} photos, {len(cloud)} Gaussians")
        t0, c0 = time.perf_counter(), time.process_time()
        degree_at = functools.partial(_degree_at, config, global_iter)
        lr_window = (global_iter, sum(config.iterations)) if config.lr_schedule == "run" else (0, planned)
        check = None if watch is None else functools.partial(_check, watch, model, degree_at, report)
        step_report = functools.partial(_step_report, report, f"stage {s + 1}/{n_stages}")
        counts = _optimise(model, cams, targets, config, sched, rng, gen, settings, height, degree_at, bar=bar,
                           densify=strategy, progress=step_report, check=check,
                           check_every=config.validation_every, lr_window=lr_window)
        n_iter = counts.pop("iterations")
        global_iter += planned
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        if bar is not None:
            bar.close()
        stopped = counts.pop("stopped")
        if watch is not None and watch.best_params is not None and converging:
            model.load_params(watch.best_params)  # the state the validation photos liked best
        carried = model.optimizer_state() if config.carry_optimizer and s < n_stages - 1 else None
        peak = peak_rss_mb() if reset_ok else max(peak_rss_mb(), rss_before)

        snap_cloud = model.snapshot().replace(background=bg)
        ids_np, parents_np = snap_cloud.extra["gvae_id"], snap_cloud.extra["gvae_parent"]
        final_size = size_fn(snap_cloud.means, cams)  # the stage's training cameras
        snap_cloud = snap_cloud.replace(extra={**snap_cloud.extra, size_key: final_size})
        lineage.add_stage(snap_cloud.replace(extra={}), ids_np, parents_np, height)
        lineage.set_normalization(*snap_cloud.normalization())
        next_id = model.next_id
        degree = config.sh_degree_at(global_iter)
        torch_cloud = snap_cloud.replace(extra={size_key: final_size}).to_torch(device=device)
        t1 = time.perf_counter()
        train_psnr = evaluate_psnr(torch_cloud, train_views, bg, degree, config.train_eval_views, settings)
        val_psnr = evaluate_psnr(torch_cloud, val_views, bg, degree, None, settings)
        test_psnr, test_ssim = evaluate_views(torch_cloud, data.views("test", height), bg, degree,
                                              config.test_eval_views, settings)
        entry = {"stage": s, "resolution": height, "iterations": n_iter, "seconds": round(seconds, 3),
                 "seconds_per_iteration": round(seconds / max(n_iter, 1), 5),
                 "cpu_seconds": round(cpu_seconds, 3),
                 "n_gaussians": len(snap_cloud), "train_psnr": round(train_psnr, 4),
                 "test_psnr": _rounded(test_psnr, 4), "test_ssim": _rounded(test_ssim, 5),
                 "gaussian_limit": limit, **start,
                 "peak_rss_mb": round(peak, 1), "rss_start_mb": round(rss_start, 1), "peak_rss_exact": reset_ok,
                 "sh_degree": degree,
                 "eval_seconds": round(time.perf_counter() - t1, 3), "next_id": next_id, **counts}
        if watch is not None:
            entry.update(validation_views=len(val_views), validation_psnr=_rounded(val_psnr, 4),
                         **watch.summary(stopped if converging else None, n_iter))
        log.append(entry)
        if converging:
            said = entry.get("test_psnr_at_planned")
            held = "" if math.isnan(test_psnr) else f", held-out {test_psnr:.2f} dB" + (
                f" (at step {said[0]}: {said[1]:.2f})" if said else "")
            say(f"stage {s + 1}: {entry['stopped']}; kept step {entry['best_step']}: validation {val_psnr:.2f} dB{held}"
                f", {len(snap_cloud)} Gaussians")
        report(n_iter, f"stage {s + 1}/{n_stages} done: {len(snap_cloud)} Gaussians",
               train_psnr=_rounded(train_psnr, 4), validation_psnr=_rounded(val_psnr, 4),
               test_psnr=_rounded(test_psnr, 4), test_ssim=_rounded(test_ssim, 5))
        if out is not None:
            stage_paths.append(write_ply(snap_cloud, out / f"stage_{s}.ply"))
            if carried is not None:
                atomic_write(out / ADAM_FILE, lambda f, state=carried: np.savez(f, **state))
            lineage.save(out / "lineage.npz")
            _write_json(out / "log.json", log)
            _write_json(out / "run.json", {"config": config.to_dict(), "stages_done": s + 1,
                                           "next_id": next_id, "data": data.source})

    final = lineage.stage_cloud(lineage.n_stages - 1)
    if final_size is None:  # every stage was done already: the size is in the last stage's PLY
        final_size = _stage_size(out, lineage.n_stages - 1, final, data, config, size_key, size_fn)
    final = final.replace(extra={**final.extra, size_key: final_size}, background=bg)
    return TrainResult(final, lineage, log, out, stage_paths)


def _degree_at(config: TrainConfig, first: int, it: int) -> int:
    """The SH degree at iteration `it` (1-based) of a stage that begins after `first` iterations."""
    return config.sh_degree_at(first + it - 1)


def _check(watch: _Watch, model: GaussianModel, degree_at, report, it: int) -> str | None:
    return watch.check(model, it, degree_at(it), report)


def _step_report(report, what: str, it: int) -> None:
    report(it, f"{what}: step {it}")


def _rounded(x: float, digits: int) -> float | None:
    return None if x is None or math.isnan(x) else round(float(x), digits)


def _gaussian_limit(config: TrainConfig, n_views: int, camera: Camera) -> tuple[int, str]:
    """The most Gaussians a stage may grow to, and why: what memory allows (`resources.train_cap`),
    `config.max_gaussians`, and `gaussians_per_pixel` times the pixels of one training photo."""
    limits = [(train_cap(n_views, camera.height, camera.width, config.sh_degree), "what memory allows")]
    if config.max_gaussians is not None:
        limits.append((int(config.max_gaussians), "max_gaussians"))
    if config.gaussians_per_pixel is not None:
        limits.append((max(1, round(config.gaussians_per_pixel * camera.width * camera.height)),
                       f"{config.gaussians_per_pixel:g} per pixel of a photo"))
    return min(limits)


def _reporter(hook: ProgressHook | None, stage: int, stages: int, steps: int, model: GaussianModel):
    """report(step, message, **measured) -> `hook` with the `PROGRESS_KEYS` (a no-op without a hook)."""
    def report(step: int, message: str, **measured) -> None:
        if hook is not None:
            hook({"stage": stage, "stages": stages, "step": int(step), "steps": int(steps), "n_gaussians": len(model),
                  "message": message, **{k: v for k, v in measured.items() if v is not None}})
    return report


class _Watch:
    """The validation photos of a stage: their PSNR every `validation_every` iterations (the curve,
    the best state's parameters) and, for the stage that trains until it converges, why it stops:
    the `Plateau` rule once the planned iterations are done, or the time budget."""

    def __init__(self, config: TrainConfig, views: Views, cameras: list[Camera], background, settings: RenderSettings,
                 started: float, planned: int, converging: bool, say, test_views: Views | None = None):
        self.views, self.cameras, self.background, self.settings = views, cameras, background, settings
        self.test_views, self.test_at_planned = test_views, None
        self.plateau = Plateau(patience=config.patience, min_gain=config.min_gain)
        self.deadline = None if config.max_minutes is None else started + 60.0 * config.max_minutes
        self.planned, self.converging, self.say = planned, converging, say
        self.curve: list[tuple[int, float]] = []
        self.best, self.best_step, self.best_params = -math.inf, 0, None

    def check(self, model: GaussianModel, it: int, degree: int, report) -> str | None:
        current = model.cloud().detach()
        if self.settings.antialias == "mip":  # drawn as training draws it: with the training cameras' filter
            current = current.replace(extra={FILTER_KEY: _model_filter(model, self.cameras)})
        value = evaluate_psnr(current, self.views, self.background, degree, None, self.settings)
        self.curve.append((it, round(value, 4)))
        message = f"step {it}: validation photos {value:.2f} dB, {len(model)} Gaussians"
        self.say(message)
        report(it, message, validation_psnr=round(value, 4))
        if not self.converging:
            return None
        if it >= self.planned and value > self.best:  # (the best state once densification is over)
            self.best, self.best_step = value, it
            self.best_params = {n: p.detach().clone() for n, p in model.params.items()}
        if it < self.planned:
            return None
        if self.test_at_planned is None and self.test_views is not None:  # said in the log, never decides
            self.test_at_planned = (it, evaluate_psnr(current, self.test_views, self.background, degree, None,
                                                      self.settings))
        if self.plateau.update(it, value):
            return f"converged: {self.plateau.reason}"
        if self.deadline is not None and time.perf_counter() > self.deadline:
            return "stopped by the time budget (max_minutes)"
        return None

    def summary(self, stopped: str | None, iterations: int) -> dict[str, Any]:
        out: dict[str, Any] = {"validation_curve": self.curve}
        if self.converging:
            out["stopped"] = stopped or f"reached max_iterations ({iterations})"
            out["best_step"] = self.best_step if self.best_params is not None else iterations
            if self.test_at_planned is not None:
                out["test_psnr_at_planned"] = [self.test_at_planned[0], round(self.test_at_planned[1], 4)]
        return out


class ParameterAverage:
    """The running average of a model's parameters over the iterations (Polyak averaging, with
    exponential weights): a step trains on one photo, so the last iterate carries that photo's pull
    (on the plush the set-aside PSNR of successive checks of a fine-tune moved by up to 0.3 dB);
    the average of the last 1 / (1 - `decay`) or so steps does not. The decay at step t is
    min(`decay`, (1 + t) / (10 + t)): the first steps weigh more, so the start is soon forgotten."""

    def __init__(self, model: GaussianModel, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ParameterAverage: decay must be in (0, 1), got {decay!r}")
        self.decay, self.steps = float(decay), 0
        self.values = {name: p.detach().clone() for name, p in model.params.items()}

    def update(self, model: GaussianModel) -> None:
        """Take in the model's current parameters (after an optimiser step; the same rows)."""
        self.steps += 1
        d = min(self.decay, (1.0 + self.steps) / (10.0 + self.steps))
        for name, p in model.params.items():
            self.values[name].mul_(d).add_(p.detach(), alpha=1.0 - d)

    def cloud(self) -> GaussianCloud:
        """The averaged parameters as a torch cloud (shared, not copied)."""
        return GaussianCloud(**self.values)


def _optimise(model: GaussianModel, cams: list[Camera], targets: torch.Tensor, config: TrainConfig, sched: dict,
              rng: np.random.Generator, gen: torch.Generator, settings: RenderSettings, height: int,
              degree_at: Callable[[int], int], *, densify: DensifyStrategy | None, bar=None,
              progress: Callable[[int], None] | None = None, check: Callable[[int], str | None] | None = None,
              check_every: int = 100, lr_window: tuple[int, int] | None = None,
              average: ParameterAverage | None = None) -> dict[str, Any]:
    """One stage's iterations (`sched`, `TrainConfig.stage_schedule`) on `model`: the reference
    recipe (views in random order without repetition, the position learning rate decaying over
    the stage or, with `lr_window` = (offset, horizon), as at iteration offset + it of a decay
    over horizon iterations, staying at its final value after; 0.8·L1 + 0.2·(1 − SSIM)), with the
    `densify` strategy's density control and opacity resets when given, without any when None (a
    fine-tune keeps its Gaussians); `average` takes in every step (used without `densify`: the same
    rows throughout). `degree_at(it)`: the SH degree at the stage's iteration `it` (1-based);
    `progress(it)` every 10 iterations; `check(it)` every `check_every` iterations: a reason to
    stop, or None. Returns the counts of cloned, split and pruned Gaussians, the iterations done
    and why it stopped early (None: it did not)."""
    counts: dict[str, Any] = {"cloned": 0, "split": 0, "pruned": 0}
    n_iter, bg = sched["iterations"], config.background
    offset, horizon = (0, n_iter) if lr_window is None else lr_window
    order: list[int] = []
    filt = _model_filter(model, cams) if config.antialias == "mip" else None
    stopped, it = None, 0
    for it in range(1, n_iter + 1):
        model.set_lr("means", position_lr(config, model.extent, offset + it - 1, horizon))
        if not order:
            order = list(rng.permutation(len(cams)))
        v = int(order.pop())
        current = model.cloud() if filt is None else model.cloud().replace(extra={FILTER_KEY: filt})
        result = render(current, cams[v], background=bg, sh_degree=degree_at(it), settings=settings)
        means2d = result.means2d
        if means2d.requires_grad:
            means2d.retain_grad()
        loss = photometric_loss(result.image, targets[v], config.lambda_dssim)
        loss.backward()
        with torch.no_grad():
            grad2d = means2d.grad if means2d.grad is not None else torch.zeros_like(means2d)
            model.add_stats(grad2d, result.visible, result.radii, cams[v].width, cams[v].height)
            model.optimizer.step()
            model.optimizer.zero_grad(set_to_none=True)
            if average is not None:
                average.update(model)
            if densify is not None and sched["densify_from"] <= it <= sched["densify_until"]:
                if it % sched["densify_every"] == 0 and it < n_iter:
                    done = densify.densify_and_prune(model, gen, image_height=height,
                                                     prune_large=it > sched["opacity_reset_every"])
                    for k in ("cloned", "split", "pruned"):
                        counts[k] += done[k]
                if (config.opacity_resets and it % sched["opacity_reset_every"] == 0
                        and it < sched["densify_until"]):
                    model.reset_opacity(config.reset_opacity_value)
            if filt is not None and (it % sched["densify_every"] == 0 or len(filt) != len(model)):
                filt = _model_filter(model, cams)  # after densification, and as the centres move
        if it % 10 == 0 or it == n_iter:
            if bar is not None:
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", psnr=f"{psnr(result.image, targets[v]):.2f}",
                                n=len(model))
                bar.update(10 if it % 10 == 0 else it % 10)
            if progress is not None:
                progress(it)
        if check is not None and it % check_every == 0:
            with torch.no_grad():
                stopped = check(it)
            if stopped is not None:
                break
    counts.update(iterations=it, stopped=stopped)
    return counts


def fine_tune(cloud: GaussianCloud, views: Views, iterations: int, *, config: TrainConfig | None = None,
              seed: int = 0, progress: Callable[[float, str], None] | None = None, device=None,
              should_stop: Callable[[int, GaussianCloud], bool] | None = None,
              check_every: int = 100, average: float | None = None) -> GaussianCloud:
    """`cloud` trained on `views` (at their resolution) for `iterations` more iterations with
    the trainer's recipe and one stage's schedule (`_optimise`: its learning rates, the position
    rate decaying over the iterations, the anti-aliasing of `config.antialias`), without density
    control: the Gaussians stay the same rows, only their parameters change (how PUP 3D-GS
    fine-tunes after pruning). The SH degree is the cloud's. Returns a numpy cloud with the input's
    extra properties, its anti-aliasing size (`gvae_dilation_3D`, or `filter_3D` when
    `config.antialias` is "mip") recomputed from the views' cameras. `progress(fraction, message)`
    every 10 iterations (an exception it raises stops the fine-tune). `should_stop(iteration,
    cloud)` every `check_every` iterations, with the current cloud (torch, detached, as it is
    drawn while training): True ends the fine-tune there (for example a `gvae_core.plateau.Plateau`
    on a validation PSNR). `average` (a decay in (0, 1)): the result, and what `should_stop` sees,
    is the running average of the iterates (`ParameterAverage`) instead of the last one."""
    config = config or TrainConfig()
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError(f"fine_tune: iterations must be >= 0, got {iterations}")
    if check_every <= 0:
        raise ValueError(f"fine_tune: check_every must be positive, got {check_every}")
    if len(views) == 0:
        raise ValueError("fine_tune: no views")
    src = cloud.numpy()
    dev = resolve_device(device)
    config = dataclasses.replace(config, resolutions=(views.cameras[0].height,), iterations=(iterations,),
                                 sh_degree=src.sh_degree)
    rng = np.random.default_rng([seed, 7_000_003])
    gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
    _, extent = scene_extent(views.cameras)
    model = GaussianModel(src.replace(extra={}), np.arange(len(src)), np.full(len(src), -1),
                          config.learning_rates(extent), extent, len(src), dev)
    sched = config.stage_schedule(0)
    mean = None if average is None else ParameterAverage(model, average)
    say = (lambda it: progress(it / max(iterations, 1), f"fine-tuning {it}/{iterations}")) if progress else None
    check = None
    if should_stop is not None:
        def check(it: int) -> str | None:
            current = (model.cloud() if mean is None else mean.cloud()).detach()
            if config.antialias == "mip":  # (the filter of the centres drawn)
                current = current.replace(extra={FILTER_KEY: _centres_filter(current.means, views.cameras)})
            return "should_stop" if should_stop(it, current) else None
    targets = training_targets(views, config.background).to(dev)
    _optimise(model, views.cameras, targets, config, sched, rng, gen,
              RenderSettings(antialias=config.antialias), views.cameras[0].height, lambda it: src.sh_degree,
              densify=None, progress=say, check=check, check_every=check_every, average=mean)
    if mean is not None:
        model.load_params(mean.values)
    out = model.snapshot()
    key, size_fn = (FILTER_KEY, filter_3d) if config.antialias == "mip" else (DILATION_KEY, dilation_3d)
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
    control a refinement at the same count is judged against). Writes `stage_<s>_more_<iterations>.ply`
    and appends the entry to `more.json`. `on_progress`: as `train_progressive`'s."""
    out = Path(run_dir)
    run_path = out / "run.json"
    if not run_path.is_file():
        raise ValueError(f"{out}: not a training run (no run.json)")
    try:
        run = json.loads(run_path.read_text(encoding="utf-8"))
        config, done, source = TrainConfig.from_dict(run["config"]), int(run["stages_done"]), run.get("data")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{run_path}: not a training run state file ({exc})") from None
    stage = done - 1 if stage is None else int(stage)
    if not 0 <= stage < done:
        raise ValueError(f"{out}: stage {stage} is not finished ({done} stage(s) are)")
    if source is None:
        raise ValueError(f"{run_path}: the run does not say what it was trained from (trained from views in memory, "
                         "or by a version that did not store it)")
    data = training_data(source, test_every=config.test_every)
    height = config.resolutions[stage]
    views, val_views = split_validation(data.views("train", height), config.validation_views)
    cloud = read_ply(out / f"stage_{stage}.ply")
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    bar = _progress_bar(int(iterations), f"stage {stage + 1} +{iterations}", progress)
    last = [0]

    def advance(fraction: float, message: str) -> None:
        done_now = int(round(fraction * int(iterations)))
        if bar is not None:
            bar.update(done_now - last[0])
        last[0] = done_now
        if on_progress is not None:
            on_progress({"stage": stage, "stages": done, "step": done_now, "steps": int(iterations),
                         "n_gaussians": len(cloud), "message": f"stage {stage + 1}: {message}"})

    try:
        t0 = time.perf_counter()
        tuned = fine_tune(cloud, views, iterations, config=config, seed=config.seed, progress=advance, device=device)
        seconds = time.perf_counter() - t0
    finally:
        torch.set_num_threads(previous)
        if bar is not None:
            bar.close()
    tuned = tuned.replace(background=config.background)
    settings = RenderSettings(antialias=config.antialias)
    dev = tuned.to_torch(device=resolve_device(device))
    train_psnr = evaluate_psnr(dev, views, config.background, tuned.sh_degree, config.train_eval_views, settings)
    val_psnr = evaluate_psnr(dev, val_views, config.background, tuned.sh_degree, None, settings)
    test_psnr, test_ssim = evaluate_views(dev, data.views("test", height), config.background, tuned.sh_degree,
                                          config.test_eval_views, settings)
    path = write_ply(tuned, out / f"stage_{stage}_more_{int(iterations)}.ply")
    entry = {"stage": stage, "resolution": height, "more": int(iterations), "seconds": round(seconds, 3),
             "n_gaussians": len(tuned), "train_psnr": round(train_psnr, 4),
             "validation_psnr": _rounded(val_psnr, 4),
             "test_psnr": _rounded(test_psnr, 4), "test_ssim": _rounded(test_ssim, 5), "file": path.name}
    more_path = out / "more.json"
    entries = json.loads(more_path.read_text(encoding="utf-8")) if more_path.is_file() else []
    _write_json(more_path, [e for e in entries if e.get("file") != path.name] + [entry])
    if on_progress is not None:
        on_progress({"stage": stage, "stages": done, "step": int(iterations), "steps": int(iterations),
                     "n_gaussians": len(tuned), "message": f"stage {stage + 1}: {iterations} more iterations done",
                     **{k: entry[k] for k in ("train_psnr", "validation_psnr", "test_psnr", "test_ssim")
                        if entry[k] is not None}})
    return MoreResult(tuned, path, entry)


def _model_filter(model: GaussianModel, cameras: list[Camera]) -> torch.Tensor:
    return _centres_filter(model.params["means"].detach(), cameras)


def _centres_filter(means: torch.Tensor, cameras: list[Camera]) -> torch.Tensor:
    """Mip-Splatting's 3D filter of Gaussians at `means` for `cameras`, on the device of `means`."""
    return torch.from_numpy(filter_3d(means.cpu().numpy(), cameras)).to(means.device)


def _stage_size(out: Path | None, stage: int, cloud: GaussianCloud, data: TrainingData, config: TrainConfig,
                key: str, size_fn) -> np.ndarray:
    """The anti-aliasing size of a finished stage: from its PLY, or (a run from before the size
    was stored) from the stage's training cameras."""
    if out is not None and (out / f"stage_{stage}.ply").is_file():
        saved = read_ply(out / f"stage_{stage}.ply")
        if key in saved.extra and len(saved) == len(cloud):
            return np.asarray(saved.extra[key], np.float32)
    views, _ = split_validation(data.views("train", config.resolutions[stage]), config.validation_views)
    return size_fn(cloud.means, views.cameras)


def _progress_bar(total: int, desc: str, enabled: bool):
    if not enabled:
        return None

    return tqdm(total=total, desc=desc, leave=True, dynamic_ncols=True)
