"""Compaction with fine-tuning: PUP 3D-GS's rounds, each removing part of the way to the count and
then training the survivors with the project's trainer (`train.fine_tune`: its recipe, one stage's
schedule, the cloud's anti-aliasing), against the capture's images or, without them, the input's
own renders (`own_renders`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from ..antialias import DILATION_KEY, FILTER_KEY, resolve_antialias, with_dilation_3d
from ..camera import Camera
from ..capture import DEFAULT_RESOLUTION, placed_views, scoring_views
from ..cloud import GaussianCloud
from ..fidelity import training_rate_views
from ..rendering import RenderSettings
from .merge import merge_groups, ordered, representatives
from .moments import moments
from .removal import removal_groups
from .report import CompactResult, input_images
from .scoring import compaction_scores
from .views import compare, sight

#: Fine-tuning iterations per round with images (PUP 3D-GS fine-tunes 5,000 after each pruning).
DEFAULT_ITERATIONS = 5000
#: Views of the input's own renders that `distill` fine-tunes against.
DISTILL_VIEWS = 32
#: `compact(distill="auto")`, the default: clouds of up to AUTO_DISTILL_MAX Gaussians are
#: fine-tuned against their own renders for AUTO_DISTILL iterations in one round; larger ones are
#: not (its cost grows with the count: 10k Gaussians without a stored training pixel size, at 256
#: px, 1.5 s compacted, 17 s fine-tuned; 30k 2.2 and 32 s, at load 8-10). On the validation and
#: training scenes (chair,
#: tableware, plant, crate; scored from four training cameras), at 50 / 30% kept: none -0.46 /
#: -0.88 dB, 25 iterations twice -0.28 / -0.43, 50 once -0.25 / -0.41, 100 once -0.21 / -0.34
#: (two rounds of 200, the earlier choice, cost four times as much for -0.28 / -0.35 from placed
#: views, against -0.29 / -0.41 for 100 once) (BENCHMARKS.md, "Compaction").
AUTO_DISTILL = 100
AUTO_DISTILL_MAX = 50_000


def training_rate(src: GaussianCloud, cameras, cams: Sequence[Camera]) -> list[Camera]:
    """`cams` rescaled to the sampling rate the cloud was trained at (`fidelity.training_rate_views`:
    from its anti-aliasing size, else from the capture's `cameras` at their full size)."""
    rate_of = src
    if cameras is not None and not {FILTER_KEY, DILATION_KEY} & set(src.extra):
        rate_of = with_dilation_3d(src, list(cameras))
    return training_rate_views(rate_of, cams)


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
    # one height for all: the lowest view's (the median lost 0.1-0.25 dB on the validation scenes)
    height = int(min(c.height for c in training_rate(src, cameras, cams)))
    cams = [c.scaled(height) for c in cams]
    return Views(cams, np.stack([img.numpy() for img in input_images(src, cams, settings or RenderSettings())]))


def compact_with_images(src: GaussianCloud, target: int, images, how: dict, rounds: int, iterations: int, seed: int,
                        views: int, resolution: int, settings: RenderSettings, say, timings: dict,
                        extra: Sequence[Camera] = (), inside=None) -> CompactResult:
    """PUP 3D-GS's rounds: remove part of the way (the fraction kept per round the same), fine-tune.
    Each round scores from `views` of the images' cameras (`capture.scoring_views`); what none of
    the images' cameras (nor the `extra` views, nor those `inside` gives, `views.sight`) sees is
    dropped as unseen."""
    from ..train import TrainConfig, fine_tune  # noqa: PLC0415 - training loads only with images

    n = len(src)
    mode = resolve_antialias(settings.antialias, src)
    config = TrainConfig(antialias="mip" if mode == "mip" else "classic", seed=seed)
    cur, groups = src, np.arange(n)
    first = None
    records = []
    cams = scoring_views(images.cameras, views, resolution, src)
    chosen = [c.world_to_cam for c in cams]
    others = [c.scaled(resolution) if c.height > resolution else c for c in images.cameras
              if not any(np.array_equal(c.world_to_cam, w) for w in chosen)] + list(extra)
    reference = input_images(src, cams, settings)
    for r in range(rounds):
        count = max(target, int(round(n * (target / n) ** ((r + 1) / rounds))))
        base = 0.9 * r / rounds
        t0 = time.perf_counter()
        say(base, f"round {r + 1}/{rounds}: scoring {len(cur):,} Gaussians ({how['score']})")
        frames: list = []
        scores = compaction_scores(cur, how["score"], cams, settings=settings, seed=seed + r, frames=frames)
        seen = sight(cur, scores, how["score"], frames, others, settings, inside)
        del frames
        if first is None:
            first = (scores, seen)
        step = removal_groups(cur, scores, count, **how, seen=seen.seen)
        cur, _ = merge_groups(cur, step)
        groups = np.where(groups >= 0, step[np.maximum(groups, 0)], -1)
        timings["remove"] = timings.get("remove", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        before = training_psnr(cur, images, config)
        cur = fine_tune(cur, images, iterations, config=config, seed=seed + r,
                        progress=lambda f, msg, b=base, k=r + 1: say(b + 0.9 / rounds * (0.2 + 0.8 * f),
                                                                     f"round {k}/{rounds}: {msg}"))
        seconds = time.perf_counter() - t0
        timings["fine-tune"] = timings.get("fine-tune", 0.0) + seconds
        records.append({"count": len(cur), "seconds": seconds, "psnr_before": before,
                        "psnr_after": training_psnr(cur, images, config)})
    idx = np.flatnonzero(groups >= 0)
    rows = representatives(groups, idx, moments(src.select(idx), np.zeros(len(idx))).mass)
    groups, rows, cur = ordered(groups, rows, cur)
    t0 = time.perf_counter()
    # (what the first round's views saw of the input)
    result = compare(CompactResult(cur, rows, groups, first[0], 0.0, timings, records), src, reference, cams,
                     first[1], settings, len(cams))
    timings["report"] = time.perf_counter() - t0
    return result


def training_psnr(cloud: GaussianCloud, images, config) -> float:
    """Mean PSNR against (up to 8 of) the training images, over the trainer's background."""
    from ..train import evaluate_psnr  # noqa: PLC0415

    return evaluate_psnr(cloud, images, config.background, cloud.sh_degree, 8,
                         RenderSettings(antialias=config.antialias if config.antialias == "mip" else "matched"))
