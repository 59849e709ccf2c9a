"""The experiment behind `gvae report`: refinement against the strongest simple alternatives at
the same cost, on scenes no choice was made on, over several seeds.

Per (scene, seed): progressive 3DGS with lineage up to the training resolution, continued with
the real 1.5x and 2x images (the upper bound, the paper's 700p/800p columns). From the
training-resolution stage and its lineage only:
- baselines: the unrefined cloud (`BASELINE`); 3DGS trained on the real 1.5x and 2x images
  (`REAL`);
- `refine`'s default (`DEFAULT`): the detail model's changes per octave with the fidelity check
  (`gvae_core.detail`, `gvae_core.octaves`; no Gaussian added), against what costs the same: the
  global knob in its per-octave form (`KNOB`, `controls.octave_knob`) and linear lineage
  extrapolation (`EXTRAPOLATION`, `controls.extrapolation_control`), each with one factor chosen on
  the training scenes; bounded by the oracle (`ORACLE`, an upper bound, not a method: every
  Gaussian's log-scale and opacity changes fitted to the pair's real 1.5x and 2x training views,
  `detail.fit_changes`);
- the paper's method (the lineage VAEs): Ours (every Gaussian) and Ours-∇² (the Hessian budget)
  at +1..+steps, with controls at Ours-∇²'s output count, step by step (`gvae_core.controls`):
  the plain 3DGS split, random selection with the model, and duplicate-in-place.
Every cloud is scored by Chamfer distance of its centres to the ground-truth mesh (accuracy plain
and weighted by opacity, completeness), PSNR/SSIM against the ground-truth test views at 1x, 1.5x
and 2x the training resolution with the anti-aliasing mode the protocol names (the primary
columns) and with the classic render beside it, NIQE of the 2x renders, its Gaussian count and
time. The runs train the classic way (the reference 3DGS, which the bundled models learned from);
the clouds carry the anti-aliasing size of the cameras they were trained with and render in the
protocol's mode (`antialias`, default "matched": `gvae_core.antialias`, BENCHMARKS.md).
Scenes and training runs are cached and reused; runs resume.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import multiprocessing
import os
import statistics
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .antialias import with_training_cameras
from .cloud import GaussianCloud
from .controls import duplicate_control, extrapolation_control, octave_knob, split_control, thin_added
from .capture import load_nerf_synthetic
from .detail import Example, FitConfig, fit_changes, load_detail
from .hessian import hessian_scores
from .lineage import Lineage
from .metrics.geometry import MeshDistance, chamfer, read_mesh_ply
from .metrics.image import image_scores
from .octaves import octave_fields, with_octaves
from .ply import read_ply
from .refinement import RefineResult, refine, refine_steps
from .rendering import RenderSettings, render, resolve_device
from .rendering.reference import render_reference
from .scenes import SPLITS, cache_dir, make_scene
from .scenes.faults import FAULTS, faulted_scene
from .superres import CHILD_GRADIENT, EXPOSURE_WEIGHT, POSE_WEIGHT, SuperResConfig, fit_octaves
from .camera import scene_extent
from .train import TrainConfig, fine_tune, train_progressive
from .vae import default_model_dir, load_model

#: Methods in result rows.
BASELINE, KNOB, REAL = "3dgs", "3dgs_knob", "3dgs_real"
OURS, OURS_H = "ours", "ours_h"
#: What `refine` does by default: the detail model with the fidelity check (`gvae_core.fidelity`).
DEFAULT = "refine"
#: At the default's cost: linear lineage extrapolation; the bound: the oracle.
EXTRAPOLATION, ORACLE = "extrapolation", "oracle"
#: Refine from the capture's images (`refine(images=...)`, `gvae_core.superres`); the same fit with
#: children (when the protocol's fit has none) or without them (when it has); the same number of
#: plain training steps at 1x (`train.fine_tune`); the same fit to the real 2x images (the oracle of
#: the fit's quantities).
IMAGES, IMAGES_CHILDREN, IMAGES_NO_CHILDREN = "images", "images_children", "images_no_children"
FINETUNE, ORACLE_IMAGES = "finetune", "oracle_images"
#: The 4x rows: from the first training stage, two octaves up (method -> its row name).
FOUR_X = {m: f"{m}_4x" for m in ("3dgs", "refine", "images", "finetune", "3dgs_real")}
SPLIT, RANDOM, DUPLICATE = "split", "random", "duplicate"
CONTROLS = (SPLIT, RANDOM, DUPLICATE)
SCALES = ("1x", "1.5x", "2x")
#: Random selection with the model chooses this many times Ours-∇²'s count of Gaussians, then its
#: children are thinned to Ours-∇²'s count (the model decides how many children each gets).
RANDOM_OVERSUPPLY = 1.5


@dataclass(frozen=True)
class Protocol:
    """One experiment profile: scenes (by default the test split) at a render profile, seeds,
    the training stages (the last is the training resolution) and the real-image stages above it
    (1.5x and 2x), how far to refine, how to render, where the global knob and the extrapolation
    factor are tuned, and how hard the oracle is fitted."""

    name: str
    scene_profile: str
    resolutions: tuple[int, ...]
    iterations: tuple[int, ...]
    higher: tuple[int, ...]
    higher_iterations: tuple[int, ...]
    train_overrides: dict = field(default_factory=dict)
    scenes: tuple[str, ...] = SPLITS["test"]
    seeds: tuple[int, ...] = (0, 1, 2)
    steps: int = 2
    budget: Any = "auto"
    antialias: str = "matched"
    test_views: int | None = None
    hessian_views: int = 8
    knob_scenes: tuple[str, ...] = SPLITS["train"]
    #: The global knob: every scale times this per octave above the training rate.
    knob_factors: tuple[float, ...] = (0.8, 0.9, 1.0, 1.1, 1.2, 1.3)
    #: Linear lineage extrapolation: this share of each Gaussian's last change per octave.
    extrapolation_factors: tuple[float, ...] = (0.0, 0.1, 0.25, 0.5, 1.0)
    #: Optimiser steps (and patch size) of the oracle's fit to a pair's real higher-resolution views.
    oracle_steps: int = 200
    oracle_patch: int = 128
    scene_seed: int = 0

    #: Whether the runs go on with the real higher-resolution images (the REAL upper bound); without,
    #: they stop at the training resolution (what a model learns from; evaluation still uses `higher`).
    train_higher: bool = True
    #: Refine from the pair's training images: the fit's settings (`superres.SuperResConfig` fields,
    #: beside its defaults), whether to run it (and its 4x rows from the first stage); the simulated
    #: capture faults (`scenes.faults`) and the 3DGS seeds their rows are made for.
    image_fit: dict = field(default_factory=dict)
    image_rows: bool = True
    image_4x: bool = True
    faults: tuple[str, ...] = ()
    fault_seeds: tuple[int, ...] = (0,)

    def train_config(self, seed: int = 0) -> TrainConfig:
        """The protocol's training: the `legacy` profile's fixed counts per stage (the higher stages
        are the lineage's ground truth, trained as long as the protocol says, not until they
        converge), so that its runs and cached results stay those the reports were made from."""
        higher = self.higher if self.train_higher else ()
        iterations = self.higher_iterations if self.train_higher else ()
        return TrainConfig.profile("legacy", resolutions=self.resolutions + higher,
                                   iterations=self.iterations + iterations, seed=seed, **self.train_overrides)

    def data(self, scene_seed: int = 0) -> Protocol:
        """The runs a model learns from: the same training on a seeded variant of each scene
        (`make_scene(..., seed=)`), stopped at the training resolution."""
        return dataclasses.replace(self, name=f"{self.name}-data", train_higher=False, scene_seed=scene_seed)

    def fits(self) -> Protocol:
        """The runs the fits to the images are chosen and measured on (`tools/superres_choices.py`,
        `tools/refine_capture.py --scene`): the same training of the scenes themselves, stopped at
        the training resolution."""
        return dataclasses.replace(self, name=f"{self.name}-val", train_higher=False)

    @property
    def train_stage(self) -> int:
        """Index of the training-resolution stage in the run."""
        return len(self.resolutions) - 1

    def run_key(self, seed: int = 0) -> str:
        """Hash of what a scene's training run with 3DGS seed `seed` depends on (the scene's seed too)."""
        key = {"scene_profile": self.scene_profile, "config": self.train_config(seed).to_dict()}
        if self.scene_seed:  # (absent for scene seed 0, so that the runs cached before it keep their keys)
            key["scene_seed"] = self.scene_seed
        blob = json.dumps(key, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


#: The benchmark protocols pin their start and cap (the visual hull, a fixed count) whatever the
#: trainer's defaults, so that their runs, cache keys and figures stay the same.
PROTOCOLS: dict[str, Protocol] = {p.name: p for p in [
    # About 80 minutes on 2 cores from nothing (50 of them the fault rows): the test scenes, three
    # seeds, small renders; the knob on the first two training scenes.
    Protocol("quick", scene_profile="small", resolutions=(50, 75, 100), iterations=(300, 200, 200),
             higher=(150, 200), higher_iterations=(200, 200),
             train_overrides=dict(init="hull", init_count=4000, max_gaussians=20_000), test_views=8,
             knob_scenes=SPLITS["train"][:2], faults=tuple(f for f in FAULTS if f != "none")),
    # The benchmark profile (hours on 2 cores; runs resume).
    Protocol("full", scene_profile="default", resolutions=(100, 150, 200), iterations=(600, 400, 400),
             higher=(300, 400), higher_iterations=(400, 400), steps=4, test_views=10,
             train_overrides=dict(init="hull", max_gaussians=50_000)),
    # Paper scale, for a machine with a GPU (`--device cuda`): training at 400 px, 800 px renders.
    Protocol("paper", scene_profile="full", resolutions=(100, 200, 400), iterations=(7000, 7000, 7000),
             higher=(600, 800), higher_iterations=(7000, 7000), steps=4, test_views=20,
             train_overrides=dict(init="random", init_count=100_000, max_gaussians=None)),
]}


#: The experiment's drivers (tools/, `gvae_core.benchmarks`) at the smallest size, to show that they run
#: (minutes from nothing): `tiny` scenes of 64 px, training 16 -> 24 -> 32 px, four test views.
SMOKE = Protocol("smoke", scene_profile="tiny", resolutions=(16, 24, 32), iterations=(60, 40, 40),
                 higher=(48, 64), higher_iterations=(40, 40), train_overrides=dict(init_count=1000, max_gaussians=5000),
                 test_views=4, seeds=(0,), oracle_steps=10)


# ----------------------------------------------------------------------------- per scene

@dataclass
class SceneRun:
    """A scene prepared for the experiment: its folder, one training run (all stages) and what
    evaluation needs."""

    name: str
    seed: int
    scene_dir: Path
    run_dir: Path
    protocol: Protocol
    seconds: dict[str, float]

    def lineage(self, stages: int | None = None) -> Lineage:
        lin = Lineage.load(self.run_dir / "lineage.npz")
        return lin if stages is None else lin.prefix(stages)

    def stage_cloud(self, stage: int):
        """A stage's cloud with the anti-aliasing size of the cameras (and resolution) it was trained
        with (recomputed: runs cached before the trainer stored it lack it)."""
        cloud = read_ply(self.run_dir / f"stage_{stage}.ply")
        cams = load_nerf_synthetic(self.scene_dir, "train", resolution=self.log()[stage]["resolution"]).cameras
        return with_training_cameras(cloud, cams, trained=self.protocol.train_config().antialias)

    def log(self) -> list[dict]:
        return json.loads((self.run_dir / "log.json").read_text())


def runs_dir(cache=None) -> Path:
    return cache_dir(cache) / "runs"


def run_dir(name: str, protocol: Protocol, seed: int = 0, cache=None) -> Path:
    return runs_dir(cache) / f"{protocol.name}-{protocol.run_key(seed)}" / name


def prepare_scene(name: str, protocol: Protocol, *, seed: int = 0, cache=None, threads: int = 1,
                  device=None, say: Callable[[str], None] = print) -> SceneRun:
    """Render the scene (cached) and train its run with 3DGS seed `seed` through every stage
    (cached, resumable)."""
    t0 = time.perf_counter()
    scene_dir = make_scene(name, profile=protocol.scene_profile, seed=protocol.scene_seed, cache=cache)
    t1 = time.perf_counter()
    out = run_dir(name, protocol, seed, cache)
    config = protocol.train_config(seed)
    done = _stages_done(out)
    if done < len(config.resolutions):
        say(f"[{name} s{seed}] training {len(config.resolutions)} stages {config.resolutions} px "
            f"({done} done) into {out}")
        train_progressive(scene_dir, config, out_dir=out, progress=False, threads=threads, device=device)
    return SceneRun(name, seed, scene_dir, out, protocol, {"scene": t1 - t0, "train": time.perf_counter() - t1})


def prepare_faulted(name: str, fault: str, protocol: Protocol, *, seed: int = 0, cache=None, threads: int = 1,
                    device=None, say: Callable[[str], None] = print) -> SceneRun:
    """A (scene, seed) trained on its training images with a simulated capture fault
    (`scenes.faults`) up to the training resolution (cached, resumable); its test views are the
    scene's own."""
    t0 = time.perf_counter()
    clean = make_scene(name, profile=protocol.scene_profile, seed=protocol.scene_seed, cache=cache)
    scene_dir = faulted_scene(clean, fault, protocol.resolutions[-1], seed=seed, cache=cache)
    t1 = time.perf_counter()
    data = protocol.data(protocol.scene_seed)
    out = runs_dir(cache) / f"faults-{data.run_key(seed)}" / scene_dir.name
    config = data.train_config(seed)
    if _stages_done(out) < len(config.resolutions):
        say(f"[{name} s{seed} {fault}] training {config.resolutions} px into {out}")
        train_progressive(scene_dir, config, out_dir=out, progress=False, threads=threads, device=device)
    return SceneRun(name, seed, scene_dir, out, data, {"scene": t1 - t0, "train": time.perf_counter() - t1})


