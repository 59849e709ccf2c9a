"""Fitting both models on stage transitions (coarse stages first, cyclic KL annealing), and
measuring them against the trivial yardstick of copying the parent."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from collections.abc import Callable, Sequence

import numpy as np
import torch

from ..lineage import APP_OPACITY, APP_SH_REST, GEO_POSITION
from ..lineage import Transition
from .features import FEATURE_OPACITY_RANGE, SH_REST_LIMIT, ParentFrame, clean_nodes
from .losses import LossWeights, appearance_error, transition_loss
from .model import GaussianVAE
from .prior import cyclic_beta


@dataclass
class FitConfig:
    """Training of both models (coarse stages first, cyclic KL annealing)."""

    steps: int = 3000
    batch: int = 256
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    anneal_alpha: float = 0.01     # beta(t) = min(alpha * (t mod R), 1)
    anneal_period: int = 500
    coarse_fraction: float = 0.3   # first part of training sees only the coarsest transitions
    weights: LossWeights = field(default_factory=LossWeights)


@dataclass
class FitResult:
    model: GaussianVAE
    history: list[dict[str, float]]
    seconds: float


def fit(transitions: Sequence[Transition], config: FitConfig | None = None, *,
        model: GaussianVAE | None = None, progress: Callable[[int, int, dict], None] | None = None) -> FitResult:
    """Train both models on stage transitions by predicting each lineage's masked last stage.
    Coarse-to-fine: the first `coarse_fraction` of steps draws only from the lowest stage, then
    every transition is drawn from in proportion to its size."""
    transitions = [t for t in transitions if len(t)]
    if not transitions:
        raise ValueError("fit: no transitions to train on (every lineage set is empty)")
    start = time.perf_counter()
    config = config or FitConfig()
    model = model or GaussianVAE.create(seed=config.seed)
    params = list(model.geometry.parameters()) + list(model.appearance.parameters())
    opt = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    # One-cycle schedule; too short a run for its warm-up phase keeps the learning rate constant.
    sched = (torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps, pct_start=0.1)
             if config.steps >= 20 else None)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    sizes = np.array([len(t) for t in transitions], float)
    coarsest = min(t.stage for t in transitions)
    coarse = np.array([t.stage == coarsest for t in transitions])
    model.geometry.train()
    model.appearance.train()
    history = []
    for step in range(config.steps):
        p = sizes * (coarse if step < config.coarse_fraction * config.steps else 1.0)
        k = rng.choice(len(transitions), p=p / p.sum())
        tr = transitions[k]
        idx = rng.choice(len(tr), size=min(config.batch, len(tr)), replace=False)
        beta = cyclic_beta(step, config.anneal_alpha, config.anneal_period)
        losses = transition_loss(model.geometry, model.appearance, tr.subset(idx), beta=beta,
                                 weights=config.weights, generator=gen)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        for part in (model.geometry, model.appearance):  # apart: one model's large gradients must
            torch.nn.utils.clip_grad_norm_(part.parameters(), 1.0)  # not shrink the other's steps
        opt.step()
        if sched is not None:
            sched.step()
        record = {k: float(v.detach()) for k, v in losses.items()}
        record["beta"] = beta
        history.append(record)
        if progress is not None:
            progress(step + 1, config.steps, record)
    model.geometry.eval()
    model.appearance.eval()
    return FitResult(model, history, time.perf_counter() - start)


@torch.no_grad()
def evaluate(model: GaussianVAE, transitions: Sequence[Transition], *, seed: int = 0,
             batch: int = 4096) -> dict[str, float]:
    """Reconstruction error on transitions (posterior means, no sampling), averaged by lineage:
    matched child-centre RMSE (parent sizes), existence accuracy, child-count error, appearance MSE,
    Chamfer (`copy_parent_baseline` is the yardstick)."""
    totals: dict[str, float] = {}
    count = 0
    for tr in transitions:
        for i in range(0, len(tr), batch):
            sub = tr.subset(np.arange(i, min(i + batch, len(tr))))
            losses = transition_loss(model.geometry, model.appearance, sub, sample=False)
            for k, v in losses.items():
                totals[k] = totals.get(k, 0.0) + float(v) * len(sub)
            count += len(sub)
    return {k: v / max(count, 1) for k, v in totals.items()}


def copy_parent_baseline(transitions: Sequence[Transition]) -> dict[str, float]:
    """The yardstick for `evaluate`: predict one child equal to the parent. Child-centre RMSE
    (parent sizes; every true child against the parent), appearance MSE (same terms as the
    loss), child-count error."""
    sq_pos, mse, count_err, n_child, n_lin = 0.0, 0.0, 0.0, 0, 0
    for tr in transitions:
        hg = clean_nodes(torch.as_tensor(tr.history_geometry))
        ha = clean_nodes(torch.as_tensor(tr.history_appearance))
        cg = clean_nodes(torch.as_tensor(tr.child_geometry))
        ca = clean_nodes(torch.as_tensor(tr.child_appearance))
        mask = torch.as_tensor(tr.child_mask).float()
        frame = ParentFrame.of(hg[:, -1])
        d2 = (frame.relative(cg[..., GEO_POSITION]) ** 2).sum(-1)
        last = ha[:, -1:].clone()  # the parent as its only child, bounded like a true child
        last[..., APP_SH_REST] = last[..., APP_SH_REST].clamp(-SH_REST_LIMIT, SH_REST_LIMIT)
        last[..., APP_OPACITY] = last[..., APP_OPACITY].clamp(*FEATURE_OPACITY_RANGE)
        sq_pos += float((d2 * mask).sum())
        mse += float((appearance_error(last, ca) * mask).sum())
        count_err += float((mask.sum(1) - 1.0).abs().sum())
        n_child += int(mask.sum())
        n_lin += len(tr)
    return {"position_rmse": math.sqrt(sq_pos / max(n_child, 1)), "mse": mse / max(n_child, 1),
            "count_error": count_err / max(n_lin, 1)}
