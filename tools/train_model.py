"""`make train-model`: reproduce the bundled lineage VAEs from scratch with the project's own pipeline.

For every benchmark scene: render it with Blender (cached), train progressive 3DGS with lineage
tracking through the training resolution and the real 1.5x and 2x stages (the `full` protocol
of `gvae_core.experiment`, cached and resumable: the same runs the report evaluates), then
train both VAEs on every stage transition of the training scenes (`gvae fit-vae`) and evaluate
them on the held-out scenes. Prints how long each part took.
Usage: python tools/train_model.py [--out models] [--protocol full] [--holdout chair tableware]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from gvae_core.cli import main as gvae
from gvae_core.experiment import PROTOCOLS, prepare_scenes
from gvae_core.scenes import SPLITS

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/train_model.py", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("models"), help="model directory (default: models)")
    p.add_argument("--protocol", default="full", choices=list(PROTOCOLS),
                   help="scenes and training runs to learn from (default: full)")
    p.add_argument("--train", nargs="*", default=list(SPLITS["train"]), help="scenes to learn from "
                   "(default: the training split)")
    p.add_argument("--holdout", nargs="*", default=list(SPLITS["validation"]),
                   help="scenes kept out of training and evaluated (default: the validation split)")
    p.add_argument("--steps", type=int, default=6000, help="VAE optimiser steps (default: 6000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cache-dir", type=Path, default=None, help="scene and run cache (default: $GVAE_CACHE_DIR)")
    p.add_argument("--jobs", type=int, default=None, help="scenes prepared at once (default: one per core)")
    args = p.parse_args(argv)

    protocol = PROTOCOLS[args.protocol]
    train, held = list(args.train), list(args.holdout)
    scenes = train + held
    if not held or not train or set(train) & set(held) or set(scenes) & set(SPLITS["test"]):
        raise SystemExit(f"need training and held-out scenes apart from each other and from the test split, got "
                         f"training {train}, held out {held}")
    start = time.perf_counter()
    prepared = prepare_scenes(scenes, protocol, cache=args.cache_dir, jobs=args.jobs,
                              say=lambda m: print(f"[train-model] {m}", flush=True))
    runs = {name: run.run_dir for name, run in prepared.items()}
    times = {name: run.seconds for name, run in prepared.items()}
    for name, t in times.items():
        print(f"[train-model] {name}: scene {t['scene']:.0f} s, 3DGS {t['train']:.0f} s (0 when cached)", flush=True)
    t0 = time.perf_counter()
    code = gvae(["fit-vae", *[str(runs[s]) for s in train], "--holdout", *[str(runs[s]) for s in held],
                 "--out", str(args.out), "--steps", str(args.steps), "--seed", str(args.seed)])
    fit_s = time.perf_counter() - t0
    total = time.perf_counter() - start
    print(f"[train-model] scenes {sum(t['scene'] for t in times.values()):.0f} s and 3DGS runs "
          f"{sum(t['train'] for t in times.values()):.0f} s (summed over scenes, several at a time), VAE fit "
          f"{fit_s:.0f} s; total {total / 60:.1f} min "
          f"(trained on {', '.join(train)}; held out {', '.join(held)})")
    return code


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