def _stages_done(path: Path) -> int:
    try:
        return int(json.loads((path / "run.json").read_text())["stages_done"])
    except (OSError, ValueError, KeyError):
        return 0


def scene_split(name: str) -> str:
    return next((split for split, names in SPLITS.items() if name in names), "other")


class Evaluator:
    """Scores clouds of one scene: Chamfer against its mesh (plain and opacity-weighted
    accuracy), PSNR/SSIM against its test views at each scale with the protocol's anti-aliasing
    mode and with the classic render, NIQE of the 2x renders; renders on `device`."""

    def __init__(self, run: SceneRun, background=(1.0, 1.0, 1.0), device=None, heights: dict[str, int] | None = None):
        p = run.protocol
        self.background = background
        self.device = device
        self.modes = {"": p.antialias, "_classic": "classic"}
        self.mesh = MeshDistance(*read_mesh_ply(run.scene_dir / "mesh.ply"))
        self.surface = np.load(run.scene_dir / "gt_points.npy")
        self.views = {}
        heights = heights or dict(zip(SCALES, (p.resolutions[-1],) + tuple(p.higher)))
        self.scales = tuple(heights)
        for label, h in heights.items():
            v = load_nerf_synthetic(run.scene_dir, "test", resolution=h)
            if p.test_views is not None and p.test_views < len(v):
                pick = np.linspace(0, len(v) - 1, p.test_views).round().astype(int)
                v = type(v)([v.cameras[i] for i in pick], v.images[pick], v.alphas[pick],
                            [v.names[i] for i in pick])
            self.views[label] = v

    def __call__(self, cloud, *, scales=None) -> dict[str, float]:
        c = chamfer(cloud.means, self.surface, self.mesh, weights=cloud.activated_opacities())
        row = {"chamfer": c.chamfer, "accuracy": c.accuracy, "weighted_accuracy": c.weighted_accuracy,
               "completeness": c.completeness, "n_gaussians": len(cloud)}
        for label in scales or self.scales:
            for suffix, mode in self.modes.items():
                niqe = not suffix and label == self.scales[-1]
                s = image_scores(cloud, self.views[label], self.background, no_reference=niqe, antialias=mode,
                                 device=self.device)
                row[f"psnr_{label}{suffix}"] = s.psnr
                row[f"ssim_{label}{suffix}"] = s.ssim
                if niqe:
                    row["niqe"] = s.niqe
        return row


