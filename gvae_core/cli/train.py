"""`gvae train CAPTURE --out RUN_DIR`: progressive 3DGS training with lineage tracking, and
`gvae train RUN_DIR --more N`: a finished stage trained N more iterations."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from . import DEVICE_HELP
from .sfm import add_sfm_arguments, prepare_capture

#: The default profile's iterations per stage and budget (said in --help without importing the trainer).
_DEFAULT_ITERATIONS = (300, 300, 1000)
_DEFAULT_PER_PIXEL = 1.0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train 3DGS coarse-to-fine on a capture (COLMAP, transforms.json, NeRF-Synthetic)",
        description="Train 3D Gaussian Splatting over increasing resolutions from a capture: a COLMAP capture "
                    "(sparse/0 + images/, binary or text; radial and OpenCV lenses undistorted on load), a "
                    "transforms.json of instant-ngp or nerfstudio (intrinsics and distortion), or a NeRF-Synthetic "
                    "folder; or a folder of photos, whose cameras structure from motion finds first (gvae sfm). A "
                    "capture with poses and no points gets its points by triangulation with those poses. Writes "
                    "stage_<s>.ply (with gvae_id / gvae_parent, the anti-aliasing size of its "
                    "training cameras and the background it was trained over), lineage.npz, log.json and run.json "
                    "into --out; an interrupted run resumes after its last finished stage. With --more N, SCENE is "
                    "a finished run: its last stage is trained N more iterations (no densification).")
    p.add_argument("scene", type=Path, metavar="CAPTURE",
                   help="the capture folder (or its COLMAP model, or a transforms*.json), or a folder of photos "
                        "(structure from motion makes its cameras first: gvae sfm); with --more, a run folder")
    p.add_argument("--out", type=Path, help="run directory to write (created if needed; required, but with --more: "
                   "no default)")
    p.add_argument("--more", type=int, metavar="N",
                   help="train the finished run CAPTURE's last stage N more iterations; writes "
                        "stage_<s>_more_<N>.ply and more.json there (default: off)")
    p.add_argument("--profile", choices=("tiny", "default", "full", "legacy"), default="default",
                   help="preset of resolutions, iterations and sizes; legacy: the schedule before the last stage "
                        "trained until convergence (600 400 400 iterations, no validation photos, no budget) "
                        "(default: %(default)s)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--resolutions", type=int, nargs="+", metavar="H",
                      help="training image heights, coarse to fine (default: the profile's: 100 150 200; tiny: "
                           "32 48 64; full: 100 200 400 800)")
    size.add_argument("--image-height", type=int, metavar="H",
                      help="the last stage's image height; earlier stages in the profile's proportions "
                           "(default: the profile's)")
    size.add_argument("--downscale", type=float, metavar="F",
                      help="the last stage at the stored images' size divided by F (floor), e.g. 4 for 1/4; earlier "
                           "stages in the profile's proportions (default: the profile's heights)")
    p.add_argument("--iterations", type=int, nargs="+", metavar="N",
                   help="iterations per stage, fixed: one number for all stages or one per stage (default: the "
                        "profile's, the last stage then training on until the validation photos stop improving: "
                        f"{' '.join(map(str, _DEFAULT_ITERATIONS))}; tiny: 200 150 150, fixed; full: 7000 7000 7000 "
                        "30000)")
    p.add_argument("--minutes", type=float, metavar="M",
                   help="time budget of the whole run: the last stage stops when it is spent (once its densification "
                        "is done), and the log says so (default: none; the validation photos decide)")
    p.add_argument("--validation-views", type=int, metavar="N",
                   help="training photos set aside (never trained on, at most one in eight) to judge when training "
                        "stops helping (default: the profile's: 8; 0: none, the iterations are then fixed)")
    p.add_argument("--test-every", type=int, metavar="N",
                   help="hold out every N-th image (sorted by name) as a test view, the LLFF / Mip-NeRF 360 "
                        "convention being 8 (default: none; a NeRF-Synthetic folder's own test split)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3),
                   help="largest SH degree (default: the profile's: 3; tiny: 1)")
    p.add_argument("--background", type=float, nargs=3, metavar=("R", "G", "B"),
                   help="background colour images are composited on and the cloud is trained over, stored with "
                        "it (default: white, 1 1 1)")
    p.add_argument("--init-points", type=Path, metavar="FILE",
                   help="initial points instead of --init's: .npy (N,3) or (N,6 with RGB), or a PLY (default: none)")
    p.add_argument("--init", choices=("auto", "sfm", "hull", "random"),
                   help="where training starts: sfm (the capture's SfM points, with random points where they leave "
                        "pixels uncovered), hull (inside the visual hull of transparent images' masks), random "
                        "(random points along the training rays) or auto: sfm, else hull for images with "
                        "transparency, else random (default: the profile's: auto; random with --profile full)")
    p.add_argument("--init-count", type=int, metavar="N",
                   help="number of random initial points (default: the profile's: 10000; tiny: 2000; full: 100000)")
    p.add_argument("--max-gaussians", type=int, metavar="N",
                   help="cap on the number of Gaussians (default: the profile's: none but what memory allows; tiny: "
                        "10000)")
    p.add_argument("--gaussians-per-pixel", type=float, metavar="F",
                   help="a budget of F Gaussians per pixel of one training photo in each stage, 0 for none "
                        f"(default: the profile's: {_DEFAULT_PER_PIXEL:g})")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any other field of gvae_core.train.TrainConfig, VALUE in JSON (repeatable), e.g. --set "
                        "patience=1000 (default: the profile's)")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice; 1 is "
                   "often fastest on a busy machine)")
    p.add_argument("--antialias", choices=("classic", "mip"),
                   help="classic (the reference 3DGS, default; stage PLYs get gvae_dilation_3D) or mip "
                   "(train with Mip-Splatting's 3D and 2D filters; stage PLYs get filter_3D)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.add_argument("--restart", action="store_true", help="start over instead of resuming (default: resume)")
    p.add_argument("--quiet", action="store_true", help="no progress bar (default: progress shown)")
    add_sfm_arguments(p)
    p.set_defaults(func=run)


def _fields(items: list[str]) -> dict:
    """--set FIELD=VALUE items as TrainConfig overrides (VALUE in JSON)."""
    import json

    from ..train import TrainConfig

    names = {f.name for f in dataclasses.fields(TrainConfig)}
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in names or not value:
            raise ValueError(f"--set {item}: expected FIELD=VALUE, FIELD one of TrainConfig's: "
                             f"{', '.join(sorted(names))}")
        try:
            out[name] = json.loads(value)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--set {item}: the value is not JSON ({exc})") from None
    return out


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


def _resolutions(args: argparse.Namespace, profile: tuple[int, ...]) -> tuple[int, ...] | None:
    """The stage heights the options ask for (None: the profile's)."""
    if args.resolutions:
        return tuple(args.resolutions)
    if args.image_height is None and args.downscale is None:
        return None
    height = args.image_height
    if height is None:
        from ..capture import read_capture

        if not args.downscale >= 1:
            raise ValueError(f"--downscale must be 1 or more, got {args.downscale}")
        height = int(read_capture(args.scene, images=False).cameras[0].height / args.downscale)
    return stage_heights(height, profile)


def stage_heights(height: int, profile: tuple[int, ...]) -> tuple[int, ...]:
    """The stage heights of `--image-height H`: the last stage at `height`, the earlier ones in the
    profile's proportions (Blender's New from Photos asks for the same)."""
    if height <= 0:
        raise ValueError(f"the last stage's image height must be positive, got {height}")
    return tuple(max(1, round(height * r / profile[-1])) for r in profile)


def run(args: argparse.Namespace) -> int:
    if args.more is not None:
        return _run_more(args)
    if args.out is None:
        raise ValueError("--out is required (the run directory to write)")
    from ..train import TrainConfig, train_progressive

    # photos -> cameras (SfM); poses without points -> points (triangulation), where the start uses them
    prepare_capture(args.scene, args, points=args.init_points is None and args.init in (None, "auto", "sfm"))
    base = TrainConfig.profile(args.profile)
    resolutions = _resolutions(args, base.resolutions)
    overrides = dict(resolutions=resolutions, sh_degree=args.sh_degree, seed=args.seed, init=args.init,
                     init_count=args.init_count, antialias=args.antialias, test_every=args.test_every,
                     background=tuple(args.background) if args.background else None, max_minutes=args.minutes,
                     validation_views=args.validation_views, gaussians_per_pixel=args.gaussians_per_pixel or None)
    if args.max_gaussians is not None:
        overrides["max_gaussians"] = args.max_gaussians
    overrides.update(_fields(args.set))
    if args.iterations:
        n_stages = len(resolutions or base.resolutions)
        its = args.iterations * n_stages if len(args.iterations) == 1 else args.iterations
        if len(its) != n_stages:
            raise ValueError(f"--iterations needs 1 or {n_stages} numbers, got {len(its)}")
        overrides["iterations"] = tuple(its)
        overrides["converge"] = False  # the count the user asked for
    elif resolutions:
        its = base.iterations
        overrides["iterations"] = (its[-1],) * len(resolutions) if len(its) != len(resolutions) else its
    config = TrainConfig.profile(args.profile, **overrides)
    if args.gaussians_per_pixel == 0:
        config = dataclasses.replace(config, gaussians_per_pixel=None)
    points = _load_points(args.init_points) if args.init_points else None
    result = train_progressive(args.scene, config, out_dir=args.out, init_points=points,
                               resume=not args.restart, progress=not args.quiet,
                               threads=args.threads, device=args.device)
    print(f"{'stage':>5} {'res':>5} {'iters':>6} {'s/it':>7} {'gaussians':>9} {'train dB':>8} {'val dB':>7} "
          f"{'test dB':>8} {'test SSIM':>9} {'peak MB':>8}")
    for e in result.log:
        test, ssim, val = e["test_psnr"], e.get("test_ssim"), e.get("validation_psnr")
        print(f"{e['stage']:>5} {e['resolution']:>5} {e['iterations']:>6} {e['seconds_per_iteration']:>7.3f} "
              f"{e['n_gaussians']:>9} {e['train_psnr']:>8.2f} {_num(val):>7.2f} {_num(test):>8.2f} {_num(ssim):>9.4f} "
              f"{e['peak_rss_mb']:>8.0f}")
    last = result.log[-1] if result.log else {}
    if "stopped" in last:
        print(f"last stage: {last['stopped']} (kept the state of step {last['best_step']})")
    print(f"wrote {result.out_dir}")
    return 0


def _run_more(args: argparse.Namespace) -> int:
    from ..train import train_more

    if args.more <= 0:
        raise ValueError(f"--more needs a positive number of iterations, got {args.more}")
    result = train_more(args.scene, args.more, progress=not args.quiet, threads=args.threads, device=args.device)
    e = result.entry
    test = "n/a" if e["test_psnr"] is None else f"{e['test_psnr']:.2f} dB, SSIM {e['test_ssim']:.4f}"
    print(f"stage {e['stage']} at {e['resolution']} px, {e['more']} more iterations in {e['seconds']:.1f} s: "
          f"{e['n_gaussians']} Gaussians, training views {e['train_psnr']:.2f} dB, held-out views {test}")
    print(f"wrote {result.path}")
    return 0
