"""The one front door from a folder to a trained splat: `train_capture`. Structure from motion
when the folder is photos without cameras (and points triangulated for poses without them, where
the start uses points), reading, training, progress and cancel; `gvae train` and Blender's New from
Photos both call it."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..capture import Capture, open_capture, read_capture
from ..capture.sfm import SfMOptions, pending_work
from ..progress import say
from .config import TrainConfig
from .data import training_data
from .progressive import TrainResult, train_progressive

__all__ = ["train_capture", "CaptureTraining", "TrainingCancelled", "SFM_SHARE"]

#: The share of the whole job's progress that structure from motion (or triangulation) takes when it runs.
SFM_SHARE = 0.2


class TrainingCancelled(RuntimeError):
    """`cancel()` asked to stop; the run folder keeps the finished stages (a later call resumes)."""


@dataclass
class CaptureTraining:
    """What `train_capture` did: the training's result, the configuration it trained with (the
    stage heights a `downscale` chose), the capture's cameras (every frame, the held-out ones
    marked) and what structure from motion did (None: nothing ran)."""

    result: TrainResult
    config: TrainConfig
    capture: Capture
    sfm: Any = None


def train_capture(path, config: TrainConfig, out_dir, *, downscale: float | None = None,
                  sfm: SfMOptions | None = None, init_points=None, own_test_split: bool = False,
                  resume: bool = True, progress: bool = True, threads: int | None = None, device=None,
                  on_progress: Callable[[dict], None] | None = None,
                  cancel: Callable[[], bool] | None = None) -> CaptureTraining:
    """Train `config` on the capture at `path` into `out_dir` (`train_progressive`): structure from
    motion first where `path` is photos without cameras (`sfm` options; `threads` its threads too),
    points triangulated with the poses of a capture without points when the start uses them.
    `downscale`: the last stage at the stored images' height divided by it (earlier stages in
    proportion). `own_test_split`: a NeRF-Synthetic folder holds out its own test split instead of
    every `config.test_every`-th image. `progress`: say what it does. `on_progress(event)`: the
    training's reports (`train.ProgressHook`, with the stage's "planned" iterations and
    "resolution") and structure from motion's, each with "phase" ("sfm" or "train"), "fraction" (of
    the whole job) and "message". `cancel()`, polled as it goes: True
    stops it (`TrainingCancelled`; what `out_dir` holds resumes)."""
    points = init_points is None and config.init in ("auto", "sfm")
    work = pending_work(path, points)
    share = SFM_SHARE if work else 0.0
    emit = on_progress or (lambda event: None)
    capture = _prepared(path, sfm, threads, points, progress, emit, work, cancel)
    if downscale is not None:
        if not downscale >= 1:
            raise ValueError(f"downscale must be 1 or more, got {downscale}")
        config = config.at_height(int(read_capture(path, images=False).cameras[0].height / downscale))
    if own_test_split and capture.kind == "nerf-synthetic":
        config = dataclasses.replace(config, test_every=None)
    data = training_data(capture, test_every=config.test_every)
    total, before = max(sum(config.iterations), 1), [sum(config.iterations[:s]) for s in range(len(config.iterations))]

    def hook(event: dict) -> None:
        if cancel is not None and cancel():
            raise TrainingCancelled(f"{out_dir}: training cancelled; the finished stages are kept (start again to "
                                    "resume)")
        s = min(int(event["stage"]), len(before) - 1)
        done = before[s] + min(int(event["step"]), config.iterations[s])
        emit({**event, "phase": "train", "fraction": share + (1.0 - share) * done / total,
              "planned": config.iterations[s], "resolution": config.resolutions[s]})

    result = train_progressive(data, config, out_dir=out_dir, init_points=init_points, resume=resume,
                               progress=progress, threads=threads, device=device, on_progress=hook)
    cameras = read_capture(path, config.test_every, images=False)
    return CaptureTraining(result, config, cameras, capture.sfm_report)


def _prepared(path, sfm: SfMOptions | None, threads: int | None, points: bool, progress: bool, emit,
              work: str | None, cancel) -> Capture:
    """The capture at `path`, made one first where it needs structure from motion or triangulation
    (`work`, said)."""
    share = SFM_SHARE if work else 0.0
    if work == "structure from motion" and progress:
        say(f"{path}: photos and no cameras: structure from motion (pycolmap, CPU)")
    elif work and progress:
        say(f"{path}: poses and no points: points triangulated with the poses (pycolmap, CPU)")
    options = sfm or SfMOptions(threads=threads)
    last = [0.0, ""]

    def sfm_progress(stage: str, fraction: float, message: str) -> None:
        emit({"phase": "sfm", "fraction": share * fraction, "message": f"{work}: {message or stage}"})
        now = time.perf_counter()
        if progress and (stage != last[1] or now - last[0] > 5.0 or fraction >= 1.0):
            say(f"  [{fraction:4.0%}] {message or stage}")
            last[:] = [now, stage]

    capture = open_capture(path, points=points, sfm=options, progress=sfm_progress, cancel=cancel)
    if capture.sfm_report is not None and progress:
        say(capture.sfm_report.summary())
    return capture
