"""`gvae report --profile quick|full|paper --out reports/`: run the experiment and write the report."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from . import DEVICE_HELP

#: `experiment.PROTOCOLS`' names (a test checks), so that `gvae --help` does not import torch.
PROFILES = ("quick", "full", "paper")


def register(subparsers) -> None:
    from ..scenes import SPLITS

    p = subparsers.add_parser(
        "report", help="run the experiment on the benchmark scenes and write the report",
        description="Make the benchmark scenes, train progressive 3DGS with lineage to the training resolution "
        "and with the real higher-resolution images for every seed, refine +1..+K (Ours, Ours-grad2, and the "
        "split, random and duplicate controls at Ours-grad2's count), evaluate (Chamfer, accuracy plain and "
        "weighted by opacity, PSNR/SSIM at 1x/1.5x/2x with the anti-aliasing filter and classic, NIQE) and "
        "write OUT/README.md, OUT/results.json and plots. Scenes and runs are cached ($GVAE_CACHE_DIR).")
    p.add_argument("--profile", choices=PROFILES, default="quick",
                   help="quick: the test scenes, 3 seeds, small sizes (about 80 min on 2 cores from nothing); "
                   "full: the benchmark profile (hours); paper: training at 400 px, for a GPU machine "
                   "(default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("reports"), help="report folder (default: %(default)s)")
    p.add_argument("--split", choices=list(SPLITS), default=None,
                   help="run the scenes of this split (default: the profile's, the test split); choices are "
                   "made on the validation split")
    p.add_argument("--scenes", nargs="*", default=None,
                   help="only these scenes (default: the --split's, else the profile's)")
    p.add_argument("--seeds", nargs="*", type=int, default=None, help="only these seeds (default: the profile's)")
    p.add_argument("--model", type=Path, default=None, help="model directory (default: the bundled one)")
    p.add_argument("--cache-dir", type=Path, default=None, help="scene and run cache (default: $GVAE_CACHE_DIR "
                   "or ~/.cache/gvae)")
    p.add_argument("--jobs", type=int, default=None,
                   help="runs processed at once, each in a process with one torch thread (default: one per core; "
                   "one with --device cuda)")
    p.add_argument("--device", default=None, help="where training and the scoring renders run: " + DEVICE_HELP)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..experiment import run_experiment
    from ..report import write_report
    from ..scenes import SPLITS

    t0 = time.perf_counter()
    scenes = args.scenes or (SPLITS[args.split] if args.split else None)
    doc = run_experiment(args.profile, model=args.model, scenes=scenes, seeds=args.seeds, cache=args.cache_dir,
                         jobs=args.jobs, device=args.device, say=lambda msg: print(msg, flush=True))
    command = "gvae report " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["report"] else \
        f"gvae report --profile {args.profile} --out {args.out}"
    path = write_report(doc, args.out, command=command)
    print(f"wrote {path} and {args.out / 'results.json'} in {(time.perf_counter() - t0) / 60:.1f} min")
    return 0
