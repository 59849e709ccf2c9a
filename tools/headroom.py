"""The headroom of refinement on the validation scenes: how much an oracle gains at 2x when it
fits, per parameter group, every Gaussian's changes per octave to the real 1.5x and 2x training
views (count unchanged; and once more after the lineage VAEs have added their children), beside
linear lineage extrapolation with its factor chosen on the training scenes.

Usage: python tools/headroom.py [--protocol quick] [--scenes chair tableware] [--seeds 0 1 2]
                                [--steps 300] [--out headroom.json]
Prints one row per (group, scene, seed) and the means; a long run: start it in the background with
its log on disk.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from gvae_core.atomic import atomic_write_text
from gvae_core.controls import extrapolation_control
from gvae_core.experiment import PROTOCOLS, Evaluator, oracle, prepare_scenes, tune_knob
from gvae_core.refinement import refine_steps
from gvae_core.scenes import SPLITS
from gvae_core.vae import load_default_model

GROUPS = {"log-scales + opacity": ("scales", "opacities"), "geometry": ("means", "quats", "scales"),
          "appearance": ("sh_dc", "sh_rest", "opacities"),
          "everything": ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest")}
CHILDREN = "everything, with the lineage VAEs' children (Ours-∇² +1)"


def _candidates(run, base, factor: float, groups, steps, seed: int):
    """(method, cloud, seconds) for the extrapolation and each oracle group of one pair."""
    lineage = run.lineage(run.protocol.train_stage + 1)
    yield f"extrapolation x{factor:g}", extrapolation_control(base, lineage, factor), 0.0
    for group in groups:
        if group == CHILDREN:
            (grown,) = refine_steps(base, steps=1, budget="auto", model=load_default_model(), lineage=lineage,
                                    seed=seed, every_step=False, fidelity=None)
            cloud, seconds = oracle(run, grown.cloud, GROUPS["everything"], steps=steps)
        else:
            cloud, seconds = oracle(run, base, GROUPS[group], steps=steps)
        yield f"oracle: {group}", cloud, seconds


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tools/headroom.py", description=__doc__.splitlines()[0])
    p.add_argument("--protocol", default="quick", choices=list(PROTOCOLS))
    p.add_argument("--scenes", nargs="*", default=list(SPLITS["validation"]))
    p.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=None, help="oracle optimiser steps (default: the protocol's)")
    p.add_argument("--groups", nargs="*", default=[*GROUPS, CHILDREN])
    p.add_argument("--data-runs", action="store_true",
                   help="evaluate on runs stopped at the training resolution (Protocol.data: cheaper; the real "
                   "higher-resolution images are only needed as views)")
    p.add_argument("--out", type=Path, default=None, help="write every row as JSON here too")
    args = p.parse_args(argv)
    protocol = PROTOCOLS[args.protocol]
    if set(args.scenes) & set(SPLITS["test"]):
        raise SystemExit("the test scenes are looked at only for the report; choose validation scenes")
    t_start = time.perf_counter()
    knob_runs = prepare_scenes(protocol.knob_scenes, protocol, say=lambda m: print(m, flush=True))
    factor = tune_knob(list(knob_runs.values()), protocol.extrapolation_factors, control=extrapolation_control,
                       with_lineage=True)
    print(f"extrapolation factor on {', '.join(factor['scenes'])}: x{factor['factor']:g} "
          f"({json.dumps({k: round(v, 3) for k, v in factor['psnr_2x'].items()})})", flush=True)
    rows = []
    for seed in args.seeds:
        runs = prepare_scenes(args.scenes, protocol.data() if args.data_runs else protocol, seed=seed,
                              say=lambda m: print(m, flush=True))
        for name, run in runs.items():
            evaluate = Evaluator(run)
            k = protocol.train_stage
            base = run.stage_cloud(k)
            ref = evaluate(base)
            for method, cloud, seconds in _candidates(run, base, factor["factor"], args.groups, args.steps, seed):
                r = evaluate(cloud)
                row = {"scene": name, "seed": seed, "method": method, "seconds": round(seconds, 1),
                       **{f"d_psnr_{s}": r[f"psnr_{s}"] - ref[f"psnr_{s}"] for s in ("1x", "1.5x", "2x")},
                       "d_ssim_2x": r["ssim_2x"] - ref["ssim_2x"], "n_gaussians": r["n_gaussians"]}
                rows.append(row)
                print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    print("\n| method | PSNR 2x dB | PSNR 1.5x dB | PSNR 1x dB | SSIM 2x | pairs |\n|---|---|---|---|---|---|")
    for method in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == method]
        cells = [f"{np.mean([r[k] for r in sel]):+.{4 if 'ssim' in k else 2}f}"
                 for k in ("d_psnr_2x", "d_psnr_1.5x", "d_psnr_1x", "d_ssim_2x")]
        print(f"| {method} | " + " | ".join(cells) + f" | {len(sel)} |")
    print(f"\n{(time.perf_counter() - t_start) / 60:.1f} min")
    if args.out is not None:
        atomic_write_text(args.out, json.dumps({"extrapolation": factor, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
