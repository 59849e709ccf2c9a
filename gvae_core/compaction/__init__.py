"""Compaction: keep the Gaussians a cloud's picture uses, merge the ones it can do without.

Captures hold millions of Gaussians, many of which change no pixel, and many more that a few
larger ones would draw almost as well. `compact` brings a cloud down to a count (a fraction, a
number, or as few as keep the picture within a PSNR tolerance). Stages, one module each:

- `views`: where it looks from. The capture's cameras when given (a few score, every one of them
  says what it sees), else views placed all around (`capture.placed_views`: outside an object,
  below it too; inside a scene that surrounds its centre, with extra views outside it). A
  Gaussian is dropped as unseen only when every view misses it.
- `scoring`: how much the picture depends on each Gaussian: by default the exact Gauss-Newton
  block of position and log-scale over the scoring views (`gvae_core.hessian`), scored as log
  det(I + H/lambda), the sensitivity of PUP 3D-GS; baselines: LightGaussian's global significance,
  opacity, random.
- `removal`: which Gaussians go where. `merge` (the default) drops what no view sees and the
  lowest-scoring PRUNE_FRACTION of the input, and merges the rest pairwise over the neighbour
  graph (`graph`), cheapest first; a pair becomes one Gaussian that matches its moments with mass
  weights (`moments`: mass = opacity x mean projected area; the cost of a pair is its mass times
  how much merging changes it, times the two's scores). `prune` drops the lowest scores.
- `merge`: the compacted cloud assembled from the groups.
- `finetune`: with the capture's images (`images`) or against the input's own renders (`distill`),
  PUP's rounds of removal and fine-tuning with the project's trainer.
- `tolerance`: the count found from a PSNR tolerance.
- `report`: the result; the PSNR of the compacted cloud's renders against the input's from views
  that see what was removed, how many removed Gaussians those views did not see, and a warning
  when the views miss more than a small share of the cloud.
- `compiled`, `kernels`: the hit counts, moments, merge costs, matching, neighbour edges and merged
  groups as compiled CPU kernels (Numba) run in threads, where Numba is; the numpy and torch code
  they stand for stays beside them as their reference (and runs where Numba is not).

Why this design (docs/benchmarks/compact.md): merging keeps the picture far better than any
pruning score without fine-tuning; the Hessian's weighting of the merges matters little, its use
is choosing what is dropped rather than merged (what no view sees, and the lowest-scoring tenth).

Untouched Gaussians keep their values bit for bit, their rows in input order; a merged Gaussian
takes the row (and the extra properties) of its most massive member, with the anti-aliasing size
(`filter_3D`, `gvae_dilation_3D`) mass-averaged. `merge_groups_reference` and
`pixel_hits_reference` are the slow, obviously correct definitions the tests hold the fast ones to.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from ..camera import Camera
from ..capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS
from ..cloud import GaussianCloud
from ..hessian import scoring_settings
from ..rendering import RenderSettings
from ..resources import check_compact_memory, reuse_freed_memory
from . import finetune
from .finetune import (AUTO_DISTILL, AUTO_DISTILL_MAX, AUTO_DISTILL_SECONDS, CHECK_EVERY, DEFAULT_ITERATIONS,
                       DISTILL_ASIDE, DISTILL_CHECK_EVERY, DISTILL_VIEWS, PHOTOS_PRUNE_FROM, PHOTOS_REMOVAL,
                       PHOTOS_SCORE, PRUNE_FROM_ITERATIONS, SET_ASIDE_EVERY, Tuning, TuningOptions,
                       compact_with_images, fine_tune_height, fine_tune_images, own_renders, set_aside,
                       still_gaining)
from .graph import NEIGHBOURS, owner_root
from .inputs import CompactInputs, compaction_inputs
from .merge import merge_groups, merge_groups_reference, ordered
from .moments import COLOUR_WEIGHT
from .removal import PRUNE_FRACTION, REMOVALS, removal_groups, target_count
from .report import PSNR_CAP, UNSEEN_WARNING, CompactResult, input_images, unseen_warning
from .scoring import SCORES, UNSEEN, compaction_scores, pixel_hits, pixel_hits_reference
from .tolerance import tolerance_count
from .views import CompactionViews, compaction_views, compare, sight

__all__ = ["SCORES", "REMOVALS", "CompactInputs", "CompactResult", "CompactionViews", "compact", "compaction_inputs",
           "compaction_scores",
           "compaction_views", "default_iterations", "default_method", "distill_iterations", "fine_tune_height",
           "fine_tune_images", "merge_groups", "merge_groups_reference", "own_renders", "owner_root", "pixel_hits",
           "pixel_hits_reference", "removal_groups", "set_aside", "target_count", "TuningOptions", "AUTO_DISTILL",
           "AUTO_DISTILL_MAX", "AUTO_DISTILL_SECONDS", "CHECK_EVERY", "COLOUR_WEIGHT", "DEFAULT_ITERATIONS",
           "DISTILL_ASIDE", "DISTILL_VIEWS", "NEIGHBOURS", "PHOTOS_PRUNE_FROM", "PHOTOS_REMOVAL", "PHOTOS_SCORE",
           "PRUNE_FROM_ITERATIONS", "PRUNE_FRACTION", "PSNR_CAP", "SET_ASIDE_EVERY", "UNSEEN", "UNSEEN_WARNING"]


# ------------------------------------------------------------------------------ checks

def _check_input(src: GaussianCloud, score: str, removal: str, prune: float) -> None:
    if len(src) == 0:
        raise ValueError("compact: the cloud is empty (nothing to compact)")
    if isinstance(prune, bool) or not isinstance(prune, (int, float, np.floating)) or not 0.0 <= prune < 1.0:
        raise ValueError(f"compact: prune must be a fraction in [0, 1), got {prune!r}")
    if score not in SCORES:
        raise ValueError(f"compact: score must be one of {', '.join(SCORES)}, got {score!r}")
    if removal not in REMOVALS:
        raise ValueError(f"compact: removal must be one of {', '.join(REMOVALS)}, got {removal!r}")
    bad = src.nonfinite_rows()
    if len(bad):
        rows = ", ".join(str(int(r)) for r in bad[:5])
        raise ValueError(f"compact: the cloud has non-finite values in {len(bad)} row(s) "
                         f"[{rows}{', ...' if len(bad) > 5 else ''}]; sanitize it first")


def default_method(images, keep, count, n: int, score: str | None, removal: str | None) -> tuple[str, str]:
    """(score, removal): those asked for, or where neither is, the default of the path: with
    `images` keeping PHOTOS_PRUNE_FROM or more of the `n` Gaussians, PHOTOS_SCORE pruned
    (PHOTOS_REMOVAL); else the Hessian's merge. One given alone goes with the other's "hessian" or
    "merge"."""
    if score is None and removal is None and images is not None and _kept(keep, count, n) >= PHOTOS_PRUNE_FROM:
        return PHOTOS_SCORE, PHOTOS_REMOVAL
    return score or "hessian", removal or "merge"


def default_iterations(keep, count, n: int) -> int:
    """The most fine-tuning iterations a round with images when none are asked for: keeping
    PHOTOS_PRUNE_FROM or more of the `n` Gaussians, PRUNE_FROM_ITERATIONS, else DEFAULT_ITERATIONS
    (`finetune` says why)."""
    return PRUNE_FROM_ITERATIONS if _kept(keep, count, n) >= PHOTOS_PRUNE_FROM else DEFAULT_ITERATIONS


def _kept(keep, count, n: int) -> float:
    """The fraction kept that `keep` or `count` of `n` asks for (0 when a tolerance decides)."""
    fraction = count / n if _number(count) and n else keep
    return float(fraction) if _number(fraction) else 0.0


def _number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _whole(value, name: str, low: int) -> int:
    """`value` as a whole number >= low, else ValueError naming it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"compact: {name} must be a whole number >= {low}, got {value!r}")
    return int(value)


