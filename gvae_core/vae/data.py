"""Training data of the models: stage transitions (`gvae_core.lineage.Transition`: lineages and
their children one stage later), from progressive training runs or from a synthetic generator
that densifies like 3DGS."""

from __future__ import annotations

from pathlib import Path
from collections.abc import Sequence

import numpy as np

from .. import quaternions
from ..densify import split_children
from ..lineage import (APP_EXIST, APP_OPACITY, APP_SH_DC, APP_SH_REST, APPEARANCE_DIM, GEO_EXIST, GEO_LOG_SCALE,
                       GEO_POSITION, GEO_QUAT, GEOMETRY_DIM, Lineage, Transition)


def synthetic_transitions(n: int = 512, stages: int = 3, *, seed: int = 0,
                          split_prob: float = 0.35, clone_prob: float = 0.15) -> list[Transition]:
    """Synthetic lineages that densify like 3DGS: per stage each Gaussian survives with jitter,
    splits into two children (the 3DGS split rule, `densify.split_children`) or clones itself
    (the parent stays, a copy appears next to it). Features as in DESIGN.md, normalised frame."""
    rng = np.random.default_rng(seed)
    geom = np.zeros((n, GEOMETRY_DIM), np.float32)
    geom[:, GEO_POSITION] = rng.uniform(-1, 1, (n, 3))
    q = rng.normal(size=(n, 4))
    geom[:, GEO_QUAT] = q / np.linalg.norm(q, axis=1, keepdims=True)
    geom[:, GEO_LOG_SCALE] = np.log(0.06) + rng.normal(0, 0.3, (n, 3))
    geom[:, GEO_EXIST] = 1
    app = np.zeros((n, APPEARANCE_DIM), np.float32)
    app[:, APP_SH_REST] = rng.normal(0, 0.05, (n, 45))
    app[:, APP_SH_DC] = rng.normal(0, 1.0, (n, 3))
    app[:, APP_OPACITY] = rng.normal(1.0, 1.0, n)
    app[:, APP_EXIST] = 1
    hist_g, hist_a = geom[:, None].copy(), app[:, None].copy()
    out = []
    for stage in range(1, stages):
        m = len(hist_g)
        last_g, last_a = hist_g[:, -1], hist_a[:, -1]
        u = rng.uniform(size=m)
        split, clone = u < split_prob, (u >= split_prob) & (u < split_prob + clone_prob)
        cg = np.zeros((m, 2, GEOMETRY_DIM), np.float32)
        ca = np.zeros((m, 2, APPEARANCE_DIM), np.float32)
        mask = np.zeros((m, 2), bool)
        rot = quaternions.to_rotmat(last_g[:, GEO_QUAT].astype(np.float64))
        sig = np.exp(last_g[:, GEO_LOG_SCALE].astype(np.float64))
        last_pos, last_ls = last_g[:, GEO_POSITION], last_g[:, GEO_LOG_SCALE]
        for c in range(2):
            cg[:, c] = last_g
            ca[:, c] = last_a
            split_pos, split_ls = split_children(last_pos, last_ls, rot, rng.normal(size=(m, 3)))
            off = split_pos - last_pos
            jitter = np.einsum("mij,mj->mi", rot, rng.normal(0, 0.05, (m, 3)) * sig)
            cg[:, c, GEO_POSITION] += np.where(split[:, None], off, jitter if c == 0 else 0.5 * off)
            cg[:, c, GEO_LOG_SCALE] = np.where(split[:, None], split_ls, last_ls) + rng.normal(0, 0.02, (m, 3))
            ca[:, c, APP_SH_DC] += rng.normal(0, 0.05, (m, 3))
            ca[:, c, APP_OPACITY] += np.where(split, -0.3, 0.1)
        mask[:, 0] = True
        mask[:, 1] = split | clone
        out.append(Transition(hist_g, hist_a, cg, ca, mask, stage, "synthetic", split | clone))
        # Next stage's lineages: every child, its history the parent's (exist = 0 for new ones).
        parent = np.concatenate([np.arange(m), np.flatnonzero(mask[:, 1])])
        slot = np.concatenate([np.zeros(m, int), np.ones(int(mask[:, 1].sum()), int)])
        new_g, new_a = hist_g[parent].copy(), hist_a[parent].copy()
        new_g[slot == 1, :, GEO_EXIST] = 0
        new_a[slot == 1, :, APP_EXIST] = 0
        hist_g = np.concatenate([new_g, cg[parent, slot][:, None]], 1)
        hist_a = np.concatenate([new_a, ca[parent, slot][:, None]], 1)
    return out


def lineage_transitions(lineage: Lineage, source: str = "", max_children: int = 4) -> list[Transition]:
    """Every stage transition of a `gvae_core.lineage.Lineage` (children beyond `max_children`
    per parent are dropped, as `Lineage.transitions` reports)."""
    return [lineage.transitions(s, max_children, source) for s in range(1, lineage.n_stages)]




def load_runs(runs: Sequence[Path], slots: int = 4) -> list[Transition]:
    """The transitions of training runs (folders holding the lineage.npz that `gvae train` writes,
    or .npz paths), each tagged with its run."""
    out = []
    for run in map(Path, runs):
        path = run / "lineage.npz" if run.is_dir() else run
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no lineage file (expected RUN_DIR/lineage.npz from `gvae train`)")
        lin = Lineage.load(path)
        if lin.n_stages < 2:
            raise ValueError(f"{path}: needs at least two stages to learn transitions, has {lin.n_stages}")
        out += lineage_transitions(lin, source=str(run), max_children=slots)
    return out
