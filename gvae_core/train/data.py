"""What a run trains from (`TrainingData`: the views of a split at a stage's height, the SfM
points) and the validation photos set aside from its training views (`split_validation`)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from ..capture import Capture, SfMPoints, open_capture
from ..datasets import Views, every_nth

__all__ = ["TrainingData", "training_data", "split_validation"]


@dataclass
class TrainingData:
    """What a run trains from: `views(split, height)` -> the split's views at that image height, or
    None when there is no such split; the capture's SfM points (None without); a line saying what
    it is; the capture's path (None for views in memory)."""

    views: Callable[[str, int], Views | None]
    points: SfMPoints | None = None
    description: str = "views given in memory"
    source: str | None = None


def training_data(data, test=None, test_every: int | None = None) -> TrainingData:
    """`data` as TrainingData: a capture (a path `capture.open_capture` reads: COLMAP, a
    transforms.json, a NeRF-Synthetic folder, a folder of photos; or a `Capture`) with every
    `test_every`-th image held out, a (split, height) -> views function, or in-memory views
    (resampled to each height; `test` views likewise)."""
    if isinstance(data, TrainingData):
        return data
    if isinstance(data, (str, os.PathLike, Capture)):
        capture = (data if isinstance(data, Capture) else open_capture(data)).held_out(test_every)

        def views(split: str, height: int):
            return capture.load(split, height) if len(capture.indices(split)) else None

        return TrainingData(views, capture.points, capture.summary(), str(capture.source))
    if callable(data):
        return TrainingData(data)
    if not isinstance(data, Views) or not (test is None or isinstance(test, Views)):
        raise ValueError("train_progressive: data must be a capture (a COLMAP model, a transforms.json, a "
                         "NeRF-Synthetic folder), a (split, height) -> views function or gvae_core.datasets.Views")
    splits = {"train": data, "test": test}

    def source(split: str, height: int):
        v = splits.get(split)
        return None if v is None else v.at_resolution(height)

    return TrainingData(source)


def split_validation(views: Views, count: int) -> tuple[Views, Views | None]:
    """(training views, validation views): `count` of `views` (at most one in eight, spread evenly
    by name from half a spacing in: none of the first or last; `datasets.every_nth`) set aside to
    judge convergence and choices, never trained on; the same photos at every image height.
    (views, None) when none is set aside."""
    n = len(views)
    k = min(int(count), n // 8)
    if k <= 0:
        return views, None
    every = Fraction(n, k)
    pick = every_nth(views.names, every, every / 2)
    return views.subset(np.setdiff1d(np.arange(n), pick)), views.subset(pick)