def distill_iterations(distill, n: int, images, tolerance) -> int:
    """The fine-tuning iterations against the input's own renders that `distill` asks for: a whole
    number as it is; "auto" (the default): AUTO_DISTILL for a cloud of at most AUTO_DISTILL_MAX
    Gaussians compacted to a fraction or a count without images, else none."""
    if isinstance(distill, str):
        if distill != "auto":
            raise ValueError(f"compact: distill must be 'auto' or a whole number of iterations, got {distill!r}")
        return AUTO_DISTILL if images is None and tolerance is None and n <= AUTO_DISTILL_MAX else 0
    _whole(distill, "distill (iterations)", 0)
    if distill and (images is not None or tolerance is not None):
        raise ValueError("compact: distill fine-tunes against the input's own renders: without images or a "
                         "tolerance")
    return int(distill)


def _check_arguments(n: int, keep, count, tolerance, images, distill: int, rounds, iterations) -> int | None:
    """The target count (None: found from the tolerance), or ValueError for arguments that do not
    go together or are out of range."""
    if images is not None or distill:
        if rounds is not None:
            _whole(rounds, "rounds", 1)
        _whole(iterations, "iterations", 0)
        if images is not None and len(images) == 0:
            raise ValueError("compact: no images")
    if tolerance is None:
        return target_count(n, keep, count)
    if keep is not None or count is not None:
        raise ValueError("compact: give one of keep, count or tolerance")
    if images is not None:
        raise ValueError("compact: a tolerance works without images (the count is found from the input's own "
                         "render); with images give a fraction or a count")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating)) \
            or not math.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"compact: tolerance must be a PSNR in dB > 0 (for example 40), got {tolerance!r}")
    return None


