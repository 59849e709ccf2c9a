"""Refinement quality on the held-out benchmark scenes, the paper's protocol (`gvae_core.experiment`,
the same run as `gvae report`): Chamfer distance to the ground-truth mesh and PSNR at 2x the
training resolution for the 3DGS baselines (training resolution; real 1.5x and 2x images), Ours
and Ours-∇² at +1..+4, and the random and plain-split controls at Ours-∇²'s budget; with the
time each refinement took. `--quick`: one scene, two steps."""

from __future__ import annotations

import dataclasses
import time

from ..experiment import PROTOCOLS, run_experiment
from ..report import ablation_table, paper_table


def run(args) -> None:
    p = PROTOCOLS["quick"]
    if getattr(args, "quick", False):
        p = dataclasses.replace(p, scenes=p.scenes[:1], steps=2, sweep=())
    t0 = time.perf_counter()
    doc = run_experiment(p, say=lambda msg: None)
    print(f"protocol {p.name}: scenes {', '.join(p.scenes)} (model trained on "
          f"{', '.join(doc['model']['train_scenes']) or '?'}), {time.perf_counter() - t0:.0f} s in all")
    print("\nChamfer distance (lower is better); % = Ours-∇² against 3DGS at the training resolution")
    print("\n".join(paper_table(doc, "chamfer", 5, True)))
    print("\nPSNR at 2x the training resolution (dB, higher is better)")
    print("\n".join(paper_table(doc, "psnr_2x", 2, False)))
    print("\nMean change against 3DGS 1x (refine ms: model steps and assembly, Hessian scoring apart)")
    print("\n".join(ablation_table(doc)))
