"""The one call that reads a capture from a folder: `open_capture` runs (or reuses) structure from
motion for a folder of photos and, when asked, triangulation for poses without points
(`capture.sfm.ensure_capture`), then reads it (`capture.dataset.read_capture`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from .dataset import Capture, read_capture
from .sfm import Progress, SfMOptions, ensure_capture

__all__ = ["open_capture"]


def open_capture(path, test_every: int | None = None, *, images: bool = True, points: bool = False,
                 sfm: SfMOptions | None = None, progress: Progress | None = None,
                 cancel: Callable[[], bool] | None = None) -> Capture:
    """The capture at `path` with every `test_every`-th image held out (`read_capture`), made one
    first where it is a folder of photos without cameras (structure from motion with the `sfm`
    options; its report is the capture's `sfm_report`) and, with `points`, given triangulated points
    where it has poses and no points. `progress(stage, fraction, message)` and `cancel()` as
    `capture.sfm.run_sfm` takes them; nothing runs where nothing is needed (the model is reused)."""
    report = ensure_capture(path, sfm, points=points, progress=progress, cancel=cancel)
    capture = read_capture(path, test_every, images=images)
    return dataclasses.replace(capture, sfm_report=report) if report is not None else capture
