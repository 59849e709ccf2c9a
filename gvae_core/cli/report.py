"""`gvae report --profile quick|full --out reports/`: run the paper's experiment and write the report."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def register(subparsers) -> None:
    from ..experiment import PROTOCOLS

    p = subparsers.add_parser(
        "report", help="run the paper's experiment on the benchmark scenes and write the report",
        description="Make the benchmark scenes, train progressive 3DGS with lineage to the training resolution "
        "and with the real higher-resolution images, refine +1..+4 (Ours, Ours-grad2, random and plain-split "
        "controls, a Hessian budget sweep), evaluate (Chamfer, PSNR/SSIM at 1x/1.5x/2x, NIQE) and write "
        "OUT/README.md, OUT/results.json and plots. Scenes and training runs are cached ($GVAE_CACHE_DIR).")
    p.add_argument("--profile", choices=list(PROTOCOLS), default="quick",
                   help="quick: the two held-out scenes at small sizes (about 6 min on 2 cores from nothing); "
                   "full: all six scenes at the benchmark profile (hours)")
    p.add_argument("--out", type=Path, default=Path("reports"), help="report folder (default: %(default)s)")
    p.add_argument("--scenes", nargs="*", default=None, help="only these scenes (default: the profile's)")
    p.add_argument("--model", type=Path, default=None, help="model directory (default: the bundled one)")
    p.add_argument("--cache-dir", type=Path, default=None, help="scene and run cache (default: $GVAE_CACHE_DIR "
                   "or ~/.cache/gvae)")
    p.add_argument("--jobs", type=int, default=None,
                   help="scenes processed at once, each in a process with one torch thread (default: one per core)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..experiment import run_experiment
    from ..report import write_report

    t0 = time.perf_counter()
    doc = run_experiment(args.profile, model=args.model, scenes=args.scenes, cache=args.cache_dir,
                         jobs=args.jobs, say=lambda msg: print(msg, flush=True))
    command = "gvae report " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["report"] else \
        f"gvae report --profile {args.profile} --out {args.out}"
    path = write_report(doc, args.out, command=command)
    print(f"wrote {path} and {args.out / 'results.json'} in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0
