"""`gvae compact IN OUT --keep FRACTION | --count N | --tolerance DB`: fewer Gaussians, the picture kept."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS
from . import progress_lines
from .sfm import prepare_capture

#: (`compaction.AUTO_DISTILL`, `AUTO_DISTILL_MAX`, `AUTO_DISTILL_SECONDS`, `SET_ASIDE_EVERY`,
#: `PHOTOS_PRUNE_FROM`, `PRUNE_FROM_ITERATIONS` and `DEFAULT_ITERATIONS`, without importing torch for --help.)
AUTO_DISTILL, AUTO_DISTILL_MAX, AUTO_DISTILL_SECONDS, SET_ASIDE_EVERY, PHOTOS_PRUNE_FROM = 1000, 50_000, 180.0, 8, 0.3
PRUNE_FROM_ITERATIONS, DEFAULT_ITERATIONS = 1000, 3000


def register(subparsers) -> None:
    c = subparsers.add_parser(
        "compact", help="remove the Gaussians a splat's picture does not need",
        description="Score every Gaussian by how much the picture depends on it (the exact Gauss-Newton block of "
        "position and log-scale over a few views, as PUP 3D-GS), drop what no view sees and the lowest-scoring "
        "tenth, merge the rest pairwise, cheapest first, down to the count asked for; with the capture's images "
        "(--images), or against the input's own renders (--distill), in rounds, each followed by fine-tuning with "
        "the project's trainer. The output keeps the input's SH degree, extra properties and anti-aliasing sizes; "
        "untouched Gaussians keep their values.")
    c.add_argument("input", type=Path, metavar="IN",
                   help="a splat file: 3DGS or compressed PLY, .splat, .spz, .sog (what `gvae info` reads)")
    c.add_argument("output", type=Path, metavar="OUT",
                   help="where the compacted cloud goes, in the format its name asks for (.ply, .compressed.ply, "
                   ".spz, .splat, .sog, meta.json)")
    target = c.add_mutually_exclusive_group(required=True)
    target.add_argument("--keep", metavar="FRACTION", help="fraction of the Gaussians to keep, in (0, 1] (0.3 or 30%%)")
    target.add_argument("--count", type=int, metavar="N", help="number of Gaussians to keep")
    target.add_argument("--tolerance", type=float, metavar="DB",
                        help="keep as few as hold the picture at the training resolution, seen from the scoring views, "
                        "at or above DB of PSNR against the input's own render (for example 40)")
    c.add_argument("--cameras", type=Path, default=None, metavar="PATH",
                   help="the capture's cameras: a transforms*.json file, a COLMAP sparse model or the reference "
                   "3DGS's cameras.json (--views of them score; none of what any of them sees is dropped as "
                   "unseen); default: the training cameras found beside IN (the reference 3DGS's MODEL/cameras.json "
                   "two folders up, a gvae train run's capture) when they see it, else views placed around the "
                   "cloud, all around an object, inside a scene that surrounds its centre")
    c.add_argument("--placed-views", action="store_true",
                   help="score from views placed around the cloud even where training cameras are found beside IN")
    c.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                   help="scoring views (of the capture's cameras, spread out; 0: all of them; with --images "
                   "LightGaussian's score counts every camera) (default: %(default)s)")
    c.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION,
                   help="scoring view height in pixels (default: %(default)s)")
    c.add_argument("--score", default=None, choices=("hessian", "lightgaussian", "opacity", "random"),
                   help=f"what ranks the Gaussians (default: hessian; with --images keeping {PHOTOS_PRUNE_FROM:.0%}% "
                   "or more, lightgaussian with --removal prune, what the images set aside chose on the project's "
                   "capture; the others are baselines)")
    c.add_argument("--removal", default=None, choices=("merge", "prune"),
                   help="merge Gaussians pairwise, after dropping the lowest-scoring tenth, or drop the lowest "
                   f"scores only (default: merge; with --images keeping {PHOTOS_PRUNE_FROM:.0%}% or more, prune)")
    c.add_argument("--images", type=Path, default=None, metavar="DATASET",
                   help="the capture's training images (a COLMAP capture, a transforms.json with its images or a "
                   "NeRF-Synthetic folder: what gvae train reads): compact in rounds, fine-tuning after each "
                   "(default: none; see --distill)")
    c.add_argument("--test-every", type=int, default=None, metavar="N",
                   help="with --cameras/--images: every N-th image of the capture (by name) was held out from "
                   "training (gvae train --test-every N): not used here either (default: none)")
    c.add_argument("--distill", type=_distill, default="auto", metavar="ITERATIONS",
                   help="without images: fine-tune at most this many iterations a round against the input's own "
                   "renders (32 views of --cameras, else placed around the cloud, at the training resolution; 8 more "
                   "set aside judge when to stop); 0: score, drop and merge only (default: auto, at most "
                   f"{AUTO_DISTILL} iterations for a cloud of up to {AUTO_DISTILL_MAX:,} Gaussians, stopped at the "
                   f"first check after {AUTO_DISTILL_SECONDS:.0f} s, none for a larger one)")
    c.add_argument("--rounds", type=int, default=None,
                   help="removal and fine-tuning rounds with --images or --distill (default: 1)")
    c.add_argument("--iterations", type=int, default=None,
                   help=f"the most fine-tuning iterations a round with --images (default: {PRUNE_FROM_ITERATIONS} "
                   f"keeping {PHOTOS_PRUNE_FROM:.0%}% or more, {DEFAULT_ITERATIONS} below; PUP 3D-GS runs 5000); each "
                   "round stops sooner when the images set aside stop improving")
    c.add_argument("--no-plateau", dest="plateau", action="store_false",
                   help="with --images or --distill: set no images aside and run every iteration (default: every "
                   f"{SET_ASIDE_EVERY}th training image is set aside, never trained on, and each round stops when "
                   "their PSNR stops rising)")
    c.add_argument("--image-height", type=int, default=None, metavar="H",
                   help="height the images are fine-tuned at (default: the training resolution the cloud's "
                   "anti-aliasing size says, else the images as they are)")
    c.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    c.add_argument("--sanitize", action="store_true", help="drop non-finite Gaussians of IN first")
    c.set_defaults(func=run_compact)


def _distill(text: str):
    """--distill: "auto" or a whole number of iterations >= 0."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 'auto' or a whole number of iterations >= 0, got {text!r}")
    return value


