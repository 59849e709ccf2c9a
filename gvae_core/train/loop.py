"""The optimisation: one training step (`train_step`) and the stage of steps around it (`run_stage`).

A step is the reference 3DGS's: the position learning rate set for the step, the next view of a
random order without repetition, its render, 0.8·L1 + 0.2·(1 − SSIM) against its photo (and,
weighted by `depth_weight`, the depth error at its SfM points: `train.depth`), the backward, Adam's
step; then the running average and the densification strategy's hook (its statistics, density
control, opacity reset: `train.strategy`) where the stage has them, and, when it trains with
Mip-Splatting's filters, the 3D filter of the training cameras kept up to date.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from ..antialias import FILTER_KEY, filter_3d
from ..camera import Camera
from ..losses import psnr
from ..rendering import RenderSettings, render
from .average import ParameterAverage
from .config import TrainConfig, position_lr
from .depth import DepthTargets, depth_loss
from .model import GaussianModel
from .photometric import photometric_loss
from .strategy import DensifyState, DensifyStrategy

__all__ = ["Stage", "StageOutcome", "train_step", "run_stage", "centres_filter"]


@dataclass
class Stage:
    """One stage's optimisation of `model` on `cameras` and their photos `targets` ((N, H, W, 3) on
    the model's device): at most `iterations` steps; the position learning rate decays as at
    iteration offset + it of a decay over horizon iterations (`lr_window`, default the stage's own
    iterations), staying at its final value after; `degree_at(it)` the SH degree at the stage's
    iteration `it` (1-based). `rng` draws the order of the views, `generator` densification's
    children. `strategy` (None: the Gaussians stay the same rows), `average` (takes in every step;
    or, with `average_from`, one of decay `average_decay` begun at that iteration, once the rows no
    longer change) and `filter_every` (with `config.antialias` "mip": iterations between refreshes of
    the 3D filter, which also follows every change of count). `depth`: the SfM points' depths each
    view sees, added to the loss with `config.depth_weight` (None: none)."""

    model: GaussianModel
    cameras: list[Camera]
    targets: torch.Tensor
    config: TrainConfig
    iterations: int
    rng: np.random.Generator
    generator: torch.Generator
    degree_at: Callable[[int], int]
    lr_window: tuple[int, int] | None = None
    strategy: DensifyStrategy | None = None
    average: ParameterAverage | None = None
    average_from: int | None = None
    average_decay: float = 0.99
    filter_every: int = 100
    depth: DepthTargets | None = None
    settings: RenderSettings = field(init=False)
    state: DensifyState | None = field(init=False, default=None)
    filter: torch.Tensor | None = field(init=False, default=None)
    order: list[int] = field(init=False, default_factory=list)
    counts: dict[str, int] = field(init=False, default_factory=lambda: {"cloned": 0, "split": 0, "pruned": 0})

    def __post_init__(self):
        self.settings = RenderSettings(antialias=self.config.antialias)
        if self.lr_window is None:
            self.lr_window = (0, self.iterations)
        if self.strategy is not None:
            self.state = self.strategy.initialize_state(self.model)
        if self.config.antialias == "mip":
            self.filter = centres_filter(self.model.params["means"].detach(), self.cameras)

    def next_view(self) -> int:
        if not self.order:
            self.order = list(self.rng.permutation(len(self.cameras)))
        return int(self.order.pop())

    def drawn(self):
        """The model as a step draws it: with the 3D filter when training with the Mip filters."""
        current = self.model.cloud()
        return current if self.filter is None else current.replace(extra={FILTER_KEY: self.filter})

    def result_params(self) -> dict[str, torch.Tensor]:
        """The parameters the stage's result is made of so far: the running average once it has one,
        else the current iterate (shared, not copied)."""
        return self.average.values if self.average is not None else self.model.params


@dataclass
class StageOutcome:
    """What `run_stage` did: the iterations run, why it stopped early (None: it did not), and the
    Gaussians densification cloned, split and pruned."""

    iterations: int
    stopped: str | None
    cloned: int = 0
    split: int = 0
    pruned: int = 0


def train_step(stage: Stage, it: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Iteration `it` (1-based) of `stage`; returns (loss, the rendered image, the view's index)."""
    model, config = stage.model, stage.config
    offset, horizon = stage.lr_window
    model.set_lr("means", position_lr(config, model.extent, offset + it - 1, horizon))
    v = stage.next_view()
    camera = stage.cameras[v]
    result = render(stage.drawn(), camera, background=config.background, sh_degree=stage.degree_at(it),
                    settings=stage.settings)
    if stage.strategy is not None:
        stage.strategy.step_pre_backward(result)
    loss = photometric_loss(result.image, stage.targets[v], config.lambda_dssim,
                            compiled=stage.settings.kernels != "torch")
    if stage.depth is not None and config.depth_weight > 0:
        loss = loss + config.depth_weight * depth_loss(result.depth, stage.depth, v)
    loss.backward()
    with torch.no_grad():
        model.optimizer.step()
        model.optimizer.zero_grad(set_to_none=True)
        if stage.average is not None:
            stage.average.update(model)
        elif stage.average_from is not None and it >= stage.average_from:
            stage.average = ParameterAverage(model, stage.average_decay)
        if stage.strategy is not None:
            done = stage.strategy.step_post_backward(model, stage.state, result, camera, it, stage.generator)
            for k, n in (done or {}).items():
                stage.counts[k] += n
        if stage.filter is not None and (it % stage.filter_every == 0 or len(stage.filter) != len(model)):
            stage.filter = centres_filter(model.params["means"].detach(), stage.cameras)  # as the centres move
    return loss, result.image, v


def run_stage(stage: Stage, *, bar=None, progress: Callable[[int], None] | None = None,
              check: Callable[[int], str | None] | None = None, check_every: int = 100) -> StageOutcome:
    """`stage`'s steps (`train_step`). `bar` (`gvae_core.progress`) and `progress(it)` every 10
    iterations and at the last; `check(it)` every `check_every` iterations: a reason to stop, or
    None."""
    stopped, it = None, 0
    for it in range(1, stage.iterations + 1):
        loss, image, v = train_step(stage, it)
        if it % 10 == 0 or it == stage.iterations:
            if bar is not None:
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", psnr=f"{psnr(image, stage.targets[v]):.2f}",
                                n=len(stage.model))
                bar.update(10 if it % 10 == 0 else it % 10)
            if progress is not None:
                progress(it)
        if check is not None and it % check_every == 0:
            with torch.no_grad():
                stopped = check(it)
            if stopped is not None:
                break
    return StageOutcome(it, stopped, **stage.counts)


def centres_filter(means: torch.Tensor, cameras: list[Camera]) -> torch.Tensor:
    """Mip-Splatting's 3D filter of Gaussians at `means` for `cameras`, on the device of `means`."""
    return torch.from_numpy(filter_3d(means.cpu().numpy(), cameras)).to(means.device)