def hessian_cameras(run: SceneRun, count: int):
    """`count` training cameras, evenly spaced, at the training resolution."""
    views = load_nerf_synthetic(run.scene_dir, "train", resolution=run.protocol.resolutions[-1])
    pick = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    return [views.cameras[i] for i in pick]


def render_timing(cloud, camera, antialias: str, repeats: int = 3, samples: int = 64, seed: int = 0) -> dict:
    """Seconds per forward render (median of `repeats`) and the largest difference from the
    float64 reference renderer on `samples` random pixels of the same image."""
    tc = cloud.to_torch()
    settings = RenderSettings(antialias=antialias)
    times = []
    with torch.no_grad():
        render(tc, camera, background=(1.0, 1.0, 1.0), settings=settings)  # warm-up
        for _ in range(repeats):
            t0 = time.perf_counter()
            image = render(tc, camera, background=(1.0, 1.0, 1.0), settings=settings).image.numpy()
            times.append(time.perf_counter() - t0)
    rng = np.random.default_rng(seed)
    pix = np.stack([rng.integers(0, camera.height, samples), rng.integers(0, camera.width, samples)], 1)
    ref = render_reference(cloud, camera, background=(1.0, 1.0, 1.0), pixels=pix, antialias=antialias)[0]
    error = float(np.abs(image[pix[:, 0], pix[:, 1]] - ref).max())
    return {"render_s": statistics.median(times), "render_error": error, "n_gaussians": len(cloud),
            "height": camera.height}


