"""Finished training runs' held-out photos scored one by one, as the run's last stage was drawn and
without the Gaussians that none of its training photos draws (`train.unseen`, the rule a stage's
result now follows): the figures of docs/benchmarks/training.md "Gaussians no training photo draws".

Each run's `run.json` gives its background, anti-aliasing, held-out spacing and validation photos
(its training photos are the capture's less the held-out and the validation ones, as it trained);
its last `stage_<s>.ply` is the result scored, at that stage's height, against the held-out photos
composited on the background (the trainer's own scoring).

Usage: python tools/unseen_trials.py CAPTURE RUN [RUN ...]
e.g.   python tools/unseen_trials.py ../shared/captures/plush runs/plush-s0 runs/plush-s1
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gvae_core.losses import psnr  # noqa: E402
from gvae_core.ply import read_ply  # noqa: E402
from gvae_core.rendering import RenderSettings, render  # noqa: E402
from gvae_core.train.data import split_validation, training_data  # noqa: E402
from gvae_core.train.unseen import seen_by_any  # noqa: E402


def per_photo(cloud, views, background, settings) -> list[float]:
    targets = torch.from_numpy(views.composite(background))
    bg = torch.tensor(background, dtype=torch.float32)
    with torch.no_grad():
        return [psnr(render(cloud, cam, background=bg, settings=settings).image.clamp(0, 1), targets[i])
                for i, cam in enumerate(views.cameras)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path)
    p.add_argument("runs", type=Path, nargs="+")
    args = p.parse_args(argv)
    for run in args.runs:
        config = json.loads((run / "run.json").read_text())["config"]
        log = json.loads((run / "log.json").read_text())
        height = log[-1]["resolution"]
        data = training_data(args.capture, test_every=config["test_every"])
        training, _ = split_validation(data.views("train", height), config["validation_views"])
        test = data.views("test", height)
        settings = RenderSettings(antialias=config["antialias"])
        cloud = read_ply(run / f"stage_{log[-1]['stage']}.ply").to_torch()
        seen = seen_by_any(cloud, training.cameras, settings).numpy()
        kept = cloud.select(np.flatnonzero(seen))
        background = tuple(config["background"])
        before, after = per_photo(cloud, test, background, settings), per_photo(kept, test, background, settings)
        print(f"{run}: {int((~seen).sum())} of {len(seen)} Gaussians drawn by no training photo; held-out PSNR "
              f"{np.mean(before):.2f} -> {np.mean(after):.2f} dB without them; per photo: "
              + ", ".join(f"{a:.2f} -> {b:.2f}" for a, b in zip(before, after)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