# ------------------------------------------------------------------------------ compact

def compact(cloud: GaussianCloud, *, keep: float | None = None, count: int | None = None,
            tolerance: float | None = None, cameras: Sequence[Camera] | None = None, views: int = DEFAULT_VIEWS,
            resolution: int = DEFAULT_RESOLUTION, score: str | None = None, removal: str | None = None,
            images=None, rounds: int | None = None, iterations: int | None = None, distill: int | str = "auto",
            plateau: bool = True, seed: int = 0,
            neighbours: int = NEIGHBOURS, prune: float = PRUNE_FRACTION, colour_weight: float = COLOUR_WEIGHT,
            render_settings: RenderSettings | None = None, tuning_options: TuningOptions | None = None,
            progress: Callable[[float, str], None] | None = None, check_memory: bool = True) -> CompactResult:
    """`cloud` with fewer Gaussians: `keep` a fraction in (0, 1], a `count`, or the fewest whose
    render from the scoring views, at the training sampling rate, stays at or above `tolerance`
    dB of PSNR against the input's (give exactly one). See the module docstring for how.

    `cameras`: the capture's cameras (`capture.load_cameras`): `views` of them, spread out, scaled to
    `resolution` px high, score; every one says what it sees. Else views placed all around the cloud
    (`capture.placed_views`; `views` of them score). `score`: one of SCORES; `removal`: "merge" or
    "prune"; by default the Hessian's merge, with `images` keeping PHOTOS_PRUNE_FROM or more
    LightGaussian's prune (`default_method`: what the images set aside chose); `prune`: the fraction of
    the input that merging drops first, the lowest scores (`removal_groups`; 0: merge all that is seen);
    `neighbours`: of each Gaussian in the merge graph; `colour_weight`: of the colour difference in the
    merge cost (`moments.pair_cost`). `images`: the capture's training images
    (`datasets.Views`, in the cloud's frame, at the resolution to fine-tune at): `rounds` rounds
    (default 1) of removal and at most `iterations` (None: `default_iterations`) of fine-tuning each
    (`train.fine_tune`), the scores
    then come from `images`' cameras; with `plateau` (the default) every SET_ASIDE_EVERY-th image is set
    aside, never trained on, and each round's fine-tuning stops when their PSNR stops rising
    (`finetune.tune`), without it every iteration runs. `distill`: without images, fine-tune as with
    them, at most `distill` iterations a round (`rounds`, default 1), against the input's own renders
    (`own_renders`: DISTILL_VIEWS views, of `cameras` or placed around the cloud, at the training
    sampling rate; with `plateau`, DISTILL_ASIDE more set aside to judge); "auto" (the default): at most
    AUTO_DISTILL iterations, stopped after AUTO_DISTILL_SECONDS, for a cloud of up to AUTO_DISTILL_MAX
    Gaussians, none for a larger one (`distill_iterations`); 0: score, drop and merge only. `seed`: the
    random score and the fine-tuning; `tuning_options`: what a study changes in the fine-tuning
    (`finetune.TuningOptions`; default: the product's).
    `progress(fraction, message)` as the work goes on (an exception it raises stops the work:
    how the Blender job cancels). `check_memory`: refuse a cloud whose estimated peak memory
    exceeds what is free (`resources.NotEnoughMemoryError`). Every check on the arguments and the
    cloud is made before any work; the input is never modified."""
    t_start = time.perf_counter()
    say = progress or (lambda fraction, message: None)
    src = cloud.numpy()
    n = len(src)
    score, removal = default_method(images, keep, count, n, score, removal)
    _check_input(src, score, removal, prune)
    auto = isinstance(distill, str)
    distill = distill_iterations(distill, n, images, tolerance)
    iterations = default_iterations(keep, count, n) if iterations is None else iterations
    target = _check_arguments(n, keep, count, tolerance, images, distill, rounds, iterations)
    if check_memory:
        extra = sum(int(np.prod(np.shape(v)[1:], dtype=np.int64)) for v in src.extra.values())
        check_compact_memory(n, src.sh_degree, extra_values=extra, views=views or DEFAULT_VIEWS,
                             resolution=resolution, neighbours=neighbours)
    settings = scoring_settings(render_settings)
    timings: dict[str, float] = {}
    how = {"score": score, "removal": removal, "neighbours": neighbours, "prune": prune,  # removal_groups'
           "colour_weight": colour_weight}
    with reuse_freed_memory():
        t0 = time.perf_counter()
        looks = None if images is not None else compaction_views(src, cameras, views, resolution)
        timings["views"] = time.perf_counter() - t0
        tuning = _tuning(src, images, cameras, distill, auto, 1 if rounds is None else rounds, iterations, plateau,
                         resolution, settings, seed, tuning_options or TuningOptions(), say)
        if tuning is not None:  # (distilled: every capture camera, or a placed scene's extra views, also looks)
            extra = [] if looks is None else looks.others if looks.placed else looks.scoring + looks.others
            result = compact_with_images(src, target, tuning, how, seed, views, resolution, settings, say, timings,
                                         extra, None if looks is None else looks.inside)
        else:
            result = _compact(src, target, tolerance, cameras, looks, how, seed, settings, say, timings,
                              listened=progress is not None)
    result.warnings = unseen_warning(n, result.unseen, looks is not None and looks.placed) + still_gaining(
        result.rounds, f"--iterations (more than {iterations:,})" if images is not None else
        f"--distill (more than {distill:,}; Fine-Tune Iterations in Blender)")
    result.cloud = result.cloud.replace(background=src.background)  # drawn over what the input was trained over
    timings["total"] = time.perf_counter() - t_start
    say(1.0, result.summary())
    return result


