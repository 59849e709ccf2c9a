"""`GaussianModel`: the Gaussians being trained, as leaf tensors with one Adam group per parameter,
and the structural edits densification makes (append, keep, clone, split, opacity reset), each
keeping Adam's moments aligned with the rows, plus the lineage ids every Gaussian carries."""

from __future__ import annotations

import numpy as np
import torch

from .. import quaternions
from ..cloud import GaussianCloud
from ..conventions import opacity_logit
from ..densify import split_children

__all__ = ["GaussianModel", "PARAMS", "adam"]

#: Parameter groups of the optimiser, in this order.
PARAMS = ("means", "sh_dc", "sh_rest", "opacities", "scales", "quats")


def adam(groups: list[dict], fused: bool = True) -> torch.optim.Adam:
    """The reference's Adam (eps 1e-15) over `groups`, torch's fused kernel where this torch has it
    for the groups' device (the same update, several times faster on the CPU than the loop over
    parameters); `fused` False: the loop over parameters."""
    if not fused:
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, foreach=False)
    try:
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
    except (RuntimeError, TypeError, ValueError):  # an older torch, or a device without the fused kernel
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


class GaussianModel:
    """Trainable Gaussians: leaf tensors per parameter, one Adam group each (state extended and
    pruned with the Gaussians), lineage ids and stage anchors.

    `lrs`: learning rate per parameter group; `extent`: the scene extent (the scale of positional
    learning rates and of densification's world sizes); `next_id`: the first id a new Gaussian
    gets; `device`: the torch device of every tensor (random draws stay on the CPU generator, so a
    run is the same on any); `fused_adam` False: Adam looping over the parameters (`adam`)."""

    def __init__(self, cloud: GaussianCloud, ids, parents, lrs: dict[str, float], extent: float, next_id: int,
                 device=None, *, fused_adam: bool = True):
        self.device = torch.device(device or "cpu")
        c = cloud.to_torch(device=self.device, dtype=torch.float32)
        self.params = {name: getattr(c, name).detach().clone().requires_grad_(True) for name in PARAMS}
        self.ids = torch.as_tensor(np.asarray(ids), dtype=torch.int64, device=self.device).clone()
        self.parents = torch.as_tensor(np.asarray(parents), dtype=torch.int64, device=self.device).clone()
        self.next_id = int(next_id)
        self.extent = float(extent)
        self.optimizer = adam([{"params": [self.params[n]], "lr": lrs[n], "name": n} for n in PARAMS], fused_adam)

    @classmethod
    def fresh(cls, cloud: GaussianCloud, lrs: dict[str, float], extent: float, device=None,
              **kwargs) -> GaussianModel:
        """`cloud`'s Gaussians with ids 0..n-1 and no parents (a fine-tune's)."""
        n = len(cloud)
        return cls(cloud, np.arange(n), np.full(n, -1), lrs, extent, n, device, **kwargs)

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

    def set_lr(self, name: str, lr: float) -> None:
        self.optimizer.param_groups[PARAMS.index(name)]["lr"] = lr

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

    def reset_optimizer_state(self) -> None:
        """Adam afresh: its moments and step counts dropped (made again at the next step)."""
        self.optimizer.state.clear()

    def snapshot(self) -> GaussianCloud:
        """A detached numpy copy with int64 extras `gvae_id` and `gvae_parent`."""
        c = GaussianCloud(**{n: p.detach().cpu() for n, p in self.params.items()}).numpy().copy()
        return c.replace(extra={"gvae_id": self.ids.cpu().numpy().copy(),
                                "gvae_parent": self.parents.cpu().numpy().copy()})

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

    def keep(self, mask: torch.Tensor) -> None:
        index = torch.nonzero(mask).flatten()
        self._edit(index, None)
        self.ids, self.parents = self.ids[index], self.parents[index]

    def clone(self, mask: torch.Tensor) -> int:
        """Copy the selected Gaussians (the reference's clone: same parameters)."""
        rows = torch.nonzero(mask).flatten()
        if len(rows):
            self.append({n: p.detach()[rows] for n, p in self.params.items()}, rows)
        return len(rows)

    def split(self, mask: torch.Tensor, generator: torch.Generator, n_children: int = 2) -> int:
        """Replace each selected Gaussian by `n_children` (`densify.split_children`); the children
        come last, in the order of their parents, the first child of each first."""
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
