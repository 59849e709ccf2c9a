"""Structure from motion's matchers and mappers side by side on one capture (the figures of
docs/benchmarks/training.md "Structure from motion that scales"): each variant runs `gvae sfm` on the
capture's photos in its own folder and process (timed: wall and CPU seconds, the load), and its model
is compared with a reference model of the same photos (the capture's own sparse/0, or `--reference`):
photos registered, points, reprojection error, the median relative rotation between every pair of
cameras against the reference's, the camera centres after the best similarity, as a share of the
reference centres' extent (their bounding box's diagonal), and how far the first photo's principal
point is from the reference's.

Usage: python tools/sfm_trials.py CAPTURE --out RUNS [--threads 2] [--variant NAME="--matcher vocabtree" ...]
e.g.   python tools/sfm_trials.py ../shared/captures/plush --out runs/sfm-trials \\
           --variant exhaustive="--matcher exhaustive" --variant vocabtree="--matcher vocabtree" \\
           --variant global="--matcher vocabtree --mapper global"
Variants that have a model already are not redone (a long job: run it in the background, log on disk).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gvae_core.capture import read_capture  # noqa: E402
from tests.photo_set import relative_rotation_errors, similarity  # noqa: E402


def compare(model_folder: Path, reference_folder: Path) -> dict:
    """The model's cameras against the reference's, on the photos both registered."""
    got, want = read_capture(model_folder, images=False), read_capture(reference_folder, images=False)
    ref = dict(zip(want.names, want.cameras))
    names = [n for n in got.names if n in ref]
    mine = dict(zip(got.names, got.cameras))
    rot = relative_rotation_errors(got, ref)
    c_got = np.stack([mine[n].center for n in names])
    c_want = np.stack([ref[n].center for n in names])
    s, r, t = similarity(c_got, c_want)
    extent = float(np.linalg.norm(c_want.max(0) - c_want.min(0)))
    centre = np.linalg.norm(s * c_got @ r.T + t - c_want, axis=1) / extent
    pp = (got.photo_cameras[0].cx - want.photo_cameras[0].cx, got.photo_cameras[0].cy - want.photo_cameras[0].cy)
    return {"compared": len(names), "principal_point_off_px": [round(float(v), 2) for v in pp],
            "rotation_median_deg": round(float(np.median(rot)), 3),
            "rotation_p90_deg": round(float(np.percentile(rot, 90)), 3),
            "centre_median_pct": round(100 * float(np.median(centre)), 3),
            "centre_max_pct": round(100 * float(centre.max()), 3)}


def run_variant(photos: Path, folder: Path, flags: str, threads: int) -> dict:
    """`gvae sfm` of `photos` (linked into `folder`) with `flags`, timed; its summary's figures."""
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "images").exists():
        (folder / "images").symlink_to(photos.resolve())
    cmd = [sys.executable, "-m", "gvae_core", "sfm", str(folder), "--threads", str(threads), *shlex.split(flags)]
    print("$ " + " ".join(cmd), flush=True)
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True,
                         env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(out, flush=True)
    row = {"flags": flags, "wall_s": round(time.perf_counter() - t0, 1), "load_at_start": round(load, 1),
           "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1), "log": out}
    for stage in ("features", "matching", "mapping"):
        m = re.search(rf"{stage} ([0-9.]+)", out)
        if m:
            row[f"{stage}_s"] = float(m.group(1))
    m = re.search(r"(\d+) of (\d+) photos registered, (\d+) points, mean reprojection error ([0-9.]+)", out)
    if m:
        row.update(registered=f"{m.group(1)} of {m.group(2)}", points=int(m.group(3)),
                   reprojection_px=float(m.group(4)))
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path, help="a capture: images/ and (unless --reference) sparse/0")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--reference", type=Path, help="the model to compare with (default: the capture's own)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--variant", action="append", default=[], metavar='NAME="FLAGS"',
                   help="a variant: its name and its gvae sfm flags")
    args = p.parse_args(argv)
    photos = args.capture / "images" if (args.capture / "images").is_dir() else args.capture
    reference = args.reference or args.capture
    summary_file = args.out / "summary.json"
    rows = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    for spec in args.variant or ['exhaustive=--matcher exhaustive']:
        name, _, flags = spec.partition("=")
        folder = args.out / name
        if name not in rows or not (folder / "sparse" / "0").is_dir():
            rows[name] = run_variant(photos, folder, flags, args.threads)
        rows[name].update(compare(folder, reference))
        args.out.mkdir(parents=True, exist_ok=True)
        summary_file.write_text(json.dumps(rows, indent=2))
    print("\n| variant | registered (points, px) | features / matching / mapping s | wall s (CPU s) | load | "
          "rotation median (p90) deg | centres median (max) % | principal point off (px) |\n"
          "|---|---:|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} (`{r['flags']}`) | {r.get('registered')} ({r.get('points')}, {r.get('reprojection_px')}) | "
              f"{r.get('features_s')} / {r.get('matching_s')} / "
              f"{r.get('mapping_s')} | {r['wall_s']} ({r['cpu_s']}) | {r['load_at_start']} | "
              f"{r['rotation_median_deg']} ({r['rotation_p90_deg']}) | {r['centre_median_pct']} "
              f"({r['centre_max_pct']}) | {r['principal_point_off_px']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
