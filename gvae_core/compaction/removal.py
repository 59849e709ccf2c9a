"""Which input Gaussians go where: `removal_groups` gives every input row its output row (-1:
dropped) for a target count, from the scores and what the views see.

`merge` (the default): the Gaussians no view sees are dropped, and so are the lowest-scoring
PRUNE_FRACTION of the input (those the picture depends on least: merged into a neighbour, they
would change it for little; never more than the removal); the rest are merged pairwise over the
neighbour graph (`graph.merge_owner`), their merge cost weighted by their scores. `prune`: the
lowest scores are dropped (PUP 3D-GS's pruning).
"""

from __future__ import annotations

import numpy as np

from ..budget import select_budget
from ..cloud import GaussianCloud
from .graph import NEIGHBOURS, merge_owner
from .moments import COLOUR_WEIGHT, moments
from .scoring import UNSEEN, merge_weights

#: How Gaussians are removed: merged into neighbours, or dropped.
REMOVALS = ("merge", "prune")
#: Scores that measure the picture (zero for a Gaussian the scoring views do not see).
PICTURE_SCORES = ("hessian", "lightgaussian")
#: Fraction of the input that `merge` drops (the lowest scores among the seen ones, never more than
#: the removal) before merging the rest: what the picture can do without is dropped, not merged.
PRUNE_FRACTION = 0.1


def target_count(n: int, keep=None, count=None) -> int:
    """The count `keep` (a fraction in (0, 1]) or `count` (1..n) asks for of `n` Gaussians."""
    if (keep is None) == (count is None):
        raise ValueError("compact: give one of keep (a fraction) or count")
    if keep is not None:
        try:
            keep = float(keep)
        except (TypeError, ValueError):
            raise ValueError(f"compact: keep must be a fraction in (0, 1], got {keep!r}") from None
        if not 0.0 < keep <= 1.0:
            raise ValueError(f"compact: keep must be a fraction in (0, 1], got {keep!r}")
        return max(1, min(n, round(keep * n)))
    if isinstance(count, (bool, np.bool_)) or not isinstance(count, (int, np.integer)):
        raise ValueError(f"compact: count must be a whole number of Gaussians, got {count!r}")
    if not 1 <= count <= n:
        raise ValueError(f"compact: count must be between 1 and the input's {n:,} Gaussians, got {count:,}")
    return int(count)


def seen_weights(scores: np.ndarray, score: str, seen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(weights, visible): each Gaussian's merge weight (`scoring.merge_weights`) and whether some
    view sees it. For a score of the picture, visible = a score above UNSEEN or `seen` (what other
    views see: the capture's other cameras, a scene's extra views); a Gaussian that only those see
    is weighted as the median seen one (the scoring views cannot tell how much the picture needs
    it). For the other scores every Gaussian is visible."""
    weight = merge_weights(scores, score)
    if score not in PICTURE_SCORES:
        return weight, np.ones(len(weight), bool)
    scored = weight > UNSEEN
    if seen is None:
        return weight, scored
    visible = scored | np.asarray(seen, bool)
    unscored = visible & ~scored
    if unscored.any():
        weight = weight.copy()
        weight[unscored] = float(np.median(weight[scored])) if scored.any() else 1.0
    return weight, visible


def groups_by_pruning(scores: np.ndarray, target: int) -> np.ndarray:
    kept = select_budget(scores, int(target))
    groups = np.full(len(scores), -1, np.int64)
    groups[kept] = np.arange(len(kept))
    return groups


def removal_groups(src: GaussianCloud, scores: np.ndarray, target: int, *, score: str = "hessian",
                   removal: str = "merge", neighbours: int = NEIGHBOURS, prune: float = PRUNE_FRACTION,
                   seen: np.ndarray | None = None, colour_weight: float = COLOUR_WEIGHT,
                   progress=None) -> np.ndarray:
    """(N,) the output row of each input row (-1: dropped) that brings `src` to `target` rows:
    removal "prune" keeps the `target` highest scores; "merge" drops what no view sees and, for a
    score of the picture ("hessian", "lightgaussian"), the lowest-scoring fraction `prune` of the
    input besides, and merges the rest pairwise (module docstring). `seen`: (N,) bool, what views
    other than the scoring ones see (`seen_weights`: never dropped as unseen); `colour_weight`: of
    the merge cost (`moments.pair_cost`)."""
    n = len(src)
    if target >= n:
        return np.arange(n)
    weight, visible = seen_weights(scores, score, seen)
    if removal == "prune":
        return groups_by_pruning(weight if score in PICTURE_SCORES else scores, target)
    kept = np.flatnonzero(visible)
    if len(kept) <= target:  # dropping what is not seen is enough: keep the highest scores
        return groups_by_pruning(weight, target)
    if score in PICTURE_SCORES:
        drop = min(int(round(prune * n)), len(kept) - target)
        kept = np.sort(kept[np.argsort(weight[kept], kind="stable")[drop:]])
    m = moments(src, weight[kept], rows=kept, colour_weight=colour_weight)
    sub = merge_owner(m, target, neighbours, progress)
    groups = np.full(n, -1, np.int64)
    # output rows in input order of their representatives
    first = np.full(target, n, np.int64)
    np.minimum.at(first, sub, kept)
    remap = np.empty(target, np.int64)
    remap[np.argsort(first, kind="stable")] = np.arange(target)
    groups[kept] = remap[sub]
    return groups
