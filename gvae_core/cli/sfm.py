"""`gvae sfm PHOTOS`: structure from motion of a folder of photos (pycolmap on the CPU) into a
COLMAP model beside them; and the SfM options and the one call (`prepare_capture`) that every
command taking a capture (train, render --cameras, refine --images/--cameras, compact
--images/--cameras) makes first, so a folder of photos works everywhere."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


#: `capture.sfm.SfMOptions`' defaults, here so that `--help` imports nothing (a test holds them equal).
SFM_IMAGE_SIZE = 1000


def add_sfm_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of structure from motion, for the commands that may run it."""
    g = parser.add_argument_group("structure from motion (a folder of photos with no cameras yet)")
    g.add_argument("--matcher", choices=("auto", "exhaustive", "sequential", "vocabtree"), default="auto",
                   help="which photo pairs are matched: every pair (exhaustive), each frame with its next ones by "
                        "name (sequential: the frames of a video), or the most similar ones by a vocabulary tree of "
                        "the photos' own features; auto: exhaustive up to 50 photos, vocabtree beyond "
                        "(default: %(default)s)")
    g.add_argument("--mapper", choices=("incremental", "global"), default="incremental",
                   help="incremental mapping (COLMAP's: photo by photo) or global mapping (GLOMAP: every photo at "
                        "once) (default: %(default)s)")
    g.add_argument("--camera", choices=("auto", "single", "per-image"), default="auto", dest="sfm_camera",
                   help="one camera shared by all photos, or one per photo; auto: shared when the photos have one "
                        "size and lens (default: %(default)s)")
    g.add_argument("--sfm-image-size", type=int, default=SFM_IMAGE_SIZE, metavar="PX",
                   help="features are found with photos scaled to at most this many pixels on the long side "
                        "(default: %(default)s)")


def sfm_options(args: argparse.Namespace):
    from ..capture.sfm import SfMOptions

    return SfMOptions(matcher=getattr(args, "matcher", "auto"), mapper=getattr(args, "mapper", "incremental"),
                      camera=getattr(args, "sfm_camera", "auto"),
                      max_image_size=getattr(args, "sfm_image_size", SFM_IMAGE_SIZE),
                      threads=getattr(args, "threads", None))


def stage_printer():
    """progress(stage, fraction, message) that prints a line when the stage changes or every few seconds."""
    last = [0.0, ""]

    def progress(stage: str, fraction: float, message: str) -> None:
        now = time.perf_counter()
        if stage != last[1] or now - last[0] > 5.0 or fraction >= 1.0:
            print(f"  [{fraction:4.0%}] {message}", flush=True)
            last[:] = [now, stage]

    return progress


def prepare_capture(path: Path, args: argparse.Namespace | None = None, *, points: bool = False):
    """Run structure from motion on `path` when it is a folder of photos with no cameras (and, with
    `points`, triangulate a capture with poses and no points), saying what it does; the SfM report
    or None."""
    from ..capture.sfm import ensure_capture, needs_sfm

    if path is None:
        return None
    if needs_sfm(path):
        print(f"{path}: photos and no cameras: structure from motion (pycolmap, CPU)", flush=True)
    report = ensure_capture(path, sfm_options(args) if args is not None else None, points=points,
                            progress=stage_printer())
    if report is not None:
        print(report.summary(), flush=True)
    return report


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sfm", help="structure from motion: a folder of photos -> a COLMAP model beside them (CPU)",
        description="Find the cameras of a folder of photos (in it or in its images/ folder) by structure from "
                    "motion with pycolmap on the CPU: SIFT features, matching, incremental mapping. Writes "
                    "PHOTOS/sparse/0 (COLMAP binary model: cameras, images, points3D) and PHOTOS/database.db, "
                    "COLMAP's own layout, which gvae train, COLMAP's GUI, gsplat and nerfstudio read; photos it "
                    "cannot register are named and left out. A failed or cancelled run leaves the folder as it was. "
                    "gvae train/render/refine/compact run this themselves on a folder of photos.")
    p.add_argument("photos", type=Path, metavar="PHOTOS", help="the folder of photos (or holding images/)")
    add_sfm_arguments(p)
    p.add_argument("--threads", type=int, help="CPU threads (default: all)")
    p.add_argument("--overwrite", action="store_true", help="redo SfM and replace the model that is there "
                   "(default: keep it and say so)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..capture.sfm import SfMCancelled, needs_sfm, run_sfm

    if not args.overwrite and not needs_sfm(args.photos):
        if (args.photos / "sparse" / "0").is_dir():
            print(f"{args.photos / 'sparse' / '0'}: a model is there already; --overwrite redoes it")
            return 0
    try:
        report = run_sfm(args.photos, sfm_options(args), progress=stage_printer(), overwrite=args.overwrite)
    except (KeyboardInterrupt, SfMCancelled):
        print(f"gvae sfm: cancelled; {args.photos} is as it was", file=sys.stderr)
        return 130
    print(report.summary())
    return 0
