"""`gvae train CAPTURE --out RUN_DIR`: progressive 3DGS training with lineage tracking (the core's
`train.train_capture`: structure from motion first for a folder of photos), and
`gvae train RUN_DIR --more N`: a finished stage trained N more iterations. The training flags are
made from `TrainConfig`'s fields (`cli.fields`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from . import DEVICE_HELP
from .fields import add_fields, field_values
from .sfm import add_sfm_arguments, sfm_options

#: The fields with a flag among the main options; the others are under "more training settings".
MAIN_FIELDS = ("iterations", "max_minutes", "validation_views", "test_every", "sh_degree", "background", "init",
               "init_count", "max_gaussians", "gaussians_per_pixel", "seed", "antialias")


def register(subparsers) -> None:
    from ..train.config import PROFILES, TrainConfig

    p = subparsers.add_parser(
        "train", help="train 3DGS coarse-to-fine on a capture (COLMAP, transforms.json, NeRF-Synthetic) or photos",
        description="Train 3D Gaussian Splatting over increasing resolutions from a capture: a COLMAP capture "
                    "(sparse/0 + images/, binary or text; radial and OpenCV lenses undistorted on load), a "
                    "transforms.json of instant-ngp or nerfstudio (intrinsics and distortion), or a NeRF-Synthetic "
                    "folder; or a folder of photos, whose cameras structure from motion finds first (gvae sfm). A "
                    "capture with poses and no points gets its points by triangulation with those poses. Writes "
                    "stage_<s>.ply (with gvae_id / gvae_parent, the anti-aliasing size of its "
                    "training cameras and the background it was trained over), lineage.npz, log.json and run.json "
                    "into --out; an interrupted run resumes after its last finished stage. With --more N, SCENE is "
                    "a finished run: its last stage is trained N more iterations (no densification). A default "
                    "below says a profile's value where the profile changes it.")
    p.add_argument("scene", type=Path, metavar="CAPTURE",
                   help="the capture folder (or its COLMAP model, or a transforms*.json), or a folder of photos "
                        "(structure from motion makes its cameras first: gvae sfm); with --more, a run folder")
    p.add_argument("--out", type=Path, help="run directory to write (created if needed; required but with --more: "
                   "no default)")
    p.add_argument("--more", type=int, metavar="N",
                   help="train the finished run CAPTURE's last stage N more iterations; writes "
                        "stage_<s>_more_<N>.ply and more.json there (default: off)")
    p.add_argument("--profile", choices=tuple(PROFILES), default="default",
                   help="preset of the fields below (default: %(default)s)")
    size = p.add_mutually_exclusive_group()
    add_fields(p, TrainConfig, ("resolutions",), profiles=PROFILES, groups={"resolutions": size})
    size.add_argument("--image-height", type=int, metavar="H",
                      help="the last stage's image height; earlier stages in the profile's proportions (default: the "
                           "profile's heights)")
    size.add_argument("--downscale", type=float, metavar="F",
                      help="the last stage at the stored images' size divided by F (floor), e.g. 4 for 1/4; earlier "
                           "stages in the profile's proportions (default: the profile's heights)")
    add_fields(p, TrainConfig, MAIN_FIELDS, profiles=PROFILES)
    p.add_argument("--init-points", type=Path, metavar="FILE",
                   help="initial points instead of --init's: .npy (N,3) or (N,6 with RGB), or a PLY (default: none)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; 1 is "
                   "often fastest on a busy machine)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.add_argument("--restart", action="store_true", help="start over instead of resuming")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    more = p.add_argument_group("more training settings (the reference 3DGS's values unless said)")
    add_fields(more, TrainConfig, [f for f in _all_fields(TrainConfig) if f not in MAIN_FIELDS + ("resolutions",)],
               profiles=PROFILES)
    add_sfm_arguments(p)
    p.set_defaults(func=run)


def _all_fields(cls) -> list[str]:
    import dataclasses

    return [f.name for f in dataclasses.fields(cls)]


def _num(x) -> float:
    return math.nan if x is None else x


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


def config_of(args: argparse.Namespace):
    """The `TrainConfig` the options ask for (`train.configure`)."""
    from ..train.config import TrainConfig, configure

    values, none = field_values(args, TrainConfig)
    resolutions, iterations = values.pop("resolutions", None), values.pop("iterations", None)
    return configure(args.profile, resolutions=resolutions, image_height=args.image_height, iterations=iterations,
                     none=none, **values)


def run(args: argparse.Namespace) -> int:
    if args.more is not None:
        return _run_more(args)
    if args.out is None:
        raise ValueError("--out is required (the run directory to write)")
    from ..train import train_capture

    config = config_of(args)
    points = _load_points(args.init_points) if args.init_points else None
    done = train_capture(args.scene, config, args.out, downscale=args.downscale, sfm=sfm_options(args),
                         init_points=points, resume=not args.restart, progress=not args.quiet,
                         threads=args.threads, device=args.device)
    _print_log(done.result.log)
    print(f"wrote {done.result.out_dir}")
    return 0


def _print_log(log: list[dict]) -> None:
    print(f"{'stage':>5} {'res':>5} {'iters':>6} {'s/it':>7} {'gaussians':>9} {'train dB':>8} {'val dB':>7} "
          f"{'test dB':>8} {'test SSIM':>9} {'peak MB':>8}")
    for e in log:
        test, ssim, val = e["test_psnr"], e.get("test_ssim"), e.get("validation_psnr")
        print(f"{e['stage']:>5} {e['resolution']:>5} {e['iterations']:>6} {e['seconds_per_iteration']:>7.3f} "
              f"{e['n_gaussians']:>9} {e['train_psnr']:>8.2f} {_num(val):>7.2f} {_num(test):>8.2f} {_num(ssim):>9.4f} "
              f"{e['peak_rss_mb']:>8.0f}")
    last = log[-1] if log else {}
    if "stopped" in last:
        print(f"last stage: {last['stopped']} (kept the state of step {last['best_step']})")


def _run_more(args: argparse.Namespace) -> int:
    from ..train import train_more

    if args.more <= 0:
        raise ValueError(f"--more needs a positive number of iterations, got {args.more}")
    result = train_more(args.scene, args.more, progress=not args.quiet, threads=args.threads, device=args.device)
    e = result.entry
    test = "n/a" if e["test_psnr"] is None else f"{e['test_psnr']:.2f} dB, SSIM {e['test_ssim']:.4f}"
    if e["test_psnr"] is not None and e.get("test_psnr_before") is not None:
        test = f"{e['test_psnr_before']:.2f} -> {test} (SSIM {e['test_ssim_before']:.4f} before)"
    print(f"stage {e['stage']} at {e['resolution']} px, {e['more']} more iterations in {e['seconds']:.1f} s: "
          f"{e['n_gaussians']} Gaussians, training views {e['train_psnr']:.2f} dB, held-out views {test}")
    print(f"wrote {result.path}")
    return 0
