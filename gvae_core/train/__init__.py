"""Progressive 3DGS training with lineage tracking, one module per job:

- `config`: `TrainConfig` (every field with its help), the named profiles, the schedules;
- `model`: `GaussianModel`, the trainable Gaussians and the edits densification makes;
- `strategy`: densification as a strategy (`DensifyStrategy`): its schedule, gradient statistics,
  opacity reset and budget, called by the loop before and after the backward;
- `loop`: one training step and the stage of steps around it; `photometric`: its loss, compiled;
- `unseen`: the Gaussians no training photo draws, which a stage's result leaves out;
- `validation`: the photos set aside and the rule that stops the last stage;
- `evaluation`: PSNR / SSIM of a cloud on views (training, compaction and refine report it);
- `average`: the running average of the iterates;
- `run_folder`: run.json, log.json, adam.npz and the stage PLYs, read and written by one class;
- `data`: what a run trains from, and the validation photos set aside;
- `progressive`: `train_progressive`, the stages; `more`: `fine_tune` and `train_more`;
- `job`: `train_capture`, the front door from a folder to a trained splat.

Importing this package imports no torch: its names load on first use.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "TrainConfig": "config", "PROFILES": "config", "configure": "config", "stage_heights": "config",
    "position_lr": "config",
    "GaussianModel": "model",
    "DensifyStrategy": "strategy", "gaussian_limit": "strategy",
    "ParameterAverage": "average",
    "evaluate_views": "evaluation", "evaluate_psnr": "evaluation", "training_targets": "evaluation",
    "RunFolder": "run_folder",
    "TrainingData": "data", "training_data": "data", "split_validation": "data",
    "ProgressHook": "reporting", "PROGRESS_KEYS": "reporting",
    "train_progressive": "progressive", "TrainResult": "progressive",
    "fine_tune": "more", "train_more": "more", "MoreResult": "more",
    "train_capture": "job", "CaptureTraining": "job", "TrainingCancelled": "job",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
