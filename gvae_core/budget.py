"""The refine budget: which Gaussians the models densify, from their Hessian scores.

`select_budget` turns scores and a budget ('all', 'auto', a fraction or a count) into rows;
`parse_budget` reads a budget typed by a user, for the command line and the Blender panel alike.
`DEFAULT_FIDELITY` is how much of what the models did refine keeps, per method (here so that the
Blender panel, which must not import torch, reads the same default).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: 'auto' keeps between 1% and 50% of the Gaussians, whatever the score distribution says.
AUTO_FRACTION_RANGE = (0.01, 0.5)
#: refine's default fidelity tolerance per method (`gvae_core.fidelity.DEFAULT_TOLERANCES` says how
#: each was chosen).
DEFAULT_FIDELITY = {"detail": 0.04, "vae": 0.01}


def parse_budget(text: str) -> str | float | int:
    """A budget typed by a user (command line, Blender panel): 'auto' (also for empty text), 'all',
    a fraction in (0, 1] ('0.1' or '10%') or a count >= 1 ('5000'). A budget that selects nothing
    is refused: it can only be a typo."""
    t = str(text).strip().lower()
    if t in ("", "auto", "all"):
        return t or "auto"
    try:
        if t.endswith("%"):
            value: float | int = float(t[:-1]) / 100.0
        elif any(ch in t for ch in ".e"):
            value = float(t)
        else:
            value = int(t)
    except ValueError:
        raise ValueError(f"budget must be 'auto', 'all', a fraction in (0, 1] (0.1, 10%) or a count >= 1, "
                         f"got {text!r}") from None
    if isinstance(value, int) and value < 1:
        raise ValueError(f"budget count must be >= 1, got {text!r}")
    if isinstance(value, float) and not 0.0 < value <= 1.0:
        raise ValueError(f"budget fraction must be in (0, 1], got {text!r}")
    return value


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold: the cut that maximises the between-class variance of a 1D histogram."""
    v = np.asarray(values, np.float64)
    lo, hi = float(v.min()), float(v.max())
    if not hi > lo:
        return hi
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    p = hist / hist.sum()
    centers = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * centers)
    total = m0[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (total * w0 - m0) ** 2 / (w0 * (1.0 - w0))
    between[~np.isfinite(between)] = -1.0
    return float(edges[int(np.argmax(between)) + 1])


def select_budget(scores: np.ndarray, budget: Any) -> np.ndarray:
    """Rows (ascending) to refine. 'all': every row; a float in (0, 1]: that fraction of the rows
    with the highest scores; an int: that many; 'auto': the rows above Otsu's threshold of the
    scores (the high-score class) that are also more than one robust standard deviation
    (1.4826 MAD) above the median score, kept between 1% and 50% of the rows."""
    n = len(scores)
    if isinstance(budget, str):
        if budget == "all":
            return np.arange(n, dtype=np.int64)
        if budget != "auto":
            raise ValueError(f"budget must be 'all', 'auto', a fraction or a count, got {budget!r}")
        if n == 0:
            return np.zeros(0, np.int64)
        v = np.asarray(scores, np.float64)
        median = float(np.median(v))
        robust = median + 1.4826 * float(np.median(np.abs(v - median)))  # robust z-score of 1
        count = int((v > max(otsu_threshold(v), robust)).sum())
        lo, hi = (math.ceil(f * n) for f in AUTO_FRACTION_RANGE)
        count = min(max(count, lo), hi)
    elif isinstance(budget, (bool, np.bool_)):
        raise ValueError(f"budget must be 'all', 'auto', a fraction or a count, got {budget!r}")
    elif isinstance(budget, (int, np.integer)):
        if budget < 0:
            raise ValueError(f"budget count must be >= 0, got {budget}")
        count = min(int(budget), n)
    elif isinstance(budget, (float, np.floating)):
        if not 0.0 <= budget <= 1.0:
            raise ValueError(f"budget fraction must be in [0, 1], got {budget}")
        count = min(int(math.ceil(budget * n - 1e-9)), n)
    else:
        raise ValueError(f"budget must be 'all', 'auto', a fraction or a count, got {budget!r}")
    return _top_rows(np.asarray(scores, np.float64), count)


def _top_rows(scores: np.ndarray, count: int) -> np.ndarray:
    """The `count` rows with the highest scores, ties going to the lower row, ascending: the first
    `count` of a stable descending sort, in O(N) (`np.partition` instead of a sort)."""
    n = len(scores)
    if count <= 0:
        return np.zeros(0, np.int64)
    if count >= n:
        return np.arange(n, dtype=np.int64)
    cut = np.partition(scores, n - count)[n - count]   # the count-th largest value
    above = np.flatnonzero(scores > cut)
    ties = np.flatnonzero(scores == cut)[: count - len(above)]
    return np.sort(np.concatenate([above, ties])).astype(np.int64)
