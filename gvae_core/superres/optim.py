"""Adam that moves only the rows a step saw: the fit draws one patch of one image a step, so on a
large capture most Gaussians get no gradient in most steps. Plain Adam still moves every row that
ever had one, by its decaying momentum (a row seen once travels about 30 learning-rate steps after
it), which on a large capture made the fit end far below where it started. Here a row's moments
and value change only in steps where its gradient is non-zero (the "selective" or "visible" Adam of
the 3DGS literature); the bias correction counts the optimiser's steps, as Adam's does. On a small
object, where a patch sees nearly every Gaussian, it is Adam.

It keeps torch's optimiser interface (`param_groups`, `state`, `add_param_group`, `step`,
`zero_grad`) without deriving from `torch.optim.Optimizer`, whose constructor imports torch's
compiler on first use (several seconds of a refine that otherwise needs none of it)."""

from __future__ import annotations

import torch

__all__ = ["VisibleAdam"]


class VisibleAdam:
    """Adam (no weight decay, no amsgrad) over row-indexed parameters, updating only the rows
    (first index) with a non-zero gradient. State keys as torch's Adam: `step`, `exp_avg`,
    `exp_avg_sq`; parameters as torch's optimisers take them (tensors, or a list of groups: dicts
    with "params" and optionally "lr")."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15):
        self.defaults = {"lr": lr, "betas": betas, "eps": eps}
        self.param_groups: list[dict] = []
        self.state: dict = {}
        params = list(params)
        for group in params if params and isinstance(params[0], dict) else [{"params": params}]:
            self.add_param_group(group)

    def add_param_group(self, group: dict) -> None:
        self.param_groups.append({**self.defaults, **group, "params": list(group["params"])})

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is not None:
                    if set_to_none:
                        p.grad = None
                    else:
                        p.grad.zero_()

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                g = p.grad
                state = self.state.setdefault(p, {})
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float64)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                t = float(state["step"])
                seen = g.reshape(len(g), -1).ne(0).any(1) if g.dim() else torch.ones((), dtype=torch.bool)
                rows = torch.nonzero(seen).reshape(-1) if g.dim() else None
                if rows is not None and len(rows) == len(g):
                    rows = None  # every row: no gather
                m, v = state["exp_avg"], state["exp_avg_sq"]
                gr = g if rows is None else g[rows]
                mr = (m if rows is None else m[rows]).mul_(b1).add_(gr, alpha=1 - b1)
                vr = (v if rows is None else v[rows]).mul_(b2).addcmul_(gr, gr, value=1 - b2)
                update = (mr / (1 - b1 ** t)) / ((vr / (1 - b2 ** t)).sqrt_().add_(group["eps"]))
                if rows is None:
                    p.sub_(update, alpha=group["lr"])
                else:
                    m[rows], v[rows] = mr, vr
                    p.index_add_(0, rows, update, alpha=-group["lr"])
        return None