def oracle(run: SceneRun, base, fields=("scales", "opacities"), *, steps: int | None = None,
           patch: int | None = None) -> tuple[GaussianCloud, float]:
    """The oracle of one pair: `base` with every Gaussian's changes per octave of `fields` fitted to
    the pair's real training views at 1.5x and 2x its training resolution; and the seconds it took."""
    p = run.protocol
    t0 = time.perf_counter()
    res = p.resolutions[-1]
    views = {label: load_nerf_synthetic(run.scene_dir, "train", resolution=h)
             for label, h in zip(SCALES[1:], (round(1.5 * res), 2 * res))}
    extent = scene_extent(views["2x"].cameras)[1]
    example = Example(base, None, views)
    changes = fit_changes(example, fields, FitConfig(steps=steps or p.oracle_steps, patch=patch or p.oracle_patch,
                                                     seed=run.seed), extent=extent)
    return with_octaves(base, changes), time.perf_counter() - t0


def run_scene(run: SceneRun, model, knob: float = 1.0, extrapolation: float = 0.0, *, detail=None, device=None,
              say: Callable[[str], None] = print) -> list[dict]:
    """Every method and step on one prepared (scene, seed); one row per (method, step). `model`: the
    lineage VAEs; `detail`: the detail model (default: the bundled one); `knob`, `extrapolation`:
    the factors chosen on the training scenes."""
    p = run.protocol
    k = p.train_stage
    evaluate = Evaluator(run, device=device)
    lineage = run.lineage(k + 1)
    base = run.stage_cloud(k)
    rows: list[dict] = []
    tag = {"scene": run.name, "seed": run.seed, "split": scene_split(run.name)}

    def add(method: str, step: int, cloud, evaluator: Evaluator | None = None, **info) -> None:
        t0 = time.perf_counter()
        row = {**tag, "method": method, "step": step, **info, **(evaluator or evaluate)(cloud)}
        row["eval_s"] = time.perf_counter() - t0
        rows.append(row)
        say(f"[{run.name} s{run.seed}] {method:9s} {'+' + str(step) if step else '':3s} {_brief(row)}")

    log = run.log()
    add(BASELINE, 0, base, resolution=log[k]["resolution"], train_s=sum(e["seconds"] for e in log[:k + 1]))
    if p.image_rows:
        image_rows(run, base, lineage, detail, evaluate, add, say)
    for i, label in enumerate(SCALES[1:] if p.train_higher else (), 1):
        add(REAL, 0, run.stage_cloud(k + i), scale=label, resolution=log[k + i]["resolution"],
            train_s=sum(e["seconds"] for e in log[:k + i + 1]))
    # refine's default and what costs the same, at +1 (one octave: 2x; nothing is added)
    add(KNOB, 1, octave_knob(base, knob), factor=knob)
    add(EXTRAPOLATION, 1, extrapolation_control(base, lineage, extrapolation), factor=extrapolation)
    t0 = time.perf_counter()
    r = refine(base, lineage=lineage, model=detail, method="detail")
    add(DEFAULT, 1, r.cloud, selected=len(r.selected), reverted=len(r.reverted), refine_s=time.perf_counter() - t0)
    bound, seconds = oracle(run, base)
    add(ORACLE, 1, bound, fit_s=seconds)

    t0 = time.perf_counter()
    scores = hessian_scores(base, hessian_cameras(run, p.hessian_views), views=0,
                            render_settings=RenderSettings(antialias=p.antialias)).numpy()
    hessian_s = time.perf_counter() - t0
    common = dict(steps=p.steps, model=model, lineage=lineage, seed=run.seed, fidelity=None)

    def refined(method: str, results, **info) -> list[RefineResult]:
        out = []
        for step, r in enumerate(results, 1):
            out.append(r)
            add(method, step, r.cloud, selected=len(r.selected), added=len(r.added),
                refine_s=r.timings["total"] - r.timings.get("hessian", 0.0) - r.timings.get("load", 0.0), **info)
        return out

    refined(OURS, refine_steps(base, budget="all", **common))
    ours_h = refined(OURS_H, refine_steps(base, budget=p.budget, scores=scores, **common), hessian_s=hessian_s)
    targets = [len(r.added) for r in ours_h]
    refined(SPLIT, split_control(base, scores, targets, seed=run.seed))
    refined(DUPLICATE, duplicate_control(base, scores, targets, seed=run.seed))
    count = math.ceil(RANDOM_OVERSUPPLY * len(ours_h[0].selected))
    noise = np.random.default_rng(run.seed + 1).random(len(base)).astype(np.float32)
    randoms = refine_steps(base, budget=count, scores=noise, **common)
    refined(RANDOM, (thin_added(r, t, seed=run.seed) for r, t in zip(randoms, targets)))
    for label in SCALES:
        rows.append({**tag, "method": "render", "scale": label,
                     **render_timing(base, evaluate.views[label].cameras[0], evaluate.modes[""])})
    return rows


