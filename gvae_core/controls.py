"""Controls of the experiment: what refinement is compared with at the same cost.

`plain_split` is the reference 3DGS split without any model, applied to chosen Gaussians.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from . import quaternions
from .cloud import GaussianCloud
from .densify import split_children
from .refinement import RefineResult


def plain_split(cloud: GaussianCloud, rows, *, steps: int = 1, seed: int = 0,
                every_step: bool = True) -> Iterator[RefineResult]:
    """Control without a model: the reference 3DGS split applied to `rows` and then, step after
    step, to all their descendants: each Gaussian becomes two (`densify.split_children`, other
    parameters copied); the first child takes the parent's row. Yields a `RefineResult` after
    every step (or only the last)."""
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
        means, log_scales = sub.means.astype(np.float64), sub.scales.astype(np.float64)
        rot = sub.rotation_matrices().astype(np.float64)
        children = sub.copy()
        children.quats = quaternions.normalize(sub.quats).astype(np.float32)
        second = children.copy()
        for child in (children, second):
            centres, scales = split_children(means, log_scales, rot, rng.standard_normal(means.shape))
            child.means, child.scales = centres.astype(np.float32), scales.astype(np.float32)
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
