"""Training objective of the two models on stage transitions: true children are matched to
predicted slots (an exhaustive optimal assignment, C is small), then the paper's loss
1e-6·β·KL + 1.0·MSE(appearance) + 0.01·Chamfer(child centres), plus the terms it leaves implicit."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .. import quaternions
from ..conventions import SH_C0, sigmoid
from ..lineage import (APP_OPACITY, APP_SH_DC, APP_SH_REST, APPEARANCE_DIM, GEO_LOG_SCALE, GEO_POSITION, GEO_QUAT,
                       GEOMETRY_DIM)
from ..lineage import Transition
from .features import FEATURE_LOG_SCALE_RANGE, FEATURE_OPACITY_RANGE, SH_REST_LIMIT, ParentFrame, clean_nodes
from .model import LineageVAE

_PERMS: dict[int, torch.Tensor] = {}


def _permutations(c: int) -> torch.Tensor:
    if c not in _PERMS:
        _PERMS[c] = torch.tensor(list(itertools.permutations(range(c))), dtype=torch.long)
    return _PERMS[c]


def match_slots(cost: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Optimal assignment of true children to predicted slots, exhaustively over permutations
    (C is small). cost (M,S,C) slot-to-child cost, mask (M,C) which children exist (C <= S).
    Returns (M,C) the slot of each child (meaningless where mask is False)."""
    m, s, c = cost.shape
    perms = _permutations(s)[:, :c]                              # (P,C): child j -> slot perms[p,j]
    picked = cost[:, perms, torch.arange(c)[None, :]]            # (M,P,C)
    total = (picked * mask[:, None, :].to(cost.dtype)).sum(-1)
    best = total.argmin(1)
    return perms[best]


