"""Compaction with fine-tuning: PUP 3D-GS's rounds, each removing part of the way to the count and
then training the survivors with the project's trainer (`train.fine_tune`: its recipe, one stage's
schedule, the cloud's anti-aliasing), against the capture's images or, without them, the input's
own renders (`own_renders`).

Judged on views it does not train on: a share of the training images (or of the own renders) is
set aside (`set_aside`); the fine-tuning checks their PSNR every CHECK_EVERY iterations and stops
when it has stopped rising (`gvae_core.plateau.Plateau`, the trainer's rule too), keeping the best
state it saw. The capture's held-out (test) images are never used here. Where the defaults below
come from: docs/benchmarks/compact.md.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..antialias import DILATION_KEY, FILTER_KEY, dilation_3d, filter_3d, resolve_antialias, with_dilation_3d
from ..camera import Camera
from ..capture import DEFAULT_RESOLUTION, load_cameras, load_capture_images, placed_views, scoring_views
from ..cloud import GaussianCloud
from ..datasets import every_nth
from ..fidelity import training_rate_views
from ..octaves import training_height
from ..plateau import Plateau
from ..rendering import RenderSettings, render
from .merge import merge_groups, ordered, representatives
from .moments import moments
from .removal import removal_groups
from .report import CompactResult, input_images
from .scoring import compaction_scores
from .views import compare, sight

#: The most fine-tuning iterations a round with images (PUP 3D-GS fine-tunes 5,000 after each
#: pruning); the plateau rule ends a round sooner. The position learning rate decays over this many.
DEFAULT_ITERATIONS = 3000
#: The same keeping PHOTOS_PRUNE_FROM or more (`default_iterations`): a shorter decay where the
#: plateau stops the fine-tuning early anyway.
PRUNE_FROM_ITERATIONS = 1000
#: With the capture's images and neither a score nor a removal asked for: keeping PHOTOS_PRUNE_FROM
#: or more of the Gaussians, LightGaussian's global significance, pruned (then fine-tuned); fewer,
#: the Hessian's merge (what the images set aside preferred).
PHOTOS_SCORE, PHOTOS_REMOVAL, PHOTOS_PRUNE_FROM = "lightgaussian", "prune", 0.3
#: Every SET_ASIDE_EVERY-th training image (by name) is set aside to judge the fine-tuning.
SET_ASIDE_EVERY = 8
#: Iterations between two checks of the set-aside images.
CHECK_EVERY = 100
#: A fine-tuning stops after PATIENCE checks without a gain of MIN_GAIN dB over the best (the
#: project's `plateau.Plateau`, with a patience of PATIENCE x the check interval in iterations).
PATIENCE = 4
MIN_GAIN = 0.02
#: Views of the input's own renders that `distill` fine-tunes against, and those set aside to judge it.
DISTILL_VIEWS = 32
DISTILL_ASIDE = 8
#: How the input's own renders are drawn: "tuned", as the fine-tuning draws (`tuning_config`: classic
#: for a cloud trained the classic way, mip for one trained with Mip-Splatting's filters), or "auto"
#: (the default render: matched, the training rate's dilation held in world units).
DISTILL_TARGET = "tuned"
#: Iterations between two checks of the set-aside own renders.
DISTILL_CHECK_EVERY = 25
#: `compact(distill="auto")`, the default: clouds of up to AUTO_DISTILL_MAX Gaussians are
#: fine-tuned against their own renders for at most AUTO_DISTILL iterations in one round, until the
#: set-aside renders stop improving; larger ones are not (its cost grows with the count).
AUTO_DISTILL = 1000
AUTO_DISTILL_MAX = 50_000
#: The default distillation stops at its first check after this many seconds (the best state kept).
AUTO_DISTILL_SECONDS = 180.0
#: With images, the fine-tuning's result, and what the set-aside images judge, is the running
#: average of its iterates over about the last 1 / (1 - AVERAGE) = 100 steps (`train.ParameterAverage`)
#: instead of the last one: a step trains on one image, so successive iterates jitter.
AVERAGE = 0.99
#: The same for the fine-tuning against the input's own renders.
DISTILL_AVERAGE = AVERAGE
#: A cloud's trainable fields.
PARAMETERS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def training_rate(src: GaussianCloud, cameras, cams: Sequence[Camera]) -> list[Camera]:
    """`cams` rescaled to the sampling rate the cloud was trained at (`fidelity.training_rate_views`:
    from its anti-aliasing size, else from the capture's `cameras` at their full size)."""
    rate_of = src
    if cameras is not None and not {FILTER_KEY, DILATION_KEY} & set(src.extra):
        rate_of = with_dilation_3d(src, list(cameras))
    return training_rate_views(rate_of, cams)


def fine_tune_height(cloud: GaussianCloud, cameras: Sequence[Camera]) -> int | None:
    """The image height at which the capture's training `cameras` trained `cloud`, read from its
    anti-aliasing size (`octaves.training_height`): where its images are fine-tuned at. None when
    the cloud has no size to say it."""
    height, _ = training_height(cloud, list(cameras))
    return int(round(height)) if math.isfinite(height) else None


def fine_tune_images(cloud: GaussianCloud, capture, test_every: int | None = None, height: int | None = None):
    """The training photos of the capture at `capture` (`datasets.Views`; every `test_every`-th held
    out as training held it out) at `height`, else at the height they trained `cloud` at
    (`fine_tune_height`): the images `compact(images=...)` fine-tunes on (`gvae compact --images`,
    Blender's Compact with Photos)."""
    height = height or fine_tune_height(cloud, load_cameras(capture, test_every))
    return load_capture_images(capture, height, test_every)


def own_renders(cloud: GaussianCloud, cameras=None, resolution: int = DEFAULT_RESOLUTION,
                settings: RenderSettings | None = None, views: int = DISTILL_VIEWS):
    """The cloud's own renders over white as training images (`datasets.Views`): `views` of the
    capture's `cameras` (spread out) or views placed around the cloud (`capture.placed_views`:
    all around an object, inside a scene; `resolution` px high), all rescaled to one height, the
    lowest of the training sampling rate's (`training_rate`)."""
    from ..datasets import Views  # noqa: PLC0415

    src = cloud.numpy()
    cams = (scoring_views(cameras, views, 1 << 30, src) if cameras is not None
            else placed_views(src, views, resolution).scoring)
    # one height for all: the lowest view's (sharper targets than the median's)
    height = int(min(c.height for c in training_rate(src, cameras, cams)))
    cams = [c.scaled(height) for c in cams]
    names = [f"own_{i:03d}" for i in range(len(cams))]
    return Views(cams, np.stack([img.numpy() for img in input_images(src, cams, settings or RenderSettings())]),
                 names=names)


def set_aside(images, every: int = SET_ASIDE_EVERY):
    """(fit, aside): `images` (`datasets.Views`) split into the views the fine-tuning trains on and
    every `every`-th by name from the middle of the first `every` (`datasets.every_nth`: away from a
    capture's own held-out every-8th) that only judge it. (images, None) when fewer than two would
    be set aside or fewer than two left."""
    n = len(images)
    aside = every_nth(images.names, every, every // 2)
    if len(aside) < 2 or n - len(aside) < 2:
        return images, None
    return images.subset(np.setdiff1d(np.arange(n), aside)), images.subset(aside)


@dataclass
class Tuning:
    """How compaction fine-tunes: `images` to train on, `aside` to judge (None: no plateau rule,
    every iteration runs), `iterations` the most a round, `rounds`, `target` what `images` are
    ("the training images", "the input's own renders"), `check_every` iterations between checks,
    `patience` checks without gain before it stops, `seconds` (None: no limit) a round's fine-tuning
    stops at the first check past (the default distillation's bound on its cost), `average` the
    decay of the running average of the iterates that is the result (None: the last iterate),
    `train_overrides` changes to the trainer's configuration (`tuning_config`)."""

    images: object
    aside: object | None
    iterations: int
    rounds: int
    target: str = "the training images"
    check_every: int = CHECK_EVERY
    patience: int = PATIENCE
    seconds: float | None = None
    average: float | None = None
    train_overrides: dict = field(default_factory=dict)


@dataclass(frozen=True)
class TuningOptions:
    """What a study may change in compaction's fine-tuning (the defaults are the product's):
    `train_overrides` (`train.TrainConfig` fields), the decay of the running average of the iterates
    a fine-tuning with images (`average`) or against the input's own renders (`distill_average`)
    ends on (None: the last iterate), and how those renders are drawn (`distill_target`, as
    DISTILL_TARGET)."""

    train_overrides: dict = field(default_factory=dict)
    average: float | None = AVERAGE
    distill_average: float | None = DISTILL_AVERAGE
    distill_target: str = DISTILL_TARGET

    def __post_init__(self):
        if self.distill_target not in ("tuned", "auto"):
            raise ValueError(f"compact: distill_target must be 'tuned' or 'auto', got {self.distill_target!r}")


def aside_psnr(cloud: GaussianCloud, aside, config, fit_cameras: Sequence[Camera]) -> float:
    """Mean PSNR over the set-aside views, of `cloud`'s raw parameters rendered as the fine-tuning
    renders them (`config.antialias`; "mip": the 3D filter of the `fit_cameras`)."""
    from ..train import evaluate_psnr  # noqa: PLC0415

    c = cloud.replace(extra={}) if len(cloud.extra) else cloud
    if config.antialias == "mip":
        means = c.means.detach().cpu().numpy() if torch.is_tensor(c.means) else c.means
        c = c.replace(extra={FILTER_KEY: filter_3d(means, fit_cameras)})
    return evaluate_psnr(c, aside, config.background, c.sh_degree, None, RenderSettings(antialias=config.antialias))


def seconds_per_iteration(cloud: GaussianCloud, images, config, repeats: int = 2) -> float:
    """What one fine-tuning iteration of `cloud` costs, measured: a forward and backward render of
    the first training view (the least of `repeats`), 1.15x for the optimiser's step."""
    tc = cloud.to_torch()
    params = {k: getattr(tc, k).detach().clone().requires_grad_(True) for k in PARAMETERS}
    c = GaussianCloud(**params)
    if config.antialias == "mip":
        c = c.replace(extra={FILTER_KEY: torch.from_numpy(filter_3d(cloud.numpy().means, images.cameras))})
    best = float("inf")
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = render(c, images.cameras[0], background=config.background,
                     settings=RenderSettings(antialias=config.antialias))
        out.image.mean().backward()
        best = min(best, time.perf_counter() - t0)
    return 1.15 * best


def tune(cloud: GaussianCloud, tuning: Tuning, config, seed: int,
         say: Callable[[float, str], None] = lambda f, m: None) -> tuple[GaussianCloud, dict]:
    """`cloud` fine-tuned on `tuning.images` (`train.fine_tune`) for at most `tuning.iterations`;
    with set-aside views, until their PSNR stops rising (`Plateau`), the best state kept. Returns
    the cloud (the anti-aliasing size recomputed, as `fine_tune` does) and its record: iterations
    run, the best's iteration, seconds, PSNR on the set-aside views (else the training views)
    before and after, and the checks."""
    from ..train import fine_tune  # noqa: PLC0415 - training loads only with images

    src = cloud.numpy()
    fit_cams = tuning.images.cameras
    judge_views = tuning.aside if tuning.aside is not None else tuning.images
    t0 = time.perf_counter()
    before = aside_psnr(src, judge_views, config, fit_cams)
    # the plateau is of the fine-tuning's own progress (its first steps may dip below `before`: it
    # is not the input's score it has to beat to go on); the best state may still be the input's
    plateau = (Plateau(patience=tuning.patience * tuning.check_every, min_gain=MIN_GAIN)
               if tuning.aside is not None else None)
    best: list = [before, 0, src]  # value, iteration, parameters (None: the last state)
    last_check = [0]
    stopped = [False]

    def should_stop(it: int, current) -> bool:
        last_check[0] = it
        value = aside_psnr(current, tuning.aside, config, fit_cams)
        if value > best[0]:
            best[:] = [value, it, GaussianCloud(**{k: getattr(current, k).detach().cpu().clone() for k in PARAMETERS})]
        stopped[0] = plateau.update(it, value) or (tuning.seconds is not None
                                                    and time.perf_counter() - t0 > tuning.seconds)
        say(it / max(tuning.iterations, 1), f"fine-tuning {it}/{tuning.iterations}, set-aside PSNR {value:.2f} dB "
            f"(best {best[0]:.2f} at {best[1]}; {before:.2f} before)")
        return stopped[0]

    tuned = fine_tune(src, tuning.images, tuning.iterations, config=config, seed=seed, progress=say,
                      average=tuning.average,
                      should_stop=should_stop if plateau is not None else None, check_every=tuning.check_every)
    if plateau is None:
        ran = best_at = tuning.iterations
        after = aside_psnr(tuned, judge_views, config, fit_cams)
    else:
        ran = last_check[0] if stopped[0] else tuning.iterations
        if not stopped[0] and last_check[0] != ran:  # every iteration ran: the last state is judged too
            last = aside_psnr(tuned, judge_views, config, fit_cams)
            plateau.update(ran, last)
            if last > best[0]:
                best[:] = [last, ran, None]
        if best[2] is not None:
            tuned = _with_parameters(tuned, best[2].numpy(), fit_cams, config)
        after, best_at = best[0], best[1]
    record = {"count": len(tuned), "iterations": ran, "best_at": best_at,
              "seconds": time.perf_counter() - t0, "psnr_before": before, "psnr_after": after,
              "judged_on": (f"the {len(tuning.aside)} of {tuning.target} set aside" if tuning.aside is not None
                            else tuning.target),
              "checks": list(plateau.history) if plateau is not None else []}
    return tuned, record


def still_gaining(records: Sequence[dict], option: str) -> list[str]:
    """A warning for each round whose fine-tuning, judged by a plateau (`tune`), ran all its
    iterations and liked its last state best: it was stopped by the cap, not the plateau (a splat
    trained briefly still gains; `option` names how to allow more)."""
    return [f"round {k} of the fine-tuning was still improving at its last iteration ({r['iterations']:,}): "
            f"allow more with {option}" for k, r in enumerate(records, 1)
            if r.get("checks") and r["best_at"] == r["iterations"] and r["iterations"] > 0]


def _with_parameters(tuned: GaussianCloud, params: GaussianCloud, cameras: Sequence[Camera], config) -> GaussianCloud:
    """`tuned` (what `fine_tune` returned) with the Gaussians' parameters of `params` (a state the
    fine-tuning went through), the anti-aliasing size recomputed for them."""
    key, size_fn = (FILTER_KEY, filter_3d) if config.antialias == "mip" else (DILATION_KEY, dilation_3d)
    out = tuned.replace(means=params.means.astype(np.float32), scales=params.scales.astype(np.float32),
                        quats=params.quats.astype(np.float32), opacities=params.opacities.astype(np.float32),
                        sh_dc=params.sh_dc.astype(np.float32), sh_rest=params.sh_rest.astype(np.float32))
    return out.replace(extra={**tuned.extra, key: size_fn(out.means, cameras)})


def tuning_config(src: GaussianCloud, settings: RenderSettings, seed: int, overrides: dict | None = None):
    """The trainer's configuration a compaction fine-tunes with: the cloud's anti-aliasing, the
    trainer's recipe with `overrides` (`train.TrainConfig` fields) changed."""
    from ..train import TrainConfig  # noqa: PLC0415

    mode = resolve_antialias(settings.antialias, src)
    return TrainConfig(antialias="mip" if mode == "mip" else "classic", seed=seed, **(overrides or {}))


def compact_with_images(src: GaussianCloud, target: int, tuning: Tuning, how: dict, seed: int,
                        views: int, resolution: int, settings: RenderSettings, say, timings: dict,
                        extra: Sequence[Camera] = (), inside=None) -> CompactResult:
    """PUP 3D-GS's rounds: remove part of the way (the fraction kept per round the same), fine-tune
    (`tune`). Each round scores from `views` of the images' cameras (`capture.scoring_views`), or for
    LightGaussian's score from all of them (its global significance sums its hits over the training
    views: one sweep a view); what none of the images' cameras (nor the set-aside ones, the `extra`
    views, those `inside` gives, `views.sight`) sees is dropped as unseen. The summary's PSNR is
    from the `views` (and the other views that see what was removed)."""
    n = len(src)
    config = tuning_config(src, settings, seed, tuning.train_overrides)
    cur, groups = src, np.arange(n)
    first = None
    records = []
    all_cams = list(tuning.images.cameras) + (list(tuning.aside.cameras) if tuning.aside is not None else [])
    cams = scoring_views(all_cams, views, resolution, src)  # (the Hessian's, and the report's)
    scoring = scoring_views(all_cams, 0, resolution, src) if how["score"] == "lightgaussian" else cams
    chosen = [c.world_to_cam for c in scoring]
    others = [c.scaled(resolution) if c.height > resolution else c for c in all_cams
              if not any(np.array_equal(c.world_to_cam, w) for w in chosen)] + list(extra)
    reference = input_images(src, cams, settings)
    rounds = tuning.rounds
    for r in range(rounds):
        count = max(target, int(round(n * (target / n) ** ((r + 1) / rounds))))
        base = 0.9 * r / rounds
        t0 = time.perf_counter()
        say(base, f"round {r + 1}/{rounds}: scoring {len(cur):,} Gaussians ({how['score']})")
        frames: list = []
        scores = compaction_scores(cur, how["score"], scoring, settings=settings, seed=seed + r, frames=frames)
        seen = sight(cur, scores, how["score"], frames, others, settings, inside)
        del frames
        if first is None:
            first = (scores, seen)
        step = removal_groups(cur, scores, count, **how, seen=seen.seen)
        cur, _ = merge_groups(cur, step)
        groups = np.where(groups >= 0, step[np.maximum(groups, 0)], -1)
        timings["remove"] = timings.get("remove", 0.0) + time.perf_counter() - t0
        if r == 0:
            per = seconds_per_iteration(cur, tuning.images, config)
            say(base, estimate_line(per, tuning, len(tuning.aside) if tuning.aside is not None else 0))
        t0 = time.perf_counter()
        cur, record = tune(cur, tuning, config, seed + r,
                           lambda f, msg, b=base, k=r + 1: say(b + 0.9 / rounds * (0.2 + 0.8 * f),
                                                               f"round {k}/{rounds}: {msg}"))
        timings["fine-tune"] = timings.get("fine-tune", 0.0) + time.perf_counter() - t0
        records.append(record)
    idx = np.flatnonzero(groups >= 0)
    rows = representatives(groups, idx, moments(src.select(idx), np.zeros(len(idx))).mass)
    groups, rows, cur = ordered(groups, rows, cur)
    t0 = time.perf_counter()
    # (what the first round's views saw of the input)
    result = compare(CompactResult(cur, rows, groups, first[0], 0.0, timings, records), src, reference, cams,
                     first[1], settings, len(cams))
    timings["report"] = time.perf_counter() - t0
    return result


def estimate_line(per_iteration: float, tuning: Tuning, aside: int) -> str:
    """What the fine-tuning will take, said before it starts."""
    most = per_iteration * tuning.iterations * tuning.rounds
    if aside:
        return (f"fine-tuning: about {per_iteration:.2f} s an iteration, at most {tuning.iterations:,} iterations a "
                f"round x {tuning.rounds} (about {_duration(most)}); it stops sooner when {aside} set-aside views "
                f"stop improving (checked every {tuning.check_every})")
    return (f"fine-tuning: about {per_iteration:.2f} s an iteration, {tuning.iterations:,} iterations a round x "
            f"{tuning.rounds}: about {_duration(most)}")


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.1f} min"
