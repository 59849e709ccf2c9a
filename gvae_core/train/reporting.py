"""How a training run tells its progress: the progress reports (`ProgressHook`, `Reporter`), the
lines it says, and the torch threads it runs with (`torch_threads`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch

__all__ = ["ProgressHook", "PROGRESS_KEYS", "Reporter", "torch_threads"]

#: Called by `train_progressive` and `train_more` with a progress report (a dict: `PROGRESS_KEYS` and,
#: when just measured, "validation_psnr", "train_psnr", "test_psnr", "test_ssim"); an exception it
#: raises stops training (the finished stages stay on disk and a later call resumes after them).
ProgressHook = Callable[[dict[str, Any]], None]
#: The keys of every progress report: stage (0-based) of stages, step (iterations done in the stage)
#: of steps (its planned count; while the last stage trains until it converges, the most it may
#: take), n_gaussians, and a message for people.
PROGRESS_KEYS = ("stage", "stages", "step", "steps", "n_gaussians", "message")


class Reporter:
    """`report(step, message, **measured)` -> `hook` with the `PROGRESS_KEYS` of stage `stage` of
    `stages` (`count()` says the Gaussians now); measured values that are None are left out. A
    no-op without a hook."""

    def __init__(self, hook: ProgressHook | None, stage: int, stages: int, steps: int, count: Callable[[], int]):
        self.hook, self.stage, self.stages, self.steps, self.count = hook, stage, stages, int(steps), count

    def __call__(self, step: int, message: str, **measured) -> None:
        if self.hook is not None:
            self.hook({"stage": self.stage, "stages": self.stages, "step": int(step), "steps": self.steps,
                       "n_gaussians": self.count(), "message": message,
                       **{k: v for k, v in measured.items() if v is not None}})


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """torch's CPU threads set to `threads` (None: as they are) for the block, restored after."""
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(previous)
