"""`ParameterAverage`: the running average of a model's parameters over its iterations."""

from __future__ import annotations

from ..cloud import GaussianCloud
from .model import GaussianModel

__all__ = ["ParameterAverage"]


class ParameterAverage:
    """The running average of a model's parameters over the iterations (Polyak averaging with
    exponential weights): a step trains on one photo, so the last iterate carries that photo's
    pull; the average of the last 1 / (1 - `decay`) or so steps does not. The decay at step t is
    min(`decay`, (1 + t) / (10 + t)): the first steps weigh more, so the start is soon forgotten."""

    def __init__(self, model: GaussianModel, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ParameterAverage: decay must be in (0, 1), got {decay!r}")
        self.decay, self.steps = float(decay), 0
        self.values = {name: p.detach().clone() for name, p in model.params.items()}

    def update(self, model: GaussianModel) -> None:
        """Take in the model's current parameters (after an optimiser step; the same rows)."""
        self.steps += 1
        d = min(self.decay, (1.0 + self.steps) / (10.0 + self.steps))
        for name, p in model.params.items():
            self.values[name].mul_(d).add_(p.detach(), alpha=1.0 - d)

    def cloud(self) -> GaussianCloud:
        """The averaged parameters as a torch cloud (shared, not copied)."""
        return GaussianCloud(**self.values)
