"""`gvae train SCENE_DIR --out RUN_DIR`: progressive 3DGS training with lineage tracking."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from . import DEVICE_HELP


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train 3DGS coarse-to-fine on a NeRF-Synthetic scene, recording lineages",
        description="Train 3D Gaussian Splatting over increasing resolutions. Writes stage_<s>.ply "
                    "(with gvae_id / gvae_parent and the anti-aliasing size of its training cameras), "
                    "lineage.npz, log.json and run.json into --out; "
                    "an interrupted run resumes after its last finished stage.")
    p.add_argument("scene", type=Path, help="NeRF-Synthetic folder (transforms_train.json, images)")
    p.add_argument("--out", type=Path, required=True, help="run directory to write (created if needed)")
    p.add_argument("--profile", choices=("tiny", "default", "full"), default="default",
                   help="preset of resolutions, iterations and sizes (default: %(default)s)")
    p.add_argument("--resolutions", type=int, nargs="+", metavar="H",
                   help="training image heights, coarse to fine (default: the profile's: 100 150 200; tiny: 32 48 64; "
                   "full: 100 200 400 800)")
    p.add_argument("--iterations", type=int, nargs="+", metavar="N",
                   help="iterations per stage: one number for all stages or one per stage (default: the profile's: "
                   "600 400 400; tiny: 200 150 150; full: 7000 7000 7000 30000)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3),
                   help="largest SH degree (default: the profile's: 3; tiny: 1)")
    p.add_argument("--background", type=float, nargs=3, metavar=("R", "G", "B"),
                   help="background colour images are composited on (default: white)")
    p.add_argument("--init-points", type=Path, metavar="FILE",
                   help="initial points instead of --init's: .npy (N,3) or (N,6 with RGB), or a PLY (default: none)")
    p.add_argument("--init", choices=("random", "hull"),
                   help="random points in the scene bounds (the reference) or inside the visual hull of "
                        "the training masks (default: the profile's: hull; random with --profile full)")
    p.add_argument("--init-count", type=int, metavar="N",
                   help="number of initial points (default: the profile's: 10000; tiny: 2000; full: 100000)")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; 1 is "
                   "often fastest on a busy machine)")
    p.add_argument("--antialias", choices=("classic", "mip"),
                   help="classic (the reference 3DGS, default; stage PLYs get gvae_dilation_3D) or mip "
                   "(train with Mip-Splatting's 3D and 2D filters; stage PLYs get filter_3D)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.add_argument("--restart", action="store_true", help="start over instead of resuming")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _load_points(path: Path):
    import numpy as np

    if not path.is_file():
        raise FileNotFoundError(f"{path}: initial points file not found")
    if path.suffix.lower() == ".ply":
        from ..ply import read_ply

        return read_ply(path).means
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise ValueError(f"{path}: cannot read points ({exc})") from None


def run(args: argparse.Namespace) -> int:
    from ..train import TrainConfig, train_progressive

    overrides = dict(resolutions=tuple(args.resolutions) if args.resolutions else None,
                     sh_degree=args.sh_degree, seed=args.seed, init=args.init, init_count=args.init_count,
                     antialias=args.antialias,
                     background=tuple(args.background) if args.background else None)
    if args.iterations:
        n_stages = len(args.resolutions or TrainConfig.profile(args.profile).resolutions)
        its = args.iterations * n_stages if len(args.iterations) == 1 else args.iterations
        if len(its) != n_stages:
            raise ValueError(f"--iterations needs 1 or {n_stages} numbers, got {len(its)}")
        overrides["iterations"] = tuple(its)
    elif args.resolutions:
        base = TrainConfig.profile(args.profile).iterations
        overrides["iterations"] = (base[-1],) * len(args.resolutions) if len(base) != len(args.resolutions) else base
    config = TrainConfig.profile(args.profile, **overrides)
    points = _load_points(args.init_points) if args.init_points else None
    result = train_progressive(args.scene, config, out_dir=args.out, init_points=points,
                               resume=not args.restart, progress=not args.quiet,
                               threads=args.threads, device=args.device)
    print(f"{'stage':>5} {'res':>5} {'iters':>6} {'s/it':>7} {'gaussians':>9} {'train dB':>8} "
          f"{'test dB':>8} {'peak MB':>8}")
    for e in result.log:
        test = e["test_psnr"]
        print(f"{e['stage']:>5} {e['resolution']:>5} {e['iterations']:>6} {e['seconds_per_iteration']:>7.3f} "
              f"{e['n_gaussians']:>9} {e['train_psnr']:>8.2f} "
              f"{(test if test is not None else math.nan):>8.2f} {e['peak_rss_mb']:>8.0f}")
    print(f"wrote {result.out_dir}")
    return 0