def image_config(protocol: Protocol, seed: int = 0, **changes) -> SuperResConfig:
    """The fit the protocol refines from images with (its `image_fit` over the defaults)."""
    return SuperResConfig(**{"seed": seed, **protocol.image_fit, **changes})


def _fit_to_images(base, views, config: SuperResConfig, start, octaves: int = 1, images_scale: int = 1):
    """`superres.fit_octaves` made into a cloud (its changes and children), and the fit."""
    fit = fit_octaves(base, views, octaves, config, start=start, images_scale=images_scale)
    cloud = with_octaves(base, fit.changes, float(octaves))
    return (cloud.append_children(fit.children, fit.child_roots) if len(fit.child_roots) else cloud), fit


def image_rows(run: SceneRun, base, lineage, detail, evaluate: Evaluator, add, say=print) -> None:
    """Refine from the pair's training images at +1 (2x): `refine(images=...)`, the same fit with
    children, or without them when the fit has them (what they buy), the same number of plain
    training steps at 1x, and the same fit to the real 2x images (the oracle of its quantities);
    and, with `image_4x`, from the first stage two octaves up (4x, scored at 1x, 2x and 4x that
    stage's resolution) beside the detail model, the same steps of 1x training and the run's stage
    trained on the real 4x images."""
    p = run.protocol
    k = p.train_stage
    log = run.log()
    res = log[k]["resolution"]
    config = image_config(p, run.seed)
    views = load_nerf_synthetic(run.scene_dir, "train", resolution=res)
    t0 = time.perf_counter()
    r = refine(base, images=views, lineage=lineage, model=detail, fit=config)
    add(IMAGES, 1, r.cloud, refine_s=time.perf_counter() - t0, added=len(r.added),
        fit_psnr=[r.fit.psnr_before, r.fit.psnr_after])
    other = CHILD_GRADIENT if config.children is None else None  # what children buy, either way
    t0 = time.perf_counter()
    r0 = refine(base, images=views, lineage=lineage, model=detail, fit=dataclasses.replace(config, children=other))
    add(IMAGES_NO_CHILDREN if other is None else IMAGES_CHILDREN, 1, r0.cloud, refine_s=time.perf_counter() - t0,
        added=len(r0.added))
    steps = r.fit.steps_run * config.views_per_step  # the same steps of plain training
    t0 = time.perf_counter()
    add(FINETUNE, 1, fine_tune(base, views, steps, seed=run.seed), train_s=time.perf_counter() - t0,
        iterations=steps)
    start = (octave_fields(refine(base, lineage=lineage, model=detail, fidelity=None).cloud)
             if config.start == "detail" else None)
    t0 = time.perf_counter()
    real = load_nerf_synthetic(run.scene_dir, "train", resolution=2 * res)
    bound, _ = _fit_to_images(base, real, config, start, images_scale=2)
    add(ORACLE_IMAGES, 1, bound, fit_s=time.perf_counter() - t0)
    if not p.image_4x:
        return
    res0 = log[0]["resolution"]
    four = Evaluator(run, heights={"1x": res0, "2x": 2 * res0, "4x": 4 * res0})
    base0, lineage0 = run.stage_cloud(0), run.lineage(1)
    add(FOUR_X[BASELINE], 0, base0, four, resolution=res0)
    t0 = time.perf_counter()
    d = refine(base0, lineage=lineage0, model=detail, method="detail", steps=2)
    add(FOUR_X[DEFAULT], 2, d.cloud, four, refine_s=time.perf_counter() - t0)
    views0 = load_nerf_synthetic(run.scene_dir, "train", resolution=res0)
    t0 = time.perf_counter()
    r = refine(base0, images=views0, lineage=lineage0, model=detail, fit=config, steps=2)
    add(FOUR_X[IMAGES], 2, r.cloud, four, refine_s=time.perf_counter() - t0, added=len(r.added))
    steps = r.fit.steps_run * config.views_per_step
    t0 = time.perf_counter()
    add(FOUR_X[FINETUNE], 2, fine_tune(base0, views0, steps, seed=run.seed), four,
        train_s=time.perf_counter() - t0, iterations=steps)
    real4 = [i for i, e in enumerate(log) if e["resolution"] == 4 * res0]
    if real4:
        add(FOUR_X[REAL], 0, run.stage_cloud(real4[0]), four, resolution=4 * res0)


