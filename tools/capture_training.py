"""Train a real capture with the project and tabulate the held-out figures (BENCHMARKS.md, "Training
on a real capture"): one `gvae train` per (image size, start), each in its own process, every 8th
photo held out (the LLFF / Mip-NeRF 360 convention); PSNR and SSIM of the held-out photos at the
training resolution, Gaussians, wall and CPU time, peak memory, how much of the training pixels
the start covered.

Usage: python tools/capture_training.py CAPTURE --out RUNS [--downscale 4 2] [--init sfm random]
                                        [--threads 2] [--test-every 8] [--picture OUT.png]
                                        [-- extra gvae train options]
e.g.   python tools/capture_training.py ../shared/captures/plush --out runs/plush --downscale 4
`--picture`: three held-out photos above the first run's renders of them (at its resolution).
Runs that finished already are reused (gvae train resumes); a long job: start it in the background
with its log on disk.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path)
    p.add_argument("--out", type=Path, required=True, help="folder for the runs (one subfolder each)")
    p.add_argument("--downscale", type=float, nargs="+", default=[4.0], help="image sizes: stored size / F")
    p.add_argument("--init", nargs="+", default=["sfm", "random"], help="starts to compare")
    p.add_argument("--test-every", type=int, default=8)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--picture", type=Path, help="held-out photos above the first run's renders of them")
    args = p.parse_args(argv)
    rows = []
    for factor in args.downscale:
        for init in args.init:
            run = args.out / f"d{factor:g}-{init}"
            cmd = [sys.executable, "-m", "gvae_core", "train", str(args.capture), "--out", str(run), "--downscale",
                   f"{factor:g}", "--test-every", str(args.test_every), "--init", init, "--threads",
                   str(args.threads), *extra]
            print("$ " + " ".join(cmd), flush=True)
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
            log = json.loads((run / "log.json").read_text())
            rows.append({"downscale": factor, "init": init, "load_at_start": round(load, 1),
                         "command_seconds": round(time.perf_counter() - t0, 1), "stages": log})
            (args.out / "summary.json").write_text(json.dumps(rows, indent=2))
    print()
    print("| size | start | covered (min view) | stages (px) | Gaussians | held-out PSNR | SSIM | train PSNR | "
          "wall s | CPU s | peak MB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        first, last = r["stages"][0], r["stages"][-1]
        wall = sum(e["seconds"] + e["eval_seconds"] for e in r["stages"])
        cpu = sum(e["cpu_seconds"] for e in r["stages"])
        print(f"| 1/{r['downscale']:g} | {first.get('start', '?')} | {first.get('start_coverage', float('nan')):.2%} "
              f"({first.get('start_coverage_min', float('nan')):.2%}) | "
              f"{'/'.join(str(e['resolution']) for e in r['stages'])} | {last['n_gaussians']} | "
              f"{last['test_psnr']:.2f} | {last['test_ssim']:.4f} | {last['train_psnr']:.2f} | {wall:.0f} | "
              f"{cpu:.0f} | {max(e['peak_rss_mb'] for e in r['stages']):.0f} |")
    if args.picture is not None and rows:
        _picture(args.out / f"d{rows[0]['downscale']:g}-{rows[0]['init']}", args.picture)
    return 0


def _picture(run: Path, path: Path, count: int = 3) -> None:
    """`count` held-out photos of the run's capture (top) and the run's last stage drawn through
    their cameras (bottom), at the run's last resolution, over the background it was trained over."""
    import numpy as np  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    from gvae_core.capture import read_capture  # noqa: PLC0415
    from gvae_core.metrics.image import render_views  # noqa: PLC0415
    from gvae_core.ply import read_ply  # noqa: PLC0415

    state = json.loads((run / "run.json").read_text())
    stage = int(state["stages_done"]) - 1
    height = state["config"]["resolutions"][stage]
    views = read_capture(state["data"], state["config"].get("test_every")).load("test", height)
    pick = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    one = type(views)([views.cameras[i] for i in pick], views.images[pick], views.alphas[pick])
    renders = render_views(read_ply(run / f"stage_{stage}.ply"), one)
    sheet = np.concatenate([np.concatenate(list(one.images), 1), np.concatenate(list(renders), 1)], 0)
    Image.fromarray((np.clip(sheet, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path, quality=85)  # (.jpg: small)
    print(f"wrote {path}: held-out photos {', '.join(views.names[i] for i in pick)} (top), {run.name} (bottom)")


if __name__ == "__main__":
    raise SystemExit(main())
