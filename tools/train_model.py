"""`make train-model`: reproduce the bundled models from scratch with the project's own pipeline.

The detail model (the default, `--model detail`): for every training scene and scene seed (seeded
variants of the objects, `make_scene(..., seed=)`), render it with Blender (cached) and train
progressive 3DGS with lineage tracking up to the quick protocol's training resolution (cached and
resumable; `Protocol.data`); every stage after the first is an example with the scene's real
training views at 1.5x and 2x its resolution, twice: with the run's lineage and without (as a
user's PLY comes); train the detail model through the renderer on all
of them (`gvae_core.detail.fit_model`) and score it on the validation scenes at 2x against the
unrefined cloud. The lineage VAEs (`--model vae`): the full protocol's runs of the training scenes
and `gvae fit-vae` with the validation scenes held out. Prints how long each part took.
Usage: python tools/train_model.py [--model detail|vae] [--out models] [--steps N] [--antialias classic|mip]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from gvae_core.cli import main as gvae
from gvae_core.detail import DetailConfig, DetailModel, FitConfig, detail_inputs, fit_model, save_detail
from gvae_core.detail.data import run_examples
from gvae_core.experiment import PROTOCOLS, Evaluator, prepare_scene, prepare_scenes
from gvae_core.octaves import with_octaves
from gvae_core.scenes import SPLITS

#: What the bundled detail model was trained with (`make train-model`), and the 3DGS seeds of the
#: validation runs it is scored on.
DETAIL_SCENE_SEEDS = (0, 1)
VALIDATION_SEEDS = (0, 1)
DETAIL_STEPS = 3000
DETAIL_PATCH = 128


def train_detail(args) -> int:
    protocol = PROTOCOLS[args.protocol]
    if args.antialias == "mip":  # runs trained (and scored) with Mip-Splatting's filters
        protocol = dataclasses.replace(protocol, name=f"{protocol.name}-mip", antialias="mip",
                                       train_overrides={**protocol.train_overrides, "antialias": "mip"})
    start = time.perf_counter()
    config = DetailConfig()
    examples, seconds = [], {"scene": 0.0, "train": 0.0}
    for scene_seed in args.scene_seeds:
        data = protocol.data(scene_seed)
        for name in args.train:
            run = prepare_scene(name, data, seed=0, cache=args.cache_dir, threads=1,
                                say=lambda m: print(f"[train-model] {m}", flush=True))
            for part in seconds:
                seconds[part] += run.seconds[part]
            examples += run_examples(run.run_dir, run.scene_dir, range(1, len(data.resolutions)),
                                     name=f"{name}-s{scene_seed}", without_lineage=True,
                                     neighbours=config.inputs_neighbours)
    prepared = time.perf_counter()
    print(f"[train-model] {len(examples)} examples from {len(args.train) * len(args.scene_seeds)} runs; scenes "
          f"{seconds['scene']:.0f} s, 3DGS {seconds['train']:.0f} s (0 when cached)", flush=True)
    model = DetailModel(config)
    losses: list[float] = []

    def progress(step: int, loss: float) -> None:
        losses.append(loss)
        if step % 250 == 0:
            print(f"[train-model] step {step}/{args.steps}: loss {np.mean(losses[-250:]):.5f}", flush=True)

    fit = FitConfig(steps=args.steps, patch=DETAIL_PATCH, seed=args.seed, antialias="auto")  # each cloud's own mode
    history = fit_model(model, examples, fit, progress)
    model.meta = {"train_scenes": list(args.train), "scene_seeds": list(args.scene_seeds),
                  "protocol": protocol.data().name, "examples": len(examples), "steps": args.steps,
                  "patch": DETAIL_PATCH, "seed": args.seed, "seconds": round(history["seconds"], 1),
                  "antialias": args.antialias,
                  "validation": {}}
    for name in args.holdout:  # (validation scenes: never trained on)
        for seed in VALIDATION_SEEDS:
            run = prepare_scene(name, protocol.data(), seed=seed, cache=args.cache_dir, threads=1)
            k = protocol.train_stage
            base, lineage = run.stage_cloud(k), run.lineage(k + 1)
            evaluate = Evaluator(run)
            before = evaluate(base)
            for label, known in (("lineage", lineage), ("no lineage", None)):
                inputs = detail_inputs(base, known, neighbours=config.inputs_neighbours)
                after = evaluate(with_octaves(base, model.changes(inputs)))
                gain = {s: round(after[f"psnr_{s}"] - before[f"psnr_{s}"], 3) for s in ("1x", "1.5x", "2x")}
                model.meta["validation"][f"{name} s{seed}, {label}"] = gain
                print(f"[train-model] {name} s{seed} ({label}): PSNR change {gain}", flush=True)
    save_detail(model, args.out)
    print(f"[train-model] data {(prepared - start) / 60:.1f} min, fit {history['seconds'] / 60:.1f} min, total "
          f"{(time.perf_counter() - start) / 60:.1f} min; saved to {args.out} ({model.size_bytes() / 1e3:.0f} kB)")
    return 0


def train_vae(args) -> int:
    protocol = PROTOCOLS[args.protocol]
    train, held = list(args.train), list(args.holdout)
    scenes = train + held
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/train_model.py", description=__doc__.splitlines()[0])
    p.add_argument("--model", choices=("detail", "vae"), default="detail", help="which model (default: detail)")
    p.add_argument("--out", type=Path, default=Path("models"), help="model directory (default: models)")
    p.add_argument("--protocol", default=None, choices=list(PROTOCOLS),
                   help="scenes and training runs to learn from (default: quick for detail, full for vae)")
    p.add_argument("--train", nargs="*", default=list(SPLITS["train"]), help="scenes to learn from "
                   "(default: the training split)")
    p.add_argument("--holdout", nargs="*", default=list(SPLITS["validation"]),
                   help="scenes kept out of training and evaluated (default: the validation split)")
    p.add_argument("--scene-seeds", nargs="*", type=int, default=list(DETAIL_SCENE_SEEDS),
                   help="detail: the seeded variants of each training scene (default: %(default)s)")
    p.add_argument("--antialias", choices=("classic", "mip"), default="classic",
                   help="detail: learn from runs trained the classic way (the shipped model) or with "
                   "Mip-Splatting's filters (default: %(default)s)")
    p.add_argument("--steps", type=int, default=None,
                   help=f"optimiser steps (default: {DETAIL_STEPS} for detail, 6000 for vae)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cache-dir", type=Path, default=None, help="scene and run cache (default: $GVAE_CACHE_DIR)")
    p.add_argument("--jobs", type=int, default=None, help="vae: scenes prepared at once (default: one per core)")
    args = p.parse_args(argv)
    if not args.holdout or not args.train or set(args.train) & set(args.holdout) \
            or set(args.train + args.holdout) & set(SPLITS["test"]):
        raise SystemExit(f"need training and held-out scenes apart from each other and from the test split, got "
                         f"training {args.train}, held out {args.holdout}")
    args.protocol = args.protocol or ("quick" if args.model == "detail" else "full")
    args.steps = args.steps or (DETAIL_STEPS if args.model == "detail" else 6000)
    return train_detail(args) if args.model == "detail" else train_vae(args)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