def fault_rows(name: str, seed: int, protocol: Protocol, detail=None, *, cache=None, device=None,
               say: Callable[[str], None] = print) -> list[dict]:
    """For each of the protocol's simulated capture faults: the (scene, seed) trained on its faulted
    training images, unrefined and refined from those images with each guard off and on (pose
    correction, exposure), scored at 1x and 2x against the scene's own test views."""
    rows = []
    for fault in protocol.faults:
        run = prepare_faulted(name, fault, protocol, seed=seed, cache=cache, say=say)
        k = run.protocol.train_stage
        res = run.log()[k]["resolution"]
        evaluate = Evaluator(run, device=device, heights={"1x": res, "2x": 2 * res})
        base, lineage = run.stage_cloud(k), run.lineage(k + 1)
        tag = {"scene": name, "seed": seed, "split": scene_split(name), "fault": fault}
        unrefined = {**tag, "method": BASELINE, "guard": "", **evaluate(base)}
        rows.append(unrefined)
        views = load_nerf_synthetic(run.scene_dir, "train", resolution=res)
        for guard, changes in GUARDS.items():
            t0 = time.perf_counter()
            r = refine(base, images=views, lineage=lineage, model=detail,
                       fit=image_config(protocol, seed, **changes))
            row = {**tag, "method": IMAGES, "guard": guard, "refine_s": time.perf_counter() - t0, **evaluate(r.cloud)}
            if r.fit.pose_pixels is not None:
                row["pose_pixels"] = float(np.median(r.fit.pose_pixels))
            if r.fit.exposure_gains is not None:
                row["exposure_spread"] = float(np.std(np.log(r.fit.exposure_gains)))
            rows.append(row)
            say(f"[{name} s{seed} {fault}] images, guard {guard}: PSNR 2x {row['psnr_2x']:.2f} (unrefined "
                f"{unrefined['psnr_2x']:.2f})")
    return rows


