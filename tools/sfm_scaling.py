"""Structure from motion on more photos than any capture here holds: the project's own photo set
(`tests/photo_set.py`: a noise-textured box on a floor, a ring of cameras at two heights with
hand-held tilts) rendered from COUNT known cameras, then `tools/sfm_trials.py`'s variants on it,
timed, their cameras compared with the true ones.

Usage: python tools/sfm_scaling.py --out RUNS [--count 300] [--width 1000 --height 750] [--roll 15]
           [--principal-point X Y] [--variant ...]
e.g.   python tools/sfm_scaling.py --out runs/sfm-300 --count 300 --variant auto= --variant global="--mapper global"
The photos and every finished variant are reused (a long job: run it in the background, log on disk).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import sfm_trials  # noqa: E402

from tests.photo_set import photo_set, ring_cameras  # noqa: E402


def write_truth(folder: Path, cameras) -> None:
    """The true cameras as a transforms.json (no images: `read_capture(images=False)` reads it)."""
    cam = cameras[0]
    frames = [{"file_path": f"images/view_{k:02d}.png", "transform_matrix": c.to_blender_c2w().tolist()}
              for k, c in enumerate(cameras)]
    meta = {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
            "frames": frames}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps(meta))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--count", type=int, default=300)
    p.add_argument("--width", type=int, default=1000)
    p.add_argument("--height", type=int, default=750)
    p.add_argument("--roll", type=float, default=15.0, help="hand-held tilt, degrees at most")
    p.add_argument("--principal-point", type=float, nargs=2, default=(0.0, 0.0), metavar=("X", "Y"),
                   help="the lens's principal point off the centre, in shares of the width and height")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--variant", action="append", default=[], metavar='NAME="FLAGS"')
    args = p.parse_args(argv)
    photos, truth = args.out / "photos", args.out / "truth"
    cameras = ring_cameras(args.count, args.width, args.height, roll=args.roll,
                           principal_point=tuple(args.principal_point))
    if not (photos.is_dir() and len(list(photos.glob("*.png"))) == args.count):
        print(f"rendering {args.count} photos of {args.width} x {args.height}", flush=True)
        photo_set(photos, cameras)
    write_truth(truth, cameras)
    flags = [f"--variant={v}" for v in args.variant] or ["--variant=auto="]
    return sfm_trials.main([str(photos), "--out", str(args.out / "runs"), "--reference", str(truth),
                            "--threads", str(args.threads), *flags])


if __name__ == "__main__":
    sys.exit(main())
