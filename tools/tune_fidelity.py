"""Choose refine's fidelity tolerance on the validation scenes (how `DEFAULT_TOLERANCES` in
gvae_core/fidelity.py were chosen).

For each validation (scene, seed) of the quick protocol (training runs cached and shared with
`make report`): the training-resolution cloud; with `--method vae`, its Hessian scores as the
experiment computes them and Ours-∇² +1 and +2 without the check; with `--method detail`, the
detail model's +1 (every Gaussian); then the check `refine` makes (its default views) at each
tolerance, applied to those same results; PSNR at 1x and 2x (the protocol's render) and weighted
accuracy against the unrefined cloud. One JSON line per pair, then a table.

    python tools/tune_fidelity.py --method vae --out build/fidelity.jsonl   # about 10 min on 2 cores
"""

from __future__ import annotations

import argparse
import json

import torch

from gvae_core.experiment import PROTOCOLS, Evaluator, hessian_cameras, prepare_scene
from gvae_core.hessian import hessian_scores
from gvae_core.detail import load_detail
from gvae_core.refinement import FidelityCheck, refine, refine_steps
from gvae_core.rendering import RenderSettings
from gvae_core.scenes import SPLITS
from gvae_core.vae import load_default_model

TOLERANCES = {"vae": (0.0025, 0.005, 0.01, 0.02, 0.04), "detail": (0.01, 0.02, 0.04, 0.08)}


def pair(name: str, seed: int, model, protocol, method: str) -> dict:
    run = prepare_scene(name, protocol, seed=seed)
    evaluate = Evaluator(run)
    base = run.stage_cloud(protocol.train_stage)
    row = {"scene": name, "seed": seed, "base": evaluate(base, scales=("1x", "2x"))}
    lineage = run.lineage(protocol.train_stage + 1)
    if method == "vae":
        settings = RenderSettings(antialias=protocol.antialias)
        cams = hessian_cameras(run, protocol.hessian_views)
        scores = hessian_scores(base, cams, views=0, render_settings=settings).numpy()
        results = refine_steps(base, steps=2, budget=protocol.budget, model=model, scores=scores, seed=seed,
                               lineage=lineage, fidelity=None)
    else:
        results = [refine(base, model=model, lineage=lineage, fidelity=None)]
    checks = {t: FidelityCheck.around(base, None, t) for t in TOLERANCES[method]}  # as refine(..., cameras=None)
    for k, r in enumerate(results, 1):
        row[f"raw{k}"] = evaluate(r.cloud, scales=("1x", "2x"))
        for t in TOLERANCES[method]:
            g = checks[t](r)
            row[f"{t}/{k}"] = {**evaluate(g.cloud, scales=("1x", "2x")), "reverted": len(g.reverted),
                               "selected": len(g.selected), "added": len(g.added)}
    return row


def table(rows: list[dict], method: str) -> list[str]:
    lines = ["| tolerance | step | mean PSNR 2x change dB | worst pair dB | lineages kept | weighted acc. % |",
             "|---|---|---|---|---|---|"]
    for t in ("raw",) + TOLERANCES[method]:
        for k in (1, 2) if method == "vae" else (1,):
            key = f"raw{k}" if t == "raw" else f"{t}/{k}"
            d = [r[key]["psnr_2x"] - r["base"]["psnr_2x"] for r in rows]
            acc = [100 * (r[key]["weighted_accuracy"] / r["base"]["weighted_accuracy"] - 1) for r in rows]
            if t == "raw":
                kept = "all"
            else:
                total = sum(r[key]["selected"] for r in rows)
                kept = f"{sum(r[key]['selected'] - r[key]['reverted'] for r in rows) / total:.1%}"
            lines.append(f"| {'none' if t == 'raw' else t} | +{k} | {sum(d) / len(d):+.3f} | {min(d):+.3f} | "
                         f"{kept} | {sum(acc) / len(acc):+.1f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="*", default=list(SPLITS["validation"]))
    parser.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    parser.add_argument("--method", choices=("detail", "vae"), default="detail")
    parser.add_argument("--model", default=None, help="model directory (default: the bundled one)")
    parser.add_argument("--out", default=None, help="JSON lines file")
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_detail(args.model) if args.method == "detail" else load_default_model()
    protocol = PROTOCOLS["quick"]
    rows = []
    for name in args.scenes:
        for seed in args.seeds:
            rows.append(pair(name, seed, model, protocol, args.method))
            print(json.dumps(rows[-1]), flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(json.dumps(rows[-1]) + "\n")
    print("\n".join(table(rows, args.method)))


if __name__ == "__main__":
    main()
