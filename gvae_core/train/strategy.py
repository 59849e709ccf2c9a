"""Densification as a strategy object, in the shape of gsplat's `strategy/`: the reference 3DGS's
adaptive density control with its schedule, its gradient statistics, the opacity reset and the
budget, all here; the loop only calls its hooks before and after the backward.

- `DensifyStrategy.for_stage(config, stage, limit)`: the stage's strategy (its schedule from
  `TrainConfig.stage_schedule`, the budget `limit` from `gaussian_limit`);
- `initialize_state(model)`: the statistics (`DensifyState`) it decides on;
- `step_pre_backward(result)`: keep the gradient of the projected centres;
- `step_post_backward(model, state, result, camera, step, generator)`, after the optimiser's step:
  accumulate the statistics and, when the schedule says, a round of density control (clone small
  Gaussians with a large view-space positional gradient, split large ones, prune transparent and
  oversized ones) and the opacity reset.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..camera import Camera
from ..conventions import activate_opacities, activate_scales
from ..densify import g_scale
from ..resources import train_cap
from .config import TrainConfig
from .model import GaussianModel

__all__ = ["DensifyStrategy", "DensifyState", "gaussian_limit"]


@dataclass
class DensifyState:
    """What a round of density control decides on, per Gaussian since the last round: the summed
    norm of the view-space positional gradient (NDC), how many steps saw it, its largest screen
    radius (pixels)."""

    grad_sum: torch.Tensor
    count: torch.Tensor
    max_radii: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device) -> DensifyState:
        return cls(torch.zeros(n, device=device), torch.zeros(n, device=device), torch.zeros(n, device=device))

    def add(self, means2d_grad: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor, width: int,
            height: int) -> None:
        """One step's gradient norms in NDC units (pixel gradient times half the image size, as the
        reference's 0.0002 threshold expects), counted where the Gaussian was visible."""
        g = means2d_grad.detach()[:, :2] * g_scale(width, height, self.grad_sum.device)
        norm = g.norm(dim=-1)
        self.grad_sum += torch.where(visible, norm, torch.zeros_like(norm))
        self.count += visible.float()
        self.max_radii = torch.where(visible, torch.maximum(self.max_radii, radii.float()), self.max_radii)

    def mean_grads(self) -> torch.Tensor:
        return self.grad_sum / self.count.clamp(min=1.0)


