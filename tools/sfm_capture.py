"""A real capture trained from its photos alone and from its poses without points (the figures of
docs/benchmarks/training.md "From a folder of photos"): builds the two folders from a COLMAP capture,
then runs `gvae sfm` (timed alone) and `gvae train` on each in its own process, and tabulates the
held-out PSNR / SSIM per stage with wall and CPU seconds and the load.

- PHOTOS: the capture's images/ copied into an empty folder (structure from motion finds the cameras);
- POSED: its sparse/0 without points3D (cameras and images files only) beside a link to its images
  (the points are triangulated with those poses).

Usage: python tools/sfm_capture.py CAPTURE --out RUNS [--downscale 4] [--test-every 8]
e.g.   python tools/sfm_capture.py ../shared/captures/plush --out runs/sfm
Folders and runs that exist are reused (SfM, triangulation and gvae train all reuse their work): a
long job, start it in the background with its log on disk.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path


def _timed(cmd: list[str]) -> dict:
    print("$ " + " ".join(cmd), flush=True)
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"wall_s": round(time.perf_counter() - t0, 1), "load_at_start": round(load, 1),
            "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path, help="a COLMAP capture: sparse/0 and images/")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--downscale", type=float, default=4.0)
    p.add_argument("--test-every", type=int, default=8)
    args = p.parse_args(argv)
    images = args.capture / "images"
    model = next(d for d in (args.capture / "sparse" / "0", args.capture / "sparse") if d.is_dir())
    photos, posed = args.out / "photos", args.out / "posed"
    if not photos.is_dir():
        shutil.copytree(images, photos)
    if not posed.is_dir():
        (posed / "sparse" / "0").mkdir(parents=True)
        for f in model.iterdir():
            if f.stem in ("cameras", "images"):
                shutil.copy(f, posed / "sparse" / "0" / f.name)
        (posed / "images").symlink_to(images.resolve())
    gvae = [sys.executable, "-m", "gvae_core"]
    rows = {}
    if not (photos / "sparse" / "0").is_dir():
        rows["sfm"] = _timed(gvae + ["sfm", str(photos)])
    for name, folder in (("photos", photos), ("posed", posed)):
        run = args.out / f"{name}-run"
        rows[name] = _timed(gvae + ["train", str(folder), "--out", str(run), "--test-every", str(args.test_every),
                                    "--downscale", f"{args.downscale:g}", "--quiet"])
        rows[name]["stages"] = json.loads((run / "log.json").read_text())
        (args.out / "summary.json").write_text(json.dumps(rows, indent=2))
    print("\n| start | held-out PSNR / SSIM per stage | Gaussians | wall s (CPU s) | load |\n|---|---|---:|---|---|")
    for name in ("photos", "posed"):
        r = rows[name]
        stages = " / ".join(f"{e['test_psnr']:.2f}" for e in r["stages"])
        last = r["stages"][-1]
        print(f"| {name} ({r['stages'][0].get('start', '')}) | {stages} "
              f"(SSIM {last['test_ssim']:.3f}) | {last['n_gaussians']:,} | {r['wall_s']} ({r['cpu_s']}) | "
              f"{r['load_at_start']} |")
    if "sfm" in rows:
        sfm = rows["sfm"]
        print(f"\nSfM alone: {sfm['wall_s']} s wall, {sfm['cpu_s']} CPU-s, load {sfm['load_at_start']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
