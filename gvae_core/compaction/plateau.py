"""When fine-tuning stops paying: a score measured every few iterations (the PSNR of views the
fine-tuning does not train on) that has not risen by `min_gain` for `patience` checks in a row.
Torch-free; the fine-tuning calls `Plateau.update` from `train.fine_tune`'s `should_stop`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

#: Checks in a row without a gain of MIN_GAIN dB over the best before the fine-tuning stops.
PATIENCE = 4
#: The least rise (dB) over the best so far that counts as still paying.
MIN_GAIN = 0.02


@dataclass
class Plateau:
    """The best value seen and where (`best`, `best_at`), and every (iteration, value) checked
    (`history`). `update(it, value)` says whether to stop: the value has not risen MIN_GAIN above
    the best for `patience` checks in a row (a smaller rise still moves the best, so that the
    best state is kept, but does not count as paying)."""

    patience: int = PATIENCE
    min_gain: float = MIN_GAIN
    best: float = -math.inf
    best_at: int = 0
    waited: int = 0
    history: list[tuple[int, float]] = field(default_factory=list)

    def __post_init__(self):
        if int(self.patience) < 1:
            raise ValueError(f"Plateau: patience must be 1 or more checks, got {self.patience}")
        if not self.min_gain >= 0.0:
            raise ValueError(f"Plateau: min_gain must be >= 0 dB, got {self.min_gain}")

    def update(self, it: int, value: float) -> bool:
        """Record `value` at iteration `it`; True when the fine-tuning should stop."""
        value = float(value)
        self.history.append((int(it), value))
        if value > self.best + self.min_gain:
            self.waited = 0
        else:
            self.waited += 1
        if value > self.best:
            self.best, self.best_at = value, int(it)
        return self.waited >= self.patience
