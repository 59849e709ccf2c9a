"""`make train-model`: reproduce the bundled lineage VAEs from scratch with the project's own pipeline.

For every benchmark scene: render it with Blender (`gvae_core.scenes.make_scene`, cached), train
progressive 3DGS with lineage tracking (`gvae train`, resumable), then train both VAEs on all but
the held-out scenes (`gvae fit-vae`) and evaluate on the held-out ones. Prints how long each part
took. Usage: python tools/train_model.py [--out models] [--runs runs/model] [--holdout chair tableware]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

DEFAULT_HOLDOUT = ("chair", "tableware")


def main(argv: list[str] | None = None) -> int:
    from gvae_core.cli import main as gvae  # noqa: PLC0415
    from gvae_core.scenes import list_scenes, make_scene  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="tools/train_model.py", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=Path("models"), help="model directory (default: models)")
    p.add_argument("--runs", type=Path, default=Path("runs/model"), help="where training runs go")
    p.add_argument("--scenes", nargs="*", default=None, help="scenes to use (default: all)")
    p.add_argument("--holdout", nargs="*", default=list(DEFAULT_HOLDOUT), help="scenes kept out of training")
    p.add_argument("--scene-profile", default="tiny", help="scene render profile (default: tiny)")
    p.add_argument("--train-profile", default="tiny", help="3DGS training profile (default: tiny)")
    p.add_argument("--steps", type=int, default=2000, help="VAE optimiser steps (default: 2000)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    scenes = args.scenes or list_scenes()
    held = [s for s in scenes if s in args.holdout]
    train = [s for s in scenes if s not in args.holdout]
    if len(held) < 2 or not train:
        raise SystemExit(f"need at least two held-out scenes and one training scene, got held out {held}, "
                         f"training {train}")
    start = time.perf_counter()
    times = {}
    for name in scenes:
        t0 = time.perf_counter()
        scene = make_scene(name, profile=args.scene_profile, seed=args.seed)
        t1 = time.perf_counter()
        run = args.runs / name
        if not (run / "lineage.npz").is_file():
            code = gvae(["train", str(scene), "--out", str(run), "--profile", args.train_profile,
                         "--seed", str(args.seed), "--quiet"])
            if code:
                return code
        times[name] = (t1 - t0, time.perf_counter() - t1)
        print(f"[train-model] {name}: scene {times[name][0]:.0f} s, 3DGS {times[name][1]:.0f} s", flush=True)
    t0 = time.perf_counter()
    code = gvae(["fit-vae", *[str(args.runs / s) for s in train], "--holdout", *[str(args.runs / s) for s in held],
                 "--out", str(args.out), "--steps", str(args.steps), "--seed", str(args.seed)])
    fit_s = time.perf_counter() - t0
    total = time.perf_counter() - start
    print(f"[train-model] scenes {sum(a for a, _ in times.values()):.0f} s, 3DGS runs "
          f"{sum(b for _, b in times.values()):.0f} s, VAE fit {fit_s:.0f} s; total {total / 60:.1f} min "
          f"(trained on {', '.join(train)}; held out {', '.join(held)})")
    return code


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    raise SystemExit(main())
