"""Adaptive density control of 3D Gaussian Splatting, apart from the trainer that uses it.

- `split_children`: the reference split rule (children drawn from the parent, scale / 1.6), the one
  definition used by the trainer, by the plain-split control and by the synthetic lineages;
- `GaussianModel`: trainable Gaussians with one Adam group per parameter, whose optimiser state
  every structural edit (append, keep, opacity reset) keeps aligned with the rows, plus lineage
  ids and the view-space gradient statistics densification decides on;
- `DensifyStrategy`: the reference's decisions (clone small Gaussians with a large view-space
  positional gradient, split large ones, prune transparent and oversized ones).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import quaternions
from .cloud import GaussianCloud
from .conventions import activate_opacities, activate_scales, opacity_logit

#: Parameter groups of the optimiser, in this order.
PARAMS = ("means", "sh_dc", "sh_rest", "opacities", "scales", "quats")


def split_children(means, log_scales, rotmats, normals, n_children: int = 2):
    """The 3DGS split of Gaussians into `n_children` each: a child's centre is drawn from the
    parent Gaussian, its log-scale is the parent's minus log(0.8 n_children) (scale / 1.6 for two).
    `normals`: standard-normal draws (..., 3), one per child, from the caller's generator (numpy or
    torch, like the other arrays); `rotmats` (..., 3, 3) the parents' rotations. Returns the
    children's (means, log-scales)."""
    offsets = (rotmats @ (normals * activate_scales(log_scales))[..., None])[..., 0]
    return means + offsets, log_scales - math.log(0.8 * n_children)


def g_scale(width: int, height: int, device=None) -> torch.Tensor:
    """Pixel-to-NDC factor of screen-space gradients: d(ndc)/d(pixel) = 2/size, so a gradient
    with respect to pixels times size/2 is the gradient with respect to NDC."""
    return torch.tensor([0.5 * width, 0.5 * height], device=device)


def adam(groups: list[dict]) -> torch.optim.Adam:
    """The reference's Adam (eps 1e-15) over `groups`, torch's fused kernel where this torch has it
    for the groups' device (on the CPU 6x faster than the loop over parameters: at 100k Gaussians of
    SH degree 3, 8 ms a step against 48, one thread); the same update either way."""
    try:
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
    except (RuntimeError, TypeError, ValueError):  # an older torch, or a device without the fused kernel
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


