"""Refinement past the training resolution (DESIGN.md step 5).

Score the input Gaussians (Hessian), pick the budget's share, and run the lineage VAEs for
`steps` sequential steps: each step extends every lineage selected so far by one stage. The
budget says where to densify: the selected Gaussians all densify at the first step; the models
say how (how many children, where, how large, what colour) and, at later steps, whether each
descendant densifies again, as they learned from progressive training. Later steps change
geometry only (children carry their parent's appearance, `carry_appearance`). With the budget
"all" every Gaussian is given to the models, which decide at every step. For a lineage, the
existing slot nearest its last node updates that Gaussian in place; every other existing slot
becomes a new Gaussian (appended after the input rows). Outputs are sanitised: finite, unit
quaternions, log-scales and opacity logits inside finite ranges.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch

from ._callable import make_module_callable
from .camera import Camera
from .cloud import _FIELDS, EXTREME_LOG_SCALE, OPACITY_LOGIT_RANGE, SH_REST_COUNTS, GaussianCloud, normalize_quats

AUTO_FRACTION_RANGE = (0.01, 0.5)
OUTPUT_SH_LIMIT = 1e3


@dataclass
class RefineResult:
    """The refined cloud (input rows first, in input order, then the added ones), which rows were
    added, each added row's parent row in the input, the step that added it, the input's Hessian
    scores, the input rows the budget selected, and seconds per part."""

    cloud: GaussianCloud
    added: np.ndarray
    parents: np.ndarray
    step: np.ndarray
    scores: np.ndarray
    selected: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def n_input(self) -> int:
        return len(self.cloud) - len(self.added)

    def summary(self) -> str:
        per_step = np.bincount(self.step, minlength=int(self.step.max(initial=0)) + 1)[1:]
        times = ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in self.timings.items())
        return (f"{self.n_input} Gaussians in, {len(self.selected)} selected, {len(self.added)} added "
                f"(per step: {', '.join(str(int(c)) for c in per_step) or '-'}), {len(self.cloud)} out; {times}")


def parse_budget(text: str) -> str | float | int:
    """CLI budget: 'all', 'auto', a fraction ('0.1' or '10%') or a count ('5000')."""
    t = str(text).strip().lower()
    if t in ("all", "auto"):
        return t
    try:
        if t.endswith("%"):
            return float(t[:-1]) / 100.0
        if any(ch in t for ch in ".e"):
            return float(t)
        return int(t)
    except ValueError:
        raise ValueError(f"budget must be 'all', 'auto', a fraction (0.1, 10%) or a count, got {text!r}") from None


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


def _initial_history(cloud: GaussianCloud, lineage: Any, selected: np.ndarray):
    """Node features (M,T,11), (M,T,50) of the selected rows, and the normalisation's scale. The
    last node is always the input Gaussian itself; earlier nodes come from the lineage when given.
    Without a lineage the selected rows are one-node lineages (as `Lineage.from_cloud` makes them)
    in the frame of the whole cloud (`scene_normalization`)."""
    from .lineage import appearance_features, geometry_features, scene_normalization  # noqa: PLC0415

    sub = cloud.select(selected)
    center, scale = scene_normalization(cloud.means) if lineage is None else (lineage.center, lineage.scale)
    geo = geometry_features(sub, center, scale)[:, None]
    app = appearance_features(sub)[:, None]
    if lineage is not None and lineage.n_stages > 1:
        seq = lineage.sequences(lineage.n_stages - 1)
        ids = cloud.extra.get("gvae_id")
        if ids is not None and len(ids) == len(cloud):
            order = np.argsort(seq.ids, kind="stable")
            ids = np.asarray(ids).astype(np.int64)
            at = np.clip(np.searchsorted(seq.ids[order], ids), 0, max(len(order) - 1, 0))
            rows = np.where(seq.ids[order][at] == ids, order[at], -1) if len(order) else np.full(len(ids), -1)
            if (rows < 0).any():
                raise ValueError(f"refine: {int((rows < 0).sum())} Gaussian id(s) of the cloud are not alive at the "
                                 f"lineage's last stage")
        elif len(seq) == len(cloud):
            rows = np.arange(len(cloud))
        else:
            raise ValueError(f"refine: the lineage's last stage has {len(seq)} Gaussians but the cloud has "
                             f"{len(cloud)} (and no gvae_id property to match them)")
        rows = rows[selected]
        geo = np.concatenate([seq.geometry[rows, :-1], geo], 1)
        app = np.concatenate([seq.appearance[rows, :-1], app], 1)
    return geo, app, float(scale)


def _finite(x: np.ndarray) -> np.ndarray:
    return x if np.isfinite(x).all() else np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def _sanitize_rows(geo: np.ndarray, app: np.ndarray, world_pos: np.ndarray, scale: float, sh_degree: int):
    """Raw, finite, bounded parameters of predicted nodes (the inverse of the lineage features,
    `cloud_from_features`, with positions given in world units, float64)."""
    from .lineage import APP_OPACITY, APP_SH_DC, APP_SH_REST, GEO_LOG_SCALE, GEO_QUAT  # noqa: PLC0415

    geo = _finite(geo)
    app = np.clip(_finite(app), -OUTPUT_SH_LIMIT, OUTPUT_SH_LIMIT).astype(np.float32, copy=False)
    big = np.finfo(np.float32).max / 4
    return GaussianCloud(
        means=np.clip(_finite(world_pos), -big, big).astype(np.float32),
        scales=np.clip(geo[:, GEO_LOG_SCALE] + math.log(scale), *EXTREME_LOG_SCALE).astype(np.float32),
        quats=normalize_quats(geo[:, GEO_QUAT].astype(np.float32)),
        opacities=np.clip(app[:, APP_OPACITY], *OPACITY_LOGIT_RANGE),
        sh_dc=app[:, APP_SH_DC].copy(),
        sh_rest=app[:, APP_SH_REST].reshape(-1, 15, 3)[:, :SH_REST_COUNTS[sh_degree]].copy())


def refine(cloud: GaussianCloud, *, steps: int = 1, budget: Any = "auto", model: Any = None,
           cameras: Sequence[Camera] | None = None, lineage: Any = None, seed: int = 0,
           progress: Callable[[float, str], None] | None = None, hessian_options: dict | None = None,
           scores: Any = None, carry_appearance: bool = True) -> RefineResult:
    """Refine `cloud` by `steps` (>= 1) sequential model steps on the Gaussians the budget selects
    (see `select_budget`). `model`: a `GaussianVAE` or a model directory (default: the bundled
    one). `cameras`: views for the Hessian (default: views placed around the cloud). `lineage`:
    the training lineage whose last stage is this cloud (default: one-node lineages). `scores`:
    precomputed Hessian scores (skips scoring). `carry_appearance`: after the first step the model
    changes geometry only, every child taking its parent's colour, SH and opacity (fed its own
    predictions, the model's appearance changes compound and PSNR above the training resolution
    falls with every step; `reports/` has the ablation). Raises ValueError on non-finite input
    rows."""
    result = None
    for result in refine_steps(cloud, steps=steps, budget=budget, model=model, cameras=cameras, lineage=lineage,
                               seed=seed, progress=progress, hessian_options=hessian_options, scores=scores,
                               every_step=False, carry_appearance=carry_appearance):
        pass
    return result


def refine_steps(cloud: GaussianCloud, *, steps: int = 1, budget: Any = "auto", model: Any = None,
                 cameras: Sequence[Camera] | None = None, lineage: Any = None, seed: int = 0,
                 progress: Callable[[float, str], None] | None = None, hessian_options: dict | None = None,
                 scores: Any = None, every_step: bool = True,
                 carry_appearance: bool = True) -> Iterator[RefineResult]:
    """`refine`, yielding the result after every step (+1, +2, ...; each one the same as `refine`
    with that many steps and the same seed), or only after the last with `every_step=False`."""
    from .vae import GaussianVAE, load_default_model  # noqa: PLC0415

    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    say = progress or (lambda fraction, message: None)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"refine: steps must be an integer >= 1, got {steps!r}")
    src = cloud.numpy()
    bad = src.nonfinite_rows()
    if len(bad):
        rows = ", ".join(str(int(r)) for r in bad[:5])
        raise ValueError(f"refine: the cloud has non-finite values in {len(bad)} row(s) "
                         f"[{rows}{', ...' if len(bad) > 5 else ''}]; sanitize it first")
    n = len(src)

    t0 = time.perf_counter()
    if model is None:
        model = load_default_model()
    elif not isinstance(model, GaussianVAE):
        model = GaussianVAE.load(model)
    timings["load"] = time.perf_counter() - t0

    say(0.05, "scoring Gaussians (Hessian)")
    t0 = time.perf_counter()
    if scores is None and budget == "all":
        scores = np.zeros(n, np.float32)  # every Gaussian is refined: nothing to rank
    if scores is None:
        from .hessian import hessian_scores  # noqa: PLC0415

        scores = hessian_scores(src, cameras, seed=seed, **(hessian_options or {}))
    scores = np.nan_to_num(np.asarray(scores.detach().cpu() if torch.is_tensor(scores) else scores,
                                      np.float32).reshape(-1), nan=0.0, posinf=0.0, neginf=0.0)
    if len(scores) != n:
        raise ValueError(f"refine: {len(scores)} scores for {n} Gaussians")
    timings["hessian"] = time.perf_counter() - t0
    selected = select_budget(scores, budget)

    t0 = time.perf_counter()
    hist_g, hist_a, scale = _initial_history(src, lineage, selected)
    timings["features"] = time.perf_counter() - t0

    gen = torch.Generator().manual_seed(int(seed))
    grow = _Growth(src, selected, hist_g, hist_a, scale)
    for k in range(1, steps + 1):
        say(0.1 + 0.85 * (k - 1) / steps, f"step {k}/{steps}: {len(grow.rows)} lineages")
        if len(grow.rows):
            # The budget chose these Gaussians to densify at the first step; later steps (and
            # every step with "all") let the model decide, lineage by lineage.
            grow.step(k, model, None if budget == "all" or k > 1 else np.ones(len(grow.rows), bool), gen,
                      more=k < steps, carry_appearance=carry_appearance and k > 1)
        if every_step or k == steps:
            final = k == steps
            if final:
                say(0.97, "assembling the refined cloud")
            result = grow.result(scores, {**timings}, t_start)
            if final:
                say(1.0, result.summary())
            suspended = time.perf_counter()
            yield result
            t_start += time.perf_counter() - suspended  # the caller's time is not ours


class _Growth:
    """The lineages being extended, step after step, and what they have added so far."""

    def __init__(self, src: GaussianCloud, selected: np.ndarray, hist_g: np.ndarray, hist_a: np.ndarray,
                 scale: float):
        self.src, self.selected, self.scale = src, selected, scale
        self.hist_g, self.hist_a = hist_g, hist_a
        self.rows = selected.copy()     # current-cloud row of each active lineage
        self.roots = selected.copy()    # its ancestor row in the input
        self.world = src.means[selected].astype(np.float64)  # exact world positions of the last nodes
        self.new_parts: list[GaussianCloud] = []
        self.updates: list[tuple[np.ndarray, GaussianCloud]] = []  # (rows, new values), in step order
        self.added_parents: list[np.ndarray] = []
        self.added_steps: list[np.ndarray] = []
        self.n_total = len(src)
        self.model_time = 0.0

    def step(self, k: int, model, densify, gen: torch.Generator, more: bool = True,
             carry_appearance: bool = False) -> None:
        """Extend every active lineage by one predicted stage (and, when `more` steps follow,
        make the lineages of the next one)."""
        t0 = time.perf_counter()
        max_nodes = max(model.geometry.config.max_nodes, model.appearance.config.max_nodes)
        g, a, p, _ = model.predict(self.hist_g[:, -max_nodes:], self.hist_a[:, -max_nodes:], densify, generator=gen)
        g, a, p = g.numpy().astype(np.float64), a.numpy(), p.numpy()
        if carry_appearance:  # every slot takes the last node's appearance; existence stays the model's
            a[..., :-1] = self.hist_a[:, -1, None, :-1]
        self.model_time += time.perf_counter() - t0
        last = self.hist_g[:, -1].astype(np.float64)
        size = np.exp(np.clip(last[:, 7:10], -20.0, 10.0).mean(1))
        last_pos = np.clip(np.nan_to_num(last[:, 0:3]), -1e6, 1e6)
        dist = np.linalg.norm(g[..., 0:3] - last_pos[:, None], axis=-1) / size[:, None]
        # Existence is sampled (seeded): thresholding at 0.5 would never add a child whose
        # probability is below one half, under-generating systematically.
        exists = torch.rand(p.shape, generator=gen).numpy() < p
        keeper = np.argmin(np.where(exists, dist, np.inf), 1)
        # World positions: the parent's exact world position plus the predicted offset.
        child_world = self.world[:, None] + (g[..., 0:3] - last_pos[:, None]) * self.scale
        # Updated parents (the nearest existing slot), then the extra slots as new Gaussians.
        upd = np.flatnonzero(exists.any(1))
        ks = keeper[upd]
        sh_degree = self.src.sh_degree
        if len(upd):
            self.updates.append((self.rows[upd], _sanitize_rows(g[upd, ks], a[upd, ks], child_world[upd, ks],
                                                                self.scale, sh_degree)))
        extra = exists.copy()
        extra[upd, ks] = False
        li, si = np.nonzero(extra)
        new_rows = self.n_total + np.arange(len(li))
        if len(li):
            self.new_parts.append(_sanitize_rows(g[li, si], a[li, si], child_world[li, si], self.scale, sh_degree))
            self.added_parents.append(self.roots[li])
            self.added_steps.append(np.full(len(li), k, np.int64))
            self.n_total += len(li)
        if not more:
            self.rows = self.rows[:0]
            return
        # Next step's lineages: updated parents and their new siblings, one node longer.
        g_node = g.astype(np.float32)
        g_node[..., 10] = 1.0
        a[..., 49] = 1.0
        cont = np.concatenate([upd, li])
        slot = np.concatenate([ks, si])
        prev_g, prev_a = self.hist_g[cont], self.hist_a[cont]  # fancy indexing copies
        prev_g[len(upd):, :, 10] = 0.0
        prev_a[len(upd):, :, 49] = 0.0
        self.hist_g = np.concatenate([prev_g, g_node[cont, slot][:, None]], 1)
        self.hist_a = np.concatenate([prev_a, a[cont, slot][:, None]], 1)
        self.world = child_world[cont, slot]
        self.rows = np.concatenate([self.rows[upd], new_rows])
        self.roots = np.concatenate([self.roots[upd], self.roots[li]])

    def result(self, scores: np.ndarray, timings: dict, t_start: float) -> RefineResult:
        """The input rows (with in-place updates applied in step order) followed by the added ones."""
        t0 = time.perf_counter()
        out = GaussianCloud.concat([self.src] + self.new_parts) if self.new_parts else self.src.copy()  # copies
        for rows, values in self.updates:
            for name in _FIELDS:
                getattr(out, name)[rows] = getattr(values, name)
        timings.update(model=self.model_time, assemble=time.perf_counter() - t0)
        timings["total"] = time.perf_counter() - t_start
        return RefineResult(
            cloud=out, added=np.arange(len(self.src), len(out), dtype=np.int64),
            parents=np.concatenate(self.added_parents) if self.added_parents else np.zeros(0, np.int64),
            step=np.concatenate(self.added_steps) if self.added_steps else np.zeros(0, np.int64),
            scores=scores, selected=self.selected, timings=timings)


def plain_split(cloud: GaussianCloud, rows, *, steps: int = 1, seed: int = 0,
                every_step: bool = True) -> Iterator[RefineResult]:
    """Control without a model: the reference 3DGS split applied to `rows` and then, step after
    step, to all their descendants. Each Gaussian becomes two whose centres are drawn from it and
    whose scales are divided by 1.6 (other parameters copied); the first child takes the
    parent's row. Yields a `RefineResult` after every step (or only the last)."""
    t_start = time.perf_counter()
    src = cloud.numpy()
    n = len(src)
    selected = np.unique(np.asarray(rows, np.int64))
    rng = np.random.default_rng(seed)
    out = src.copy()
    active = selected.copy()
    roots = selected.copy()
    parents, step_of = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for k in range(1, steps + 1):
        sub = out.select(active)
        sigma = np.exp(np.clip(sub.scales.astype(np.float64), *EXTREME_LOG_SCALE))
        rot = sub.rotation_matrices()
        draws = [np.einsum("nij,nj->ni", rot, rng.standard_normal(sigma.shape) * sigma) for _ in range(2)]
        children = sub.copy()
        children.scales = (sub.scales - math.log(1.6)).astype(np.float32)
        children.quats = normalize_quats(sub.quats).astype(np.float32)
        second = children.copy()
        children.means = (sub.means + draws[0]).astype(np.float32)
        second.means = (sub.means + draws[1]).astype(np.float32)
        for name in ("means", "scales", "quats"):
            getattr(out, name)[active] = getattr(children, name)
        new_rows = len(out) + np.arange(len(active))
        out = GaussianCloud.concat([out, second.replace(extra={})])
        parents.append(roots.copy())
        step_of.append(np.full(len(active), k, np.int64))
        active = np.concatenate([active, new_rows])
        roots = np.concatenate([roots, roots])
        if every_step or k == steps:
            result = RefineResult(cloud=out.copy(), added=np.arange(n, len(out), dtype=np.int64),
                                  parents=np.concatenate(parents), step=np.concatenate(step_of),
                                  scores=np.zeros(n, np.float32), selected=selected,
                                  timings={"hessian": 0.0, "model": 0.0, "total": time.perf_counter() - t_start})
            suspended = time.perf_counter()
            yield result
            t_start += time.perf_counter() - suspended