#: The guards the fault rows compare: none, each alone (their `SuperResConfig` settings).
GUARDS = {"none": {"pose": None, "exposure": None}, "pose": {"pose": POSE_WEIGHT, "exposure": None},
          "exposure": {"pose": None, "exposure": EXPOSURE_WEIGHT}}


def _brief(row: dict) -> str:
    parts = [f"n={row['n_gaussians']}", f"CD={row['chamfer']:.5f}", f"wAcc={row['weighted_accuracy']:.5f}"]
    parts += [f"PSNR{s}={row[f'psnr_{s}']:.2f}/{row[f'psnr_{s}_classic']:.2f}" for s in SCALES if f"psnr_{s}" in row]
    return " ".join(parts)


# ----------------------------------------------------------------------------- the knob and the extrapolation

def tune_knob(runs: Sequence[SceneRun], factors: Sequence[float], device=None, *, control=octave_knob,
              with_lineage: bool = False) -> dict:
    """One global factor, chosen on `runs` (the training scenes): the factor whose `control` of the
    unrefined clouds (default: the global scale knob per octave; `extrapolation_control` with
    `with_lineage`) scores the best mean PSNR at 2x with the protocol's render. Returns the factor
    and the table it was chosen from."""
    table = {f"{f:g}": [] for f in factors}
    for run in runs:
        evaluate = Evaluator(run, device=device)
        k = run.protocol.train_stage
        base = run.stage_cloud(k)
        lineage = run.lineage(k + 1) if with_lineage else None
        for f in factors:
            cloud = control(base, lineage, f) if with_lineage else control(base, f)
            s = image_scores(cloud, evaluate.views["2x"], evaluate.background, no_reference=False,
                             antialias=evaluate.modes[""], device=device)
            table[f"{f:g}"].append(s.psnr)
    means = {f: float(np.mean(v)) for f, v in table.items()}
    best = max(means, key=means.get)
    return {"factor": float(best), "psnr_2x": means, "scenes": [r.name for r in runs]}


# ----------------------------------------------------------------------------- the whole experiment

def run_experiment(protocol: Protocol | str, *, model=None, detail=None, scenes=None, seeds=None, cache=None,
                   jobs: int | None = None, device=None, say: Callable[[str], None] = print) -> dict:
    """The whole experiment: the knob's training-scene runs and every (scene, seed) prepared,
    the knob tuned, every (scene, seed) evaluated, `jobs` at a time in worker processes of one
    torch thread each (default: one per core, one on a GPU); returns the results document
    (protocol, model, knob, per-run logs and timings, rows). `device`: where training and the
    renders of the scores run ("cuda" on a GPU machine; the Hessian and the models stay on the
    CPU)."""
    p = PROTOCOLS[protocol] if isinstance(protocol, str) else protocol
    model_dir = Path(model) if model is not None else default_model_dir()
    detail_dir = Path(detail) if detail is not None else model_dir
    loaded = load_model(model_dir)
    detail_model = load_detail(detail_dir)
    pairs = [(name, seed) for name in (scenes or p.scenes) for seed in (seeds or p.seeds)]
    knob_pairs = [(name, p.seeds[0]) for name in p.knob_scenes]
    started = time.time()
    t0 = time.perf_counter()
    device = str(resolve_device(device))
    jobs = _job_count(jobs if jobs or device == "cpu" else 1, len(pairs))
    prepared = _map(prepare_job, [(n, s, p, cache, device) for n, s in dict.fromkeys(knob_pairs + pairs)], jobs,
                    say)
    runs = dict(zip(dict.fromkeys(knob_pairs + pairs), prepared))
    say(f"tuning the global knob and the extrapolation factor on {', '.join(p.knob_scenes)}")
    knob_runs = [runs[pair] for pair in knob_pairs]
    knob = tune_knob(knob_runs, p.knob_factors, device)
    extrapolation = tune_knob(knob_runs, p.extrapolation_factors, device, control=extrapolation_control,
                              with_lineage=True)
    for name, tuned in (("knob", knob), ("extrapolation", extrapolation)):
        say(f"{name}: x{tuned['factor']:g} (mean PSNR 2x by factor: "
            + ", ".join(f"{f}: {v:.2f}" for f, v in tuned["psnr_2x"].items()) + ")")
    results = _map(evaluate_job, [(runs[pair], model_dir, knob["factor"], extrapolation["factor"], detail_dir, device)
                                  for pair in pairs], jobs, say)
    doc = {"protocol": {**asdict(p), "train_config": p.train_config().to_dict()},
           "model": {"dir": portable_path(model_dir, cache), "sizes": loaded.sizes(),
                     "train_scenes": loaded.meta.get("train_scenes", []),
                     "held_out_scenes": loaded.meta.get("held_out_scenes", []),
                     "detail": {"dir": portable_path(detail_dir, cache), "bytes": detail_model.size_bytes(),
                                "config": asdict(detail_model.config), "meta": detail_model.meta}},
           "knob": knob, "extrapolation": extrapolation,
           "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(started)), "runs": {},
           "rows": [], "jobs": jobs, "device": device, "split": _common_split(name for name, _ in pairs)}
    fault_pairs = [(name, seed) for name, seed in pairs if seed in p.fault_seeds] if p.faults else []
    if fault_pairs:
        say(f"simulated capture faults ({', '.join(p.faults)}) on {len(fault_pairs)} pair(s)")
    doc["fault_rows"] = sum(_map(fault_job, [(name, seed, p, detail_dir, cache, device) for name, seed in fault_pairs],
                                 jobs, say), [])
    for (name, seed), rows in zip(pairs, results):
        run = runs[(name, seed)]
        doc["rows"] += rows
        doc["runs"][f"{name}/s{seed}"] = {"scene": name, "seed": seed, "split": scene_split(name),
                                          "scene_dir": portable_path(run.scene_dir, cache),
                                          "run_dir": portable_path(run.run_dir, cache),
                                          "log": run.log(), "seconds": run.seconds}
    doc["seconds"] = time.perf_counter() - t0
    return json_safe(doc)


