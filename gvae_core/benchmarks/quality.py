"""Refinement quality on the test scenes (`gvae_core.experiment`, the same run as `gvae report
--profile quick`): Ours-∇² against the best alternative at the same Gaussian count, and every
method's change against the unrefined cloud, with the time the whole run took. `--quick`: one
scene, one seed."""

from __future__ import annotations

import dataclasses
import time

from ..experiment import PROTOCOLS, run_experiment
from ..report import Results, headline_table, methods_table


def run(args) -> None:
    p = PROTOCOLS["quick"]
    if getattr(args, "quick", False):
        p = dataclasses.replace(p, scenes=p.scenes[:1], seeds=p.seeds[:1], knob_scenes=p.knob_scenes[:1])
    t0 = time.perf_counter()
    doc = run_experiment(p, say=lambda msg: None)
    res = Results(doc, doc["split"])
    print(f"protocol {p.name}: scenes {', '.join(p.scenes)}, seeds {p.seeds} (model trained on "
          f"{', '.join(doc['model']['train_scenes']) or '?'}), {time.perf_counter() - t0:.0f} s in all")
    print("\nOurs-∇² against the best alternative at the same count (mean ± 95% interval over pairs)")
    print("\n".join(headline_table(res)))
    print("\nEvery method: change against the unrefined cloud")
    print("\n".join(methods_table(res)))