class GaussianModel:
    """Trainable Gaussians: leaf tensors per parameter, one Adam group each (state extended and
    pruned with the Gaussians), lineage ids and stage anchors, densification statistics.

    `lrs`: learning rate per parameter group; `extent`: the scene extent the strategy's world-size
    thresholds are relative to; `next_id`: the first id a new Gaussian gets; `device`: the torch
    device of every tensor (random draws stay on the CPU generator, so a run is the same on any)."""

    def __init__(self, cloud: GaussianCloud, ids, parents, lrs: dict[str, float], extent: float, next_id: int,
                 device=None):
        self.device = torch.device(device or "cpu")
        c = cloud.to_torch(device=self.device, dtype=torch.float32)
        self.params = {name: getattr(c, name).detach().clone().requires_grad_(True) for name in PARAMS}
        self.ids = torch.as_tensor(np.asarray(ids), dtype=torch.int64, device=self.device).clone()
        self.parents = torch.as_tensor(np.asarray(parents), dtype=torch.int64, device=self.device).clone()
        self.next_id = int(next_id)
        self.extent = float(extent)
        self.optimizer = adam([{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in PARAMS])
        self.reset_stats()

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def cloud(self) -> GaussianCloud:
        """The Gaussians as a torch cloud sharing the trainable tensors."""
        return GaussianCloud(**self.params)

    def load_params(self, values: dict[str, torch.Tensor]) -> None:
        """Set every parameter to `values` (same shapes: an earlier state of the same rows)."""
        with torch.no_grad():
            for name in PARAMS:
                self.params[name].copy_(values[name])

    def optimizer_state(self) -> dict[str, np.ndarray]:
        """Adam's moments and step count of every parameter (numpy, keys "<name>.<what>"): what the
        next stage starts from when it carries them (`load_optimizer_state`)."""
        out = {}
        for name in PARAMS:
            for key, value in self.optimizer.state.get(self.params[name], {}).items():
                out[f"{name}.{key}"] = value.detach().cpu().numpy().copy()
        return out

    def load_optimizer_state(self, state: dict[str, np.ndarray]) -> bool:
        """Adam's state from `optimizer_state` of the same rows; nothing changes (False) when it is
        empty or does not fit the parameters."""
        fits = bool(state) and all(
            state.get(f"{n}.{k}") is not None and state[f"{n}.{k}"].shape == tuple(self.params[n].shape)
            for n in PARAMS for k in ("exp_avg", "exp_avg_sq"))
        if not fits:
            return False
        for name in PARAMS:
            param = self.params[name]
            self.optimizer.state[param] = {
                key.split(".", 1)[1]: torch.as_tensor(value).to(param.device).clone()
                for key, value in state.items() if key.split(".", 1)[0] == name}
        return True

    def snapshot(self) -> GaussianCloud:
        """A detached numpy copy with int64 extras `gvae_id` and `gvae_parent`."""
        c = GaussianCloud(**{n: p.detach().cpu() for n, p in self.params.items()}).numpy().copy()
        return c.replace(extra={"gvae_id": self.ids.cpu().numpy().copy(),
                                "gvae_parent": self.parents.cpu().numpy().copy()})

    def reset_stats(self) -> None:
        n = len(self)
        self.grad_accum = torch.zeros(n, device=self.device)
        self.grad_count = torch.zeros(n, device=self.device)
        self.max_radii = torch.zeros(n, device=self.device)

    def set_lr(self, name: str, lr: float) -> None:
        self.optimizer.param_groups[PARAMS.index(name)]["lr"] = lr

    def add_stats(self, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor,
                  width: int, height: int) -> None:
        """Accumulate the view-space positional gradient norm in NDC units (pixel gradient times
        half the image size, as the reference's 0.0002 threshold expects)."""
        g = means2d_grad.detach()[:, :2] * g_scale(width, height, self.device)
        norm = g.norm(dim=-1)
        self.grad_accum += torch.where(visible, norm, torch.zeros_like(norm))
        self.grad_count += visible.float()
        self.max_radii = torch.where(visible, torch.maximum(self.max_radii, radii.float()), self.max_radii)

    # ------------------------------------------------------------ structure edits
    def _edit(self, index: torch.Tensor, new: dict[str, torch.Tensor] | None) -> None:
        """Keep rows `index` (long) of every parameter and its Adam moments, then append `new`
        parameter rows with zero moments."""
        for gi, name in enumerate(PARAMS):
            group = self.optimizer.param_groups[gi]
            old = group["params"][0]
            kept = old.detach()[index]
            extra = new[name].detach() if new is not None else kept[:0]
            param = torch.cat([kept, extra], 0).requires_grad_(True)
            state = self.optimizer.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    s = state[key][index]
                    state[key] = torch.cat([s, torch.zeros((len(extra),) + tuple(s.shape[1:]), dtype=s.dtype,
                                                         device=s.device)], 0)
                self.optimizer.state[param] = state
            group["params"][0] = param
            self.params[name] = param

    def append(self, new: dict[str, torch.Tensor], source_rows: torch.Tensor) -> None:
        """Add Gaussians born from rows `source_rows`: fresh ids, the source's stage anchor."""
        n_new = len(source_rows)
        new_ids = torch.arange(self.next_id, self.next_id + n_new, dtype=torch.int64, device=self.device)
        self.next_id += n_new
        parents = self.parents[source_rows]
        self._edit(torch.arange(len(self)), new)
        self.ids = torch.cat([self.ids, new_ids])
        self.parents = torch.cat([self.parents, parents])
        z = torch.zeros(n_new, device=self.device)
        self.grad_accum, self.grad_count = torch.cat([self.grad_accum, z]), torch.cat([self.grad_count, z])
        self.max_radii = torch.cat([self.max_radii, z])

    def keep(self, mask: torch.Tensor) -> None:
        index = torch.nonzero(mask).flatten()
        self._edit(index, None)
        self.ids, self.parents = self.ids[index], self.parents[index]
        self.grad_accum, self.grad_count = self.grad_accum[index], self.grad_count[index]
        self.max_radii = self.max_radii[index]

    def clone(self, mask: torch.Tensor) -> int:
        """Copy the selected Gaussians (the reference's clone: same parameters)."""
        rows = torch.nonzero(mask).flatten()
        if len(rows):
            self.append({n: p.detach()[rows] for n, p in self.params.items()}, rows)
        return len(rows)

    def split(self, mask: torch.Tensor, generator: torch.Generator, n_children: int = 2) -> int:
        """Replace each selected Gaussian by `n_children` (`split_children`)."""
        rows = torch.nonzero(mask).flatten()
        if not len(rows):
            return 0
        p = {n: t.detach() for n, t in self.params.items()}
        src = rows.repeat(n_children)
        new = {n: t[src] for n, t in p.items()}
        normals = torch.randn(new["scales"].shape, generator=generator).to(self.device)
        rot = quaternions.to_rotmat(quaternions.normalize(new["quats"]))
        new["means"], new["scales"] = split_children(new["means"], new["scales"], rot, normals, n_children)
        self.append(new, src)
        keep = torch.ones(len(self), dtype=torch.bool, device=self.device)
        keep[rows] = False
        self.keep(keep)
        return len(rows)

    def reset_opacity(self, value: float) -> None:
        """Opacities above `value` come down to it; their Adam moments restart."""
        gi = PARAMS.index("opacities")
        old = self.params["opacities"]
        new = torch.minimum(old.detach(), torch.tensor(opacity_logit(value), device=old.device)).requires_grad_(True)
        state = self.optimizer.state.pop(old, None)
        if state:
            state["exp_avg"] = torch.zeros_like(state["exp_avg"])
            state["exp_avg_sq"] = torch.zeros_like(state["exp_avg_sq"])
            self.optimizer.state[new] = state
        self.optimizer.param_groups[gi]["params"][0] = new
        self.params["opacities"] = new


@dataclass
class DensifyStrategy:
    """The reference 3DGS adaptive density control, thresholds in the reference's units: mean
    view-space gradient (NDC) `grad_threshold`; Gaussians larger than `percent_dense` x extent are
    split, smaller ones cloned; opacity below `prune_opacity` is pruned, and (after the first
    opacity reset) so is a world size above `max_world_size` x extent or, when set, a screen
    radius above `max_screen_fraction` x image height. `max_gaussians` caps the count (the highest
    gradients win)."""

    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_world_size: float = 0.1
    max_screen_fraction: float | None = None
    max_gaussians: int | None = 50_000

    def densify_and_prune(self, model: GaussianModel, generator: torch.Generator, *, prune_large: bool,
                          image_height: int) -> dict[str, int]:
        """One round of density control on `model`; returns what it did."""
        grads = model.grad_accum / model.grad_count.clamp(min=1.0)
        scale_max = activate_scales(model.params["scales"].detach()).max(1).values
        high = grads >= self.grad_threshold
        large = scale_max > self.percent_dense * model.extent
        clone_mask, split_mask = high & ~large, high & large
        if self.max_gaussians is not None:
            room = max(self.max_gaussians - len(model), 0)
            cand = clone_mask | split_mask
            if int(cand.sum()) > room:  # keep the highest gradients that fit
                score = torch.where(cand, grads, torch.full_like(grads, -1.0))
                chosen = torch.zeros_like(cand)
                if room:
                    chosen[torch.topk(score, room).indices] = True
                clone_mask, split_mask = clone_mask & chosen, split_mask & chosen
        n_clone = model.clone(clone_mask)
        pad = torch.zeros(len(model) - len(split_mask), dtype=torch.bool, device=split_mask.device)
        n_split = model.split(torch.cat([split_mask, pad]), generator)
        prune = activate_opacities(model.params["opacities"].detach()) < self.prune_opacity
        if prune_large:
            scale_max = activate_scales(model.params["scales"].detach()).max(1).values
            prune |= scale_max > self.max_world_size * model.extent
            if self.max_screen_fraction is not None:
                prune |= model.max_radii > self.max_screen_fraction * image_height
        if bool(prune.all()):  # never prune everything away
            prune[torch.argmax(model.params["opacities"].detach())] = False
        model.keep(~prune)
        model.reset_stats()
        return {"cloned": n_clone, "split": n_split, "pruned": int(prune.sum())}