def parse_keep(text: str) -> float:
    """--keep: a fraction in (0, 1], as 0.3 or 30%."""
    t = str(text).strip()
    try:
        value = float(t[:-1]) / 100.0 if t.endswith("%") else float(t)
    except ValueError:
        value = float("nan")
    if not 0.0 < value <= 1.0:
        raise ValueError(f"--keep must be a fraction in (0, 1] (0.3 or 30%), got {text!r}")
    return value


def run_compact(args: argparse.Namespace) -> int:
    from ..compaction import compact, compaction_inputs, distill_iterations  # noqa: PLC0415
    from ..formats import output_format, read_splat_file, write_splat_file  # noqa: PLC0415

    output_format(args.output)  # a name it cannot write is refused before any work
    keep = parse_keep(args.keep) if args.keep is not None else None
    if args.output.resolve() == args.input.resolve():
        raise ValueError(f"{args.output}: OUT must not be IN (the input is left as it is)")
    if args.images is None and (args.image_height is not None or args.iterations is not None):
        raise ValueError("--iterations and --image-height need --images")
    if args.test_every is not None and args.images is None and args.cameras is None:
        raise ValueError("--test-every needs --cameras or --images")
    for capture_path in (args.cameras, args.images):  # a folder of photos: its cameras by SfM first
        prepare_capture(capture_path)
    t0 = time.perf_counter()
    cloud = read_splat_file(args.input, sanitize=args.sanitize)
    given = compaction_inputs(cloud, source=args.input, cameras=args.cameras, images=args.images,
                              placed_views=args.placed_views, test_every=args.test_every,
                              image_height=args.image_height)
    for line in given.notes:
        tail = " (--placed-views to place views instead)" if given.found and line.startswith("scoring from") else ""
        print(f"gvae compact: {line}{tail}", flush=True)
    cameras, images = given.cameras, given.images
    t_read = time.perf_counter() - t0
    progress = progress_lines()
    result = compact(cloud, keep=keep, count=args.count, tolerance=args.tolerance, cameras=cameras, views=args.views,
                     resolution=args.resolution, score=args.score, removal=args.removal, images=images,
                     rounds=args.rounds, iterations=args.iterations,
                     distill=args.distill, plateau=args.plateau, seed=args.seed,
                     progress=progress if images is not None or distill_iterations(args.distill, len(cloud), images,
                                                                                   args.tolerance) else None)
    t0 = time.perf_counter()
    write_splat_file(result.cloud, args.output)
    t_write = time.perf_counter() - t0
    size_in, size_out = args.input.stat().st_size, args.output.stat().st_size
    print(f"read {args.input} in {t_read:.2f} s")
    print(result.summary())
    for k, r in enumerate(result.rounds, 1):
        print(f"  round {k}: {r['count']:,} Gaussians, fine-tuned {r['seconds']:.1f} s ({r['iterations']:,} "
              f"iterations, the best state at {r['best_at']:,}), PSNR on {r['judged_on']} {r['psnr_before']:.2f} -> "
              f"{r['psnr_after']:.2f} dB")
    print(f"Gaussians {len(result.groups):,} -> {len(result.cloud):,}; file {_size(size_in)} -> {_size(size_out)} "
          f"({size_out / max(size_in, 1):.1%}); PSNR against the input's render {result.psnr:.2f} dB; "
          f"wrote {args.output} in {t_write:.2f} s")
    for warning in result.warnings:
        print(f"gvae compact: warning: {warning}", file=sys.stderr)
    return 0


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n} B"

