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
from .atomic import atomic_write_text
from .camera import Camera, look_target
from .capture import Capture, SfMPoints, read_capture
from .cloud import GaussianCloud
from .conventions import SH_REST_COUNTS
from .datasets import Views
from .densify import DensifyStrategy, GaussianModel
from .initialization import INIT_MODES, coverage, initial_cloud, start_points
from .lineage import Lineage
from .losses import photometric_loss, psnr, ssim
from .ply import read_ply, write_ply
from .rendering import RenderSettings, render, resolve_device
from .resources import current_rss_mb, estimate_train_memory, peak_rss_mb, reset_peak_rss, train_cap

#: Profiles: overrides of the `TrainConfig` defaults. `default` is the benchmark profile.
PROFILES: dict[str, dict[str, Any]] = {
    "tiny": dict(resolutions=(32, 48, 64), iterations=(200, 150, 150), init_count=2000,
                 max_gaussians=10_000, sh_degree=1),
    "default": dict(),
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
    `gvae_dilation_3D` for "classic" (rendered "matched"), `filter_3D` for "mip"."""

    resolutions: tuple[int, ...] = (100, 150, 200)
    iterations: tuple[int, ...] = (600, 400, 400)
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

    @classmethod
    def profile(cls, name: str = "default", **overrides) -> TrainConfig:
        """A named profile (`tiny`, `default`, `full`) with some fields overridden."""
        if name not in PROFILES:
            raise ValueError(f"unknown training profile {name!r}; choose from {sorted(PROFILES)}")
        values = {**PROFILES[name], **{k: v for k, v in overrides.items() if v is not None}}
        return cls(**values)

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
        their default, so that existing runs keep their keys and still resume."""
        d = json.loads(json.dumps(dataclasses.asdict(self)))
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        for name in ADDED_FIELDS:
            if getattr(self, name) == defaults[name]:
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


#: `TrainConfig` fields that `to_dict` writes only when they are not at their default.
ADDED_FIELDS = ("antialias", "test_every")


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

def _targets(views, background) -> torch.Tensor:
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


def train_progressive(data, config: TrainConfig | None = None, *, out_dir=None, test=None,
                      init_points=None, resume: bool = True, progress: bool = True,
                      threads: int | None = None, device=None) -> TrainResult:
    """Train 3DGS coarse-to-fine over `config.resolutions`, recording lineages.

    `data`: a capture (a COLMAP model with its images, a transforms.json, a NeRF-Synthetic folder;
    `training_data`), in-memory views (cameras, images, alphas; with optional `test` views), or a
    function (split, height) -> views. `init_points`: optional (N,3)/(N,6) initial points instead of
    `config.init`'s (`gvae_core.initialization`). With `out_dir`, stage PLYs, lineage.npz,
    log.json and run.json are written there after every stage and an interrupted run resumes
    (unless `resume` is False, which starts over). `threads`: torch CPU threads while training
    (restored afterwards); on a busy machine 1 is often much faster than oversubscribing. `device`:
    the torch device to train on (default the CPU; "cuda" with a CUDA build of torch and a GPU);
    the random draws are the CPU's on any device."""
    previous_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    try:
        return _train(data, config or TrainConfig(), out_dir, test, init_points, resume, progress,
                      resolve_device(device))
    finally:
        torch.set_num_threads(previous_threads)


def _train(data, config: TrainConfig, out_dir, test, init_points, resume: bool, progress: bool,
           device: torch.device) -> TrainResult:
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

    for s in range(first_stage, len(config.resolutions)):
        height = config.resolutions[s]
        train_views = data.views("train", height)
        if train_views is None or len(train_views) == 0:
            raise ValueError("train_progressive: no training views")
        _, extent = scene_extent(train_views.cameras)
        rng = np.random.default_rng([config.seed, s])
        gen = torch.Generator().manual_seed(int(rng.integers(2 ** 62)))
        start = {}
        if s == 0:
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
        cam0 = train_views.cameras[0]
        cap = train_cap(len(train_views), cam0.height, cam0.width, config.sh_degree)
        limit = cap if config.max_gaussians is None else min(cap, config.max_gaussians)
        strategy = dataclasses.replace(config.densify_strategy(), max_gaussians=limit)
        need = estimate_train_memory(len(cloud), len(train_views), cam0.height, cam0.width, config.sh_degree)
        say(f"stage {s + 1}: {len(train_views)} views of {cam0.width}x{cam0.height}, {len(cloud)} Gaussians; memory "
            f"about {need / 2**30:.2f} GiB now, at most {limit} Gaussians"
            + (" (what memory allows)" if limit == cap else ""))
        sched = config.stage_schedule(s)
        targets = _targets(train_views, bg).to(device)
        cams = train_views.cameras
        n_iter = sched["iterations"]
        reset_ok = reset_peak_rss()
        rss_before = peak_rss_mb()
        rss_start = current_rss_mb()
        bar = _progress_bar(n_iter, f"stage {s + 1}/{len(config.resolutions)} {height}px", progress)
        t0, c0 = time.perf_counter(), time.process_time()
        counts = _optimise(model, cams, targets, config, sched, rng, gen, settings, height,
                           lambda it, start=global_iter: config.sh_degree_at(start + it - 1), bar=bar,
                           densify=strategy)
        global_iter += n_iter
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        if bar is not None:
            bar.close()
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
        test_psnr, test_ssim = evaluate_views(torch_cloud, data.views("test", height), bg, degree,
                                              config.test_eval_views, settings)
        entry = {"stage": s, "resolution": height, "iterations": n_iter, "seconds": round(seconds, 3),
                 "seconds_per_iteration": round(seconds / max(n_iter, 1), 5),
                 "cpu_seconds": round(cpu_seconds, 3),
                 "n_gaussians": len(snap_cloud), "train_psnr": round(train_psnr, 4),
                 "test_psnr": None if math.isnan(test_psnr) else round(test_psnr, 4),
                 "test_ssim": None if math.isnan(test_ssim) else round(test_ssim, 5),
                 "gaussian_limit": limit, **start,
                 "peak_rss_mb": round(peak, 1), "rss_start_mb": round(rss_start, 1), "peak_rss_exact": reset_ok,
                 "sh_degree": degree,
                 "eval_seconds": round(time.perf_counter() - t1, 3), "next_id": next_id, **counts}
        log.append(entry)
        if out is not None:
            stage_paths.append(write_ply(snap_cloud, out / f"stage_{s}.ply"))
            lineage.save(out / "lineage.npz")
            _write_json(out / "log.json", log)
            _write_json(out / "run.json", {"config": config.to_dict(), "stages_done": s + 1,
                                           "next_id": next_id, "data": data.source})

    final = lineage.stage_cloud(lineage.n_stages - 1)
    if final_size is None:  # every stage was done already: the size is in the last stage's PLY
        final_size = _stage_size(out, lineage.n_stages - 1, final, data, config.resolutions[-1], size_key,
                                 size_fn)
    final = final.replace(extra={**final.extra, size_key: final_size}, background=bg)
    return TrainResult(final, lineage, log, out, stage_paths)


def _optimise(model: GaussianModel, cams: list[Camera], targets: torch.Tensor, config: TrainConfig, sched: dict,
              rng: np.random.Generator, gen: torch.Generator, settings: RenderSettings, height: int,
              degree_at: Callable[[int], int], *, densify: DensifyStrategy | None, bar=None,
              progress: Callable[[int], None] | None = None,
              should_stop: Callable[[int, GaussianCloud], bool] | None = None,
              check_every: int = 100) -> dict[str, int]:
    """One stage's iterations (`sched`, `TrainConfig.stage_schedule`) on `model`: the reference
    recipe (views in random order without repetition, the position learning rate decaying over
    the stage, 0.8·L1 + 0.2·(1 − SSIM)), with the `densify` strategy's density control and opacity
    resets when given, without any when None (a fine-tune keeps its Gaussians). `degree_at(it)`:
    the SH degree at the stage's iteration `it` (1-based); `progress(it)` every 10 iterations;
    `should_stop(it, cloud)` every `check_every` iterations with the current torch cloud (True ends
    the iterations there). Returns the counts of cloned, split and pruned Gaussians."""
    counts = {"cloned": 0, "split": 0, "pruned": 0}
    n_iter, bg = sched["iterations"], config.background
    order: list[int] = []
    filt = _model_filter(model, cams) if config.antialias == "mip" else None
    for it in range(1, n_iter + 1):
        model.set_lr("means", position_lr(config, model.extent, it - 1, n_iter))
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
            if densify is not None and sched["densify_from"] <= it <= sched["densify_until"]:
                if it % sched["densify_every"] == 0 and it < n_iter:
                    done = densify.densify_and_prune(model, gen, image_height=height,
                                                     prune_large=it > sched["opacity_reset_every"])
                    for k in counts:
                        counts[k] += done[k]
                if it % sched["opacity_reset_every"] == 0 and it < sched["densify_until"]:
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
        if should_stop is not None and it % check_every == 0 and it < n_iter:
            with torch.no_grad():
                if should_stop(it, model.cloud()):
                    break
    return counts


def fine_tune(cloud: GaussianCloud, views: Views, iterations: int, *, config: TrainConfig | None = None,
              seed: int = 0, progress: Callable[[float, str], None] | None = None, device=None,
              should_stop: Callable[[int, GaussianCloud], bool] | None = None,
              check_every: int = 100) -> GaussianCloud:
    """`cloud` trained on `views` (at their resolution) for `iterations` more iterations with
    the trainer's recipe and one stage's schedule (`_optimise`: its learning rates, the position
    rate decaying over the iterations, the anti-aliasing of `config.antialias`), without density
    control: the Gaussians stay the same rows, only their parameters change (how PUP 3D-GS
    fine-tunes after pruning). The SH degree is the cloud's. Returns a numpy cloud with the input's
    extra properties, its anti-aliasing size (`gvae_dilation_3D`, or `filter_3D` when
    `config.antialias` is "mip") recomputed from the views' cameras. `progress(fraction, message)`
    every 10 iterations (an exception it raises stops the fine-tune). `should_stop(it, cloud)`:
    called every `check_every` iterations with the current torch cloud; True ends the fine-tune
    there, `iterations` being then the most it runs (the schedule is still that of `iterations`)."""
    config = config or TrainConfig()
    iterations = int(iterations)
    if iterations < 0:
        raise ValueError(f"fine_tune: iterations must be >= 0, got {iterations}")
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
    say = (lambda it: progress(it / max(iterations, 1), f"fine-tuning {it}/{iterations}")) if progress else None
    _optimise(model, views.cameras, _targets(views, config.background).to(dev), config, sched, rng, gen,
              RenderSettings(antialias=config.antialias), views.cameras[0].height, lambda it: src.sh_degree,
              densify=None, progress=say, should_stop=should_stop, check_every=max(1, int(check_every)))
    out = model.snapshot()
    key, size_fn = (FILTER_KEY, filter_3d) if config.antialias == "mip" else (DILATION_KEY, dilation_3d)
    extra = {k: v for k, v in src.extra.items() if k not in (FILTER_KEY, DILATION_KEY)}
    return out.replace(extra={**extra, key: size_fn(out.means, views.cameras)})


@dataclass
class MoreResult:
    """A finished stage trained `iterations` more: the cloud, where it was written, and its log entry
    (PSNR/SSIM on the training and held-out views at the stage's resolution, time)."""

    cloud: GaussianCloud
    path: Path
    entry: dict[str, Any]


def train_more(run_dir, iterations: int, *, stage: int | None = None, progress: bool = True,
               threads: int | None = None, device=None) -> MoreResult:
    """Train a finished stage of the run in `run_dir` (the last by default) `iterations` more
    iterations on its training views at its resolution, the run's configuration, without density
    control (`fine_tune`: the same Gaussians; the control a refinement at the same count is judged
    against). Writes `stage_<s>_more_<iterations>.ply` and appends the entry to `more.json`."""
    out = Path(run_dir)
    run_path = out / "run.json"
    if not run_path.is_file():
        raise ValueError(f"{out}: not a training run (no run.json)")
    try:
        run = json.loads(run_path.read_text(encoding="utf-8"))
        config, done, source = TrainConfig(**run["config"]), int(run["stages_done"]), run.get("data")
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
    views = data.views("train", height)
    cloud = read_ply(out / f"stage_{stage}.ply")
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    bar = _progress_bar(int(iterations), f"stage {stage + 1} +{iterations}", progress)
    last = [0]

    def advance(fraction: float, message: str) -> None:
        if bar is not None:
            done_now = int(round(fraction * int(iterations)))
            bar.update(done_now - last[0])
            last[0] = done_now

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
    test_psnr, test_ssim = evaluate_views(dev, data.views("test", height), config.background, tuned.sh_degree,
                                          config.test_eval_views, settings)
    path = write_ply(tuned, out / f"stage_{stage}_more_{int(iterations)}.ply")
    entry = {"stage": stage, "resolution": height, "more": int(iterations), "seconds": round(seconds, 3),
             "n_gaussians": len(tuned), "train_psnr": round(train_psnr, 4),
             "test_psnr": None if math.isnan(test_psnr) else round(test_psnr, 4),
             "test_ssim": None if math.isnan(test_ssim) else round(test_ssim, 5), "file": path.name}
    more_path = out / "more.json"
    entries = json.loads(more_path.read_text(encoding="utf-8")) if more_path.is_file() else []
    _write_json(more_path, [e for e in entries if e.get("file") != path.name] + [entry])
    return MoreResult(tuned, path, entry)


def _model_filter(model: GaussianModel, cameras: list[Camera]) -> torch.Tensor:
    return torch.from_numpy(filter_3d(model.params["means"].detach().cpu().numpy(), cameras)).to(model.device)


def _stage_size(out: Path | None, stage: int, cloud: GaussianCloud, data: TrainingData, height: int, key: str,
                size_fn) -> np.ndarray:
    """The anti-aliasing size of a finished stage: from its PLY, or (a run from before the size
    was stored) from the stage's training cameras."""
    if out is not None and (out / f"stage_{stage}.ply").is_file():
        saved = read_ply(out / f"stage_{stage}.ply")
        if key in saved.extra and len(saved) == len(cloud):
            return np.asarray(saved.extra[key], np.float32)
    return size_fn(cloud.means, data.views("train", height).cameras)


def _progress_bar(total: int, desc: str, enabled: bool):
    if not enabled:
        return None

    return tqdm(total=total, desc=desc, leave=True, dynamic_ncols=True)