def portable_path(path, cache=None) -> str:
    """`path` as a report can show it on any machine: inside the repository relative to it, inside the
    cache as `<cache>/...`, else as it is."""
    path = Path(path).resolve()
    for base, label in ((Path(__file__).resolve().parents[1], None), (cache_dir(cache).resolve(), "<cache>")):
        if path.is_relative_to(base):
            rel = path.relative_to(base).as_posix()
            return rel if label is None else f"{label}/{rel}"
    return str(path)


def _common_split(names) -> str:
    splits = {scene_split(n) for n in names}
    return splits.pop() if len(splits) == 1 else "mixed"


def prepare_job(name: str, seed: int, protocol: Protocol, cache=None, device=None, say=None) -> SceneRun:
    return prepare_scene(name, protocol, seed=seed, cache=cache, threads=1, device=device, say=say or _print)


def evaluate_job(run: SceneRun, model_dir, knob: float, extrapolation: float, detail_dir=None, device=None,
                 say=None) -> list[dict]:
    detail = load_detail(detail_dir) if detail_dir is not None else None
    return run_scene(run, load_model(model_dir), knob, extrapolation, detail=detail, device=device,
                     say=say or _print)


def fault_job(name: str, seed: int, protocol: Protocol, detail_dir=None, cache=None, device=None,
              say=None) -> list[dict]:
    detail = load_detail(detail_dir) if detail_dir is not None else None
    return fault_rows(name, seed, protocol, detail, cache=cache, device=device, say=say or _print)


def prepare_scenes(names, protocol: Protocol, *, seed: int = 0, cache=None, jobs: int | None = None,
                   say: Callable[[str], None] = print) -> dict[str, SceneRun]:
    """`prepare_scene` for several scenes (one 3DGS seed), `jobs` at a time."""
    names = list(names)
    runs = _map(prepare_job, [(n, seed, protocol, cache) for n in names], _job_count(jobs, len(names)), say)
    return dict(zip(names, runs))


def _map(fn, arg_lists: list[tuple], jobs: int, say: Callable[[str], None]) -> list:
    """fn(*args, say=...) for every args tuple, in `jobs` worker processes (in order)."""
    if jobs == 1:
        return [fn(*args, say=say) for args in arg_lists]
    with _pool(jobs) as pool:
        futures = [pool.submit(fn, *args) for args in arg_lists]
        return [f.result() for f in futures]


def _job_count(jobs: int | None, tasks: int) -> int:
    """Worker processes for `tasks` jobs: `jobs`, or one per core, and no more than the tasks."""
    return max(1, min(jobs or os.cpu_count() or 1, tasks))


def _pool(jobs: int):
    # spawn: a forked torch process can hang in its thread pools.
    return ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_one_thread)


def _print(msg: str) -> None:
    print(msg, flush=True)


def _one_thread() -> None:
    torch.set_num_threads(1)


def json_safe(obj):
    """JSON-safe copy of results (dicts, lists, numpy numbers): NaN and infinities become None."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