def _tuning(src: GaussianCloud, images, cameras, distill: int, auto: bool, rounds: int, iterations: int,
            plateau: bool, resolution: int, settings: RenderSettings, seed: int, options: TuningOptions,
            say) -> Tuning | None:
    """How the fine-tuning goes (None: there is none): against the input's own renders with
    `distill` iterations, else with the capture's `images`; with `plateau`, views set aside judge it."""
    if distill:
        say(0.0, "rendering the input for the fine-tuning")
        aside = DISTILL_ASIDE if plateau else 0
        drawn = settings if options.distill_target == "auto" else \
            replace(settings, antialias=finetune.tuning_config(src, settings, seed, options.train_overrides).antialias)
        renders = own_renders(src, cameras, resolution, drawn, DISTILL_VIEWS + aside)
        fit, judge = set_aside(renders, (DISTILL_VIEWS + aside) // aside) if aside else (renders, None)
        return Tuning(fit, judge, distill, rounds, "the input's own renders", DISTILL_CHECK_EVERY,
                      seconds=AUTO_DISTILL_SECONDS if auto else None, average=options.distill_average,
                      train_overrides=options.train_overrides)
    if images is not None:
        fit, judge = set_aside(images) if plateau else (images, None)
        return Tuning(fit, judge, iterations, rounds, average=options.average,
                      train_overrides=options.train_overrides)
    return None


def _compact(src: GaussianCloud, target: int | None, tolerance, cameras, looks: CompactionViews, how: dict, seed: int,
             settings: RenderSettings, say, timings: dict, listened: bool = True) -> CompactResult:
    """Compaction without fine-tuning: score, see, remove, merge, report. `listened`: whether a
    caller follows the progress (without one the scoring is given none, and so does not make
    every renderer kernel ready up front to say that it compiles: `rendering.compiled.compile_kernels`;
    they load as they are first used)."""
    n = len(src)
    cams = looks.scoring
    t0 = time.perf_counter()
    frames: list = []
    say(0.0, f"scoring {n:,} Gaussians ({how['score']})")
    scores = compaction_scores(src, how["score"], cams, settings=settings, seed=seed, frames=frames,
                               progress=(lambda f, msg: say(0.6 * f, msg)) if listened else None)
    timings["score"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    seen = sight(src, scores, how["score"], frames, looks.others, settings, inside=looks.inside)
    timings["sight"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    reference = input_images(src, cams, settings, frames)
    del frames
    how = {**how, "seen": seen.seen}
    if target is None:
        target = tolerance_count(src, scores, float(tolerance), cameras, cams, how, settings, say)
        timings["tolerance search"] = time.perf_counter() - t0
        t0 = time.perf_counter()
    say(0.65, f"removing {n - target:,} of {n:,} Gaussians ({how['removal']})")
    groups = removal_groups(src, scores, target, **how, progress=lambda f, msg: say(0.65 + 0.25 * f, msg))
    out, rows = merge_groups(src, groups)
    groups, rows, out = ordered(groups, rows, out)
    timings["remove"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    say(0.92, "comparing the pictures")
    result = compare(CompactResult(out, rows, groups, scores, 0.0, timings, tolerance=tolerance), src, reference,
                     cams, seen, settings, len(cams))
    timings["report"] = time.perf_counter() - t0
    return result
