"""Controls of the experiment: what refinement is compared with at the same cost, the same
number of Gaussians out.

Each control takes the Gaussian counts a refinement added after each step (`targets`, cumulative)
and adds exactly as many, so that every comparison is at equal output count:
- `split_control`: the reference 3DGS split (`densify.split_children`) of as many Gaussians as
  the count needs: first of the ones already split (their lineages, as refinement extends its
  own), in random order, then of the untouched ones with the highest scores;
- `duplicate_control`: the same choice, but each chosen Gaussian gets an exact copy of itself and
  both share its opacity (1 - (1 - o')² = o), so the render hardly changes: what the count alone
  buys;
- `thin_added`: a refinement's added Gaussians thinned at random to a count (random selection
  with the model is refinement with random scores, oversupplied, then thinned).
At the same count (none added), for the detail refine: `extrapolation_control` (each Gaussian
continues its last lineage change) and `octave_knob` (one global scale change per octave), each
with one factor chosen on the training scenes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from . import quaternions
from .cloud import GaussianCloud
from .conventions import activate_opacities
from .densify import split_children
from .detail.features import lineage_nodes
from .octaves import with_octaves
from .refinement import RefineResult

#: An operation on the chosen Gaussians: (chosen (numpy cloud), generator) -> (their new values,
#: the Gaussians to append, one per chosen row).
Operation = Callable[[GaussianCloud, np.random.Generator], tuple[GaussianCloud, GaussianCloud]]


def _split(chosen: GaussianCloud, rng: np.random.Generator) -> tuple[GaussianCloud, GaussianCloud]:
    means, log_scales = chosen.means.astype(np.float64), chosen.scales.astype(np.float64)
    rot = chosen.rotation_matrices().astype(np.float64)
    out = []
    for _ in range(2):
        centres, scales = split_children(means, log_scales, rot, rng.standard_normal(means.shape))
        out.append(chosen.replace(means=centres.astype(np.float32), scales=scales.astype(np.float32),
                                  quats=quaternions.normalize(chosen.quats).astype(np.float32)))
    return out[0], out[1].replace(extra={})


def _duplicate(chosen: GaussianCloud, rng: np.random.Generator) -> tuple[GaussianCloud, GaussianCloud]:
    shared = 1.0 - np.sqrt(1.0 - activate_opacities(chosen.opacities.astype(np.float64)))
    shared = np.clip(shared, 1e-12, 1.0 - 1e-12)
    logits = np.log(shared / (1.0 - shared)).astype(np.float32)
    both = chosen.replace(opacities=logits)
    return both, both.replace(extra={})


def _grow(cloud: GaussianCloud, scores, targets: Sequence[int], seed: int, operate: Operation,
          every_step: bool) -> Iterator[RefineResult]:
    t_start = time.perf_counter()
    src = cloud.numpy()
    n = len(src)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(scores) != n:
        raise ValueError(f"control: {len(scores)} scores for {n} Gaussians")
    order = np.argsort(-scores, kind="stable")  # untouched Gaussians, best score first
    rng = np.random.default_rng(seed)
    out = src.copy()
    active = np.zeros(0, np.int64)       # rows of `out` already operated on, or born from one
    root = np.arange(n, dtype=np.int64)  # each row's ancestor among the input rows
    fresh_used = 0
    parents, steps, done = [], [], 0
    for k, target in enumerate(targets, 1):
        need = max(int(target) - done, 0)
        again = rng.permutation(active)[:need]
        fresh = order[fresh_used:fresh_used + need - len(again)]
        fresh_used += len(fresh)
        chosen = np.concatenate([again, fresh]).astype(np.int64)
        updated, children = operate(out.select(chosen), rng)
        for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
            getattr(out, name)[chosen] = getattr(updated, name)
        new_rows = len(out) + np.arange(len(chosen))
        out = out.append_children(children, chosen)
        root = np.concatenate([root, root[chosen]])
        active = np.concatenate([active, fresh, new_rows])
        parents.append(root[chosen])
        steps.append(np.full(len(chosen), k, np.int64))
        done += len(chosen)
        if every_step or k == len(targets):
            result = RefineResult(cloud=out.copy(), added=np.arange(n, len(out), dtype=np.int64),
                                  parents=np.concatenate(parents), step=np.concatenate(steps),
                                  scores=scores.astype(np.float32), selected=np.unique(np.concatenate(parents)),
                                  timings={"hessian": 0.0, "model": 0.0, "total": time.perf_counter() - t_start})
            suspended = time.perf_counter()
            yield result
            t_start += time.perf_counter() - suspended


def split_control(cloud: GaussianCloud, scores, targets: Sequence[int], *, seed: int = 0,
                  every_step: bool = True) -> Iterator[RefineResult]:
    """The plain 3DGS split at equal output count: after step k exactly `targets[k-1]` Gaussians
    have been added (see the module docstring for which ones split). Yields a `RefineResult`
    after every step (or only the last)."""
    return _grow(cloud, scores, targets, seed, _split, every_step)


def duplicate_control(cloud: GaussianCloud, scores, targets: Sequence[int], *, seed: int = 0,
                      every_step: bool = True) -> Iterator[RefineResult]:
    """Duplicate-in-place at equal output count: the chosen Gaussians get an exact copy, the
    pair sharing the opacity so that the render hardly changes."""
    return _grow(cloud, scores, targets, seed, _duplicate, every_step)


def thin_added(result: RefineResult, target: int, *, seed: int = 0) -> RefineResult:
    """`result` with its added Gaussians thinned at random to `target` (all of them when it
    added fewer); the input rows and their order are kept."""
    n = result.n_input
    rng = np.random.default_rng(seed)
    keep_added = np.sort(rng.permutation(len(result.added))[:max(int(target), 0)])
    keep = np.concatenate([np.arange(n), n + keep_added])
    return RefineResult(cloud=result.cloud.select(keep), added=np.arange(n, len(keep), dtype=np.int64),
                        parents=result.parents[keep_added], step=result.step[keep_added], scores=result.scores,
                        selected=result.selected, timings=result.timings)


def extrapolation_control(cloud: GaussianCloud, lineage, factor: float, limit: float = 1.0) -> GaussianCloud:
    """Linear lineage extrapolation, the simplest reading of refinement's own idea: each Gaussian
    continues `factor` times its last stage-to-stage change of log-scales and opacity logit, per
    octave of training resolution between those stages, as changes per octave above its training
    rate (`gvae_core.octaves`: the training-resolution picture is kept). `factor` is chosen on the
    training scenes; a Gaussian without history (or no lineage) does not change."""
    scales, opac, _, octaves = lineage_nodes(cloud, lineage)
    change = {"scales": (factor * (scales[:, 2] - scales[:, 1]) / octaves[1]).astype(np.float32),
              "opacities": (factor * (opac[:, 2] - opac[:, 1]) / octaves[1]).astype(np.float32)}
    return with_octaves(cloud.numpy(), change, limit)


def octave_knob(cloud: GaussianCloud, factor: float, limit: float = 1.0) -> GaussianCloud:
    """One global knob at the same cost as a refinement: every Gaussian's scale times `factor` per
    octave above its training rate (at the training resolution the cloud is as it was)."""
    n = len(cloud)
    return with_octaves(cloud.numpy(), {"scales": np.full((n, 3), math.log(factor), np.float32)}, limit)
