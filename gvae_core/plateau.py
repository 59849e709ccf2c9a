"""When more training stops helping: a plateau rule on a sequence of (step, value) measurements.

`Plateau` is the one rule the trainer's convergence (`gvae_core.train`: the last stage trains until
its validation photos stop improving) and a fine-tune's early stop (compaction) use: feed it each
measurement (higher is better, for example a PSNR; `higher_is_better=False` for a loss) and it says
stop once `patience` steps have passed since the last gain of at least `min_gain` over the best so
far. Plain Python, no torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["Plateau"]


@dataclass
class Plateau:
    """A plateau rule: `update(step, value)` -> True once the best value has not risen by at least
    `min_gain` (in the value's units, e.g. dB) for `patience` steps. `best`, `best_step`: the best
    value that counted as a gain and its step; `history`: every (step, value) given; `reason`: why
    it said stop (empty until then). A non-finite value is recorded but never counts as a gain."""

    patience: int = 500
    min_gain: float = 0.02
    higher_is_better: bool = True
    best: float = math.nan
    best_step: int = 0
    history: list[tuple[int, float]] = field(default_factory=list)
    reason: str = ""

    def __post_init__(self):
        if self.patience <= 0:
            raise ValueError(f"Plateau: patience must be positive, got {self.patience}")
        if not self.min_gain >= 0:
            raise ValueError(f"Plateau: min_gain must be >= 0, got {self.min_gain}")

    def gain(self, value: float) -> float:
        """How much `value` is better than the best so far (+inf before any finite value)."""
        if math.isnan(self.best):
            return math.inf
        return value - self.best if self.higher_is_better else self.best - value

    def update(self, step: int, value: float) -> bool:
        """Record `value` measured at `step` (steps must not go back); True: stop."""
        step, value = int(step), float(value)
        if self.history and step < self.history[-1][0]:
            raise ValueError(f"Plateau: step {step} comes before the last one ({self.history[-1][0]})")
        if not self.history:
            self.best_step = step
        self.history.append((step, value))
        if math.isfinite(value) and (math.isnan(self.best) or self.gain(value) >= self.min_gain):
            self.best, self.best_step = value, step
        if step - self.best_step >= self.patience:
            self.reason = (f"no gain of {self.min_gain:g} over the best ({self.best:.4g} at step {self.best_step}) "
                           f"in {step - self.best_step} steps")
            return True
        return False

    @property
    def stopped(self) -> bool:
        return bool(self.reason)