def match_slots_reference(cost: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Slow reference of `match_slots`: the Hungarian algorithm per lineage (scipy)."""
    from scipy.optimize import linear_sum_assignment  # noqa: PLC0415 - scipy is slow to import; tests only

    out = np.zeros(mask.shape, np.int64)
    for i in range(len(cost)):
        cols = np.flatnonzero(mask[i])
        if len(cols):
            rows, js = linear_sum_assignment(cost[i][:, cols].T)
            out[i, cols[rows]] = js
    return out


@dataclass
class LossWeights:
    """Loss weights: the paper's 1e-6 KL, 1.0 MSE (colour, opacity) and 0.01 Chamfer; the terms
    the paper leaves implicit (existence, matched log-scale/rotation, densification, the
    likelihood of child centres under the slots' offset distributions) share the geometry weight."""

    kl: float = 1e-6
    mse: float = 1.0
    chamfer: float = 0.01
    exist: float = 0.01
    geometry_state: float = 0.01
    appearance_exist: float = 0.01
    densify: float = 0.01
    offset_nll: float = 0.01


def _pad_children(arr: np.ndarray | torch.Tensor, slots: int) -> torch.Tensor:
    t = torch.as_tensor(arr)
    c = t.shape[1]
    if c >= slots:
        return t[:, :slots]
    pad = torch.zeros((t.shape[0], slots - c) + tuple(t.shape[2:]), dtype=t.dtype)
    return torch.cat([t, pad], 1)


def appearance_error(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Squared error (..., per child) of appearance features: the DC colour (in RGB), the SH rest
    coefficients and the opacity (activated); the true values are bounded as the model's inputs."""
    colour = ((SH_C0 * (pred[..., APP_SH_DC] - true[..., APP_SH_DC])) ** 2).sum(-1)
    sh = ((pred[..., APP_SH_REST] - true[..., APP_SH_REST].clamp(-SH_REST_LIMIT, SH_REST_LIMIT)) ** 2).sum(-1)
    opacity = (sigmoid(pred[..., APP_OPACITY]) - sigmoid(true[..., APP_OPACITY].clamp(*FEATURE_OPACITY_RANGE))) ** 2
    return colour + sh + opacity


@dataclass
class _Targets:
    """One batch's inputs and true children, cleaned and padded to the models' slots: histories,
    children's geometry and appearance, which children exist (bool and float), their count (at
    least 1) and which parents densified."""

    hg: torch.Tensor
    ha: torch.Tensor
    cg: torch.Tensor
    ca: torch.Tensor
    mask: torch.Tensor
    maskf: torch.Tensor
    n_child: torch.Tensor
    densified: torch.Tensor

    @classmethod
    def of(cls, batch: Transition, slots: int) -> _Targets:
        mask = _pad_children(batch.child_mask, slots).bool()
        maskf = mask.float()
        return cls(clean_nodes(torch.as_tensor(batch.history_geometry)),
                   clean_nodes(torch.as_tensor(batch.history_appearance)),
                   clean_nodes(_pad_children(batch.child_geometry, slots)),
                   clean_nodes(_pad_children(batch.child_appearance, slots)),
                   mask, maskf, maskf.sum().clamp(min=1.0), torch.as_tensor(batch.densified))


@dataclass
class _Matching:
    """The true children matched to the geometry slots: their centres (parent frame) and the
    predicted ones, squared distances slot-to-child (M,S,C), the true log-scales, each child's slot
    (M,C; `slot_of` clamped to the slots) and the existence target (M,S)."""

    true_rel: torch.Tensor
    pred_rel: torch.Tensor
    d2: torch.Tensor
    true_ls: torch.Tensor
    slot_of: torch.Tensor
    target_exist: torch.Tensor


def _match(pg, frame: ParentFrame, t: _Targets, slots: int) -> _Matching:
    """Match each true child to a slot by centre, log-scale and the slot's belief that it exists."""
    true_rel = frame.relative(t.cg[..., GEO_POSITION])                      # (M,C,3)
    pred_rel = pg.offsets                                                    # (M,S,3)
    d2 = ((pred_rel[:, :, None] - true_rel[:, None]) ** 2).sum(-1)          # (M,S,C)
    true_ls = t.cg[..., GEO_LOG_SCALE].clamp(*FEATURE_LOG_SCALE_RANGE)
    ls2 = ((pg.children[:, :, None, GEO_LOG_SCALE] - true_ls[:, None]) ** 2).sum(-1)
    with torch.no_grad():  # DETR-style: a slot that believes it exists is cheaper to match
        exist_cost = -F.logsigmoid(pg.exist_logit)[:, :, None]
        assign = match_slots(d2 + ls2 + exist_cost, t.mask)                  # (M,C)
    rows = torch.arange(len(t.mask))[:, None]
    target_exist = torch.zeros_like(pg.exist_logit)
    target_exist[rows.expand_as(assign)[t.mask], assign[t.mask]] = 1.0
    return _Matching(true_rel, pred_rel, d2, true_ls, assign.clamp(max=slots - 1), target_exist)


def _chamfer(pg, m: _Matching, t: _Targets) -> torch.Tensor:
    """Existence-weighted Chamfer on child centres (parent frame), both directions. The weights
    are detached: existence is learned from the matching alone (BCE), else a slot placed badly
    would be taught not to exist rather than to move."""
    prob = torch.sigmoid(pg.exist_logit).detach()
    big = torch.finfo(m.d2.dtype).max / 4
    to_pred = torch.where(t.mask[:, None], m.d2, big).min(2).values          # (M,S) slot -> nearest child
    to_true = m.d2.min(1).values                                            # (M,C) child -> nearest slot
    has_child = t.mask.any(1, keepdim=True)
    return ((to_true * t.maskf).sum() / t.n_child
            + (prob * to_pred * has_child).sum() / (prob * has_child).sum().clamp(min=1e-6))


def _geometry_terms(pg, frame: ParentFrame, m: _Matching, t: _Targets) -> tuple[torch.Tensor, torch.Tensor]:
    """(state, offset_nll): the matched slots' log-scale and rotation error (quaternion
    sign-invariant), and the likelihood of each matched child's centre under its slot's offset
    distribution (parent frame, sigma units; residuals clamped at 10 spreads so that a few far
    jumps do not rule)."""
    mg = torch.gather(pg.children, 1, m.slot_of[..., None].expand(-1, -1, GEOMETRY_DIM))
    qdot = (mg[..., GEO_QUAT] * quaternions.canonical(t.cg[..., GEO_QUAT])).sum(-1).abs().clamp(max=1.0)
    state = ((((mg[..., GEO_LOG_SCALE] - m.true_ls) ** 2).sum(-1) + 4.0 * (1.0 - qdot)) * t.maskf).sum() / t.n_child
    true_local = frame.local(t.cg[..., GEO_POSITION]).clamp(-1e3, 1e3)
    mean_local = torch.gather(pg.local_mean, 1, m.slot_of[..., None].expand(-1, -1, 3))
    spread = torch.gather(pg.local_spread, 1, m.slot_of[..., None].expand(-1, -1, 3))
    z2 = (((true_local - mean_local) / spread) ** 2).clamp(max=100.0)
    offset_nll = ((0.5 * z2 + spread.log()).sum(-1) * t.maskf).sum() / t.n_child
    return state, offset_nll


def _diagnostics(pg, pa, m: _Matching, t: _Targets) -> dict[str, torch.Tensor]:
    """Accuracies and counts that say how the models do (no gradient)."""
    with torch.no_grad():
        target = m.target_exist.bool()
        pred_exist = pg.exist_logit > 0
        p_both = 0.5 * (torch.sigmoid(pg.exist_logit) + torch.sigmoid(pa.exist_logit))
        matched_pos = ((torch.gather(m.pred_rel, 1, m.slot_of[..., None].expand(-1, -1, 3)) - m.true_rel) ** 2).sum(-1)
        return {"densify_accuracy": ((pg.densify_logit > 0) == t.densified).float().mean(),
                "exist_accuracy": (pred_exist == target).float().mean(),
                "position_rmse": ((matched_pos * t.maskf).sum() / t.n_child).sqrt(),
                "count_error": (pred_exist.float().sum(1) - t.maskf.sum(1)).abs().mean(),
                "expected_count_bias": (torch.sigmoid(pg.exist_logit).sum(1) - t.maskf.sum(1)).mean(),
                "exist_accuracy_appearance": ((pa.exist_logit > 0) == target).float().mean(),
                "exist_accuracy_combined": ((p_both > 0.5) == target).float().mean(),
                "expected_count_bias_combined": (p_both.sum(1) - t.maskf.sum(1)).mean()}


def transition_loss(geometry: LineageVAE, appearance: LineageVAE, batch: Transition, *, beta: float = 1.0,
                    weights: LossWeights | None = None, generator: torch.Generator | None = None,
                    sample: bool = True) -> dict[str, torch.Tensor]:
    """Both models' losses on one batch of transitions. True children are matched to the
    geometry model's slots (centres and log-scales in the parent frame); the appearance model
    is supervised on the same slots, so that slot k of both models describes one Gaussian."""
    slots = geometry.config.slots
    t = _Targets.of(batch, slots)
    pg, mu_g, lv_g, z_g = geometry(t.hg, t.densified, sample=sample, generator=generator)
    densify = F.binary_cross_entropy_with_logits(pg.densify_logit, t.densified.float())
    frame = ParentFrame.of(geometry._prepare(t.hg)[:, -1])
    m = _match(pg, frame, t, slots)
    exist_g = F.binary_cross_entropy_with_logits(pg.exist_logit, m.target_exist)
    chamfer = _chamfer(pg, m, t)
    state, offset_nll = _geometry_terms(pg, frame, m, t)
    kl_g = geometry.kl(mu_g, lv_g, z_g).mean()

    pa, mu_a, lv_a, z_a = appearance(t.ha, t.densified, sample=sample, generator=generator)
    ma = torch.gather(pa.children, 1, m.slot_of[..., None].expand(-1, -1, APPEARANCE_DIM))
    mse = (appearance_error(ma, t.ca) * t.maskf).sum() / t.n_child
    exist_a = F.binary_cross_entropy_with_logits(pa.exist_logit, m.target_exist)
    kl_a = appearance.kl(mu_a, lv_a, z_a).mean()

    w = weights or LossWeights()
    total = (w.kl * beta * (kl_g + kl_a) + w.mse * mse + w.chamfer * chamfer + w.exist * exist_g
             + w.geometry_state * state + w.appearance_exist * exist_a + w.densify * densify
             + w.offset_nll * offset_nll)
    seen = _diagnostics(pg, pa, m, t)
    return {"total": total, "kl_geometry": kl_g, "kl_appearance": kl_a, "mse": mse, "chamfer": chamfer,
            "densify": densify, "densify_accuracy": seen.pop("densify_accuracy"), "offset_nll": offset_nll,
            "exist": exist_g, "state": state, **seen}