@dataclass
class DensifyStrategy:
    """The reference 3DGS adaptive density control, thresholds in the reference's units: mean
    view-space gradient (NDC) `grad_threshold`; Gaussians larger than `percent_dense` x extent are
    split, smaller ones cloned; opacity below `prune_opacity` is pruned, and after `prune_large_after`
    iterations so is a world size above `max_world_size` x extent or, when set, a screen radius above
    `max_screen_fraction` x image height. `max_gaussians`: the budget (the highest gradients win).
    Schedule (iterations of the stage): a round every `every` from `start` to `stop`, none at
    `last` (the stage's final iteration); with `opacity_resets`, opacities come down to
    `reset_value` every `reset_every` before `stop`."""

    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_world_size: float = 0.1
    max_screen_fraction: float | None = None
    max_gaussians: int | None = 50_000
    start: int = 500
    stop: int = 15_000
    every: int = 100
    last: int | None = None
    prune_large_after: int = 3000
    opacity_resets: bool = False
    reset_every: int = 3000
    reset_value: float = 0.01

    @classmethod
    def for_stage(cls, config: TrainConfig, stage: int, limit: int | None, last: int | None = None) -> DensifyStrategy:
        """Stage `stage`'s strategy: the configuration's thresholds, its schedule
        (`TrainConfig.stage_schedule`), `limit` Gaussians at most, no round at iteration `last`."""
        sched = config.stage_schedule(stage)
        return cls(grad_threshold=config.densify_grad_threshold, percent_dense=config.percent_dense,
                   prune_opacity=config.prune_opacity, max_world_size=config.max_world_size,
                   max_screen_fraction=config.max_screen_fraction, max_gaussians=limit,
                   start=sched["densify_from"], stop=sched["densify_until"], every=sched["densify_every"],
                   last=sched["iterations"] if last is None else last,
                   prune_large_after=sched["opacity_reset_every"], opacity_resets=config.opacity_resets,
                   reset_every=sched["opacity_reset_every"], reset_value=config.reset_opacity_value)

    def initialize_state(self, model: GaussianModel) -> DensifyState:
        return DensifyState.zeros(len(model), model.device)

    def step_pre_backward(self, result) -> None:
        """Keep the gradient of the projected centres (`RenderResult.means2d`) for the statistics."""
        if result.means2d.requires_grad:
            result.means2d.retain_grad()

    def step_post_backward(self, model: GaussianModel, state: DensifyState, result, camera: Camera, step: int,
                           generator: torch.Generator) -> dict[str, int] | None:
        """After step `step`'s optimiser step: the statistics, then what the schedule asks for at
        this step (a round of density control, an opacity reset); what a round did, else None."""
        grad = result.means2d.grad
        state.add(grad if grad is not None else torch.zeros_like(result.means2d), result.visible, result.radii,
                  camera.width, camera.height)
        if not self.start <= step <= self.stop:
            return None
        done = None
        if step % self.every == 0 and (self.last is None or step < self.last):
            done = self.densify_and_prune(model, state, generator, prune_large=step > self.prune_large_after,
                                          image_height=camera.height)
        if self.opacity_resets and step % self.reset_every == 0 and step < self.stop:
            model.reset_opacity(self.reset_value)
        return done

    def densify_and_prune(self, model: GaussianModel, state: DensifyState, generator: torch.Generator, *,
                          prune_large: bool, image_height: int) -> dict[str, int]:
        """One round of density control on `model` (`state` restarts after it); returns what it did."""
        grads = state.mean_grads()
        clone_mask, split_mask = self._grow(model, grads)
        n_clone = model.clone(clone_mask)
        pad = torch.zeros(len(model) - len(split_mask), dtype=torch.bool, device=split_mask.device)
        split_rows = torch.cat([split_mask, pad])
        n_split = model.split(split_rows, generator)
        # radii follow the rows: clones and children start at 0, split parents are gone
        radii = torch.cat([state.max_radii, torch.zeros(n_clone, device=state.max_radii.device)])[~split_rows]
        radii = torch.cat([radii, torch.zeros(2 * n_split, device=radii.device)])
        prune = self._prune(model, radii, prune_large, image_height)
        model.keep(~prune)
        fresh = DensifyState.zeros(len(model), model.device)
        state.grad_sum, state.count, state.max_radii = fresh.grad_sum, fresh.count, fresh.max_radii
        return {"cloned": n_clone, "split": n_split, "pruned": int(prune.sum())}

    def _grow(self, model: GaussianModel, grads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(clone, split) masks: high gradients, small or large, the highest within the budget."""
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
        return clone_mask, split_mask

    def _prune(self, model: GaussianModel, radii: torch.Tensor, prune_large: bool, image_height: int) -> torch.Tensor:
        prune = activate_opacities(model.params["opacities"].detach()) < self.prune_opacity
        if prune_large:
            scale_max = activate_scales(model.params["scales"].detach()).max(1).values
            prune |= scale_max > self.max_world_size * model.extent
            if self.max_screen_fraction is not None:
                prune |= radii > self.max_screen_fraction * image_height
        if bool(prune.all()):  # never prune everything away
            prune[torch.argmax(model.params["opacities"].detach())] = False
        return prune


def gaussian_limit(config: TrainConfig, n_views: int, camera: Camera) -> tuple[int, str]:
    """The most Gaussians a stage may grow to, and why: what memory allows (`resources.train_cap`),
    `config.max_gaussians`, and `gaussians_per_pixel` times the pixels of one training photo."""
    limits = [(train_cap(n_views, camera.height, camera.width, config.sh_degree), "what memory allows")]
    if config.max_gaussians is not None:
        limits.append((int(config.max_gaussians), "max_gaussians"))
    if config.gaussians_per_pixel is not None:
        limits.append((max(1, round(config.gaussians_per_pixel * camera.width * camera.height)),
                       f"{config.gaussians_per_pixel:g} per pixel of a photo"))
    return min(limits)
