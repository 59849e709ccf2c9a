"""The validation photos of a stage: training photos set aside (never trained on) and drawn every
few iterations (the curve), and for the stage that trains until it converges, when to stop (the
`gvae_core.plateau.Plateau` rule once the planned iterations are done, or the time budget) and the
state they liked best."""

from __future__ import annotations

import math
import time
from typing import Any

import torch

from ..antialias import FILTER_KEY
from ..camera import Camera
from ..cloud import GaussianCloud
from ..datasets import Views
from ..plateau import Plateau
from ..rendering import RenderSettings
from .config import TrainConfig
from .evaluation import evaluate_psnr
from .loop import centres_filter

__all__ = ["Validation"]


class Validation:
    """A stage's validation photos `views`. `planned`: the stage's planned iterations; `converging`:
    whether it trains on past them until the photos stop improving (from `started`, a
    `time.perf_counter()`, `config.max_minutes` at most); `test_views` (converging only): the
    held-out views, drawn once at the planned count for the log (they never decide)."""

    def __init__(self, config: TrainConfig, views: Views, cameras: list[Camera], settings: RenderSettings,
                 started: float, planned: int, converging: bool, say, test_views: Views | None = None):
        self.views, self.cameras, self.background, self.settings = views, cameras, config.background, settings
        self.test_views, self.test_at_planned = test_views, None
        self.plateau = Plateau(patience=config.patience, min_gain=config.min_gain)
        self.deadline = None if config.max_minutes is None else started + 60.0 * config.max_minutes
        self.planned, self.converging, self.say = planned, converging, say
        self.curve: list[tuple[int, float]] = []
        self.best, self.best_step, self.best_params = -math.inf, 0, None

    def check(self, params: dict[str, torch.Tensor], it: int, degree: int, report) -> str | None:
        """The validation PSNR at iteration `it` of the Gaussians `params` (the stage's result so far:
        `Stage.result_params`; said, reported, on the curve); a reason to stop, or None."""
        current = self.drawn(params)
        value = self._score(current, it, degree)
        message = f"step {it}: validation photos {value:.2f} dB, {len(current)} Gaussians"
        self.say(message)
        report(it, message, validation_psnr=round(value, 4))
        if not self.converging:
            return None
        if it >= self.planned and value > self.best:  # (the best state once densification is over)
            self._keep(params, it, value)
        if it < self.planned:
            return None
        if self.test_at_planned is None and self.test_views is not None:  # said in the log, never decides
            self.test_at_planned = (it, evaluate_psnr(current, self.test_views, self.background, degree, None,
                                                      self.settings))
        if self.plateau.update(it, value):
            return f"converged: {self.plateau.reason}"
        if self.deadline is not None and time.perf_counter() > self.deadline:
            return "stopped by the time budget (max_minutes)"
        return None

    def drawn(self, params: dict[str, torch.Tensor]) -> GaussianCloud:
        """The Gaussians `params` as training draws them (with the training cameras' filter in "mip")."""
        current = GaussianCloud(**params).detach()
        if self.settings.antialias == "mip":
            current = current.replace(extra={FILTER_KEY: centres_filter(current.means, self.cameras)})
        return current

    def judge(self, params: dict[str, torch.Tensor], it: int, degree: int) -> bool:
        """Whether the validation photos like `params` (at iteration `it`, on the curve) better than the
        best state so far; if so it becomes the best."""
        value = self._score(self.drawn(params), it, degree)
        self.say(f"step {it}: validation photos {value:.2f} dB (the best so far {self.best:.2f})")
        if value <= self.best:
            return False
        self._keep(params, it, value)
        return True

    def _score(self, cloud: GaussianCloud, it: int, degree: int) -> float:
        """The validation PSNR of `cloud`, put on the curve at iteration `it`."""
        value = evaluate_psnr(cloud, self.views, self.background, degree, None, self.settings)
        self.curve.append((it, round(value, 4)))
        return value

    def _keep(self, params: dict[str, torch.Tensor], it: int, value: float) -> None:
        """`params` (a copy) as the best state, at iteration `it` with PSNR `value`."""
        self.best, self.best_step = value, it
        self.best_params = {n: p.detach().clone() for n, p in params.items()}

    def summary(self, stopped: str | None, iterations: int) -> dict[str, Any]:
        """The log's record of the validation: the curve and, converging, why it stopped and the state kept."""
        out: dict[str, Any] = {"validation_curve": self.curve}
        if self.converging:
            out["stopped"] = stopped or f"reached max_iterations ({iterations})"
            out["best_step"] = self.best_step if self.best_params is not None else iterations
            if self.test_at_planned is not None:
                out["test_psnr_at_planned"] = [self.test_at_planned[0], round(self.test_at_planned[1], 4)]
        return out
