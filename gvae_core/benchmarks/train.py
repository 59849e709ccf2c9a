"""Progressive training: seconds per iteration, peak memory and PSNR per resolution.

One benchmark scene (default: the first of `list_scenes()`, or $GVAE_BENCH_TRAIN_SCENE) trained
with the `default` training profile on the `default` scene profile (`--quick`: the `tiny`
profiles). Every row is one stage of the same run: its time and its error (train/test PSNR). The
project's counterpart of the paper's resolution-scaling (VRAM) table: peak resident memory of
the process per stage, and how much it rose above the memory at the start of the stage.
"""

from __future__ import annotations

import os
import tempfile
import time

from ..scenes import BlenderNotAvailable, list_scenes, make_scene
from ..train import TrainConfig, train_progressive


def run(args) -> None:
    quick = bool(getattr(args, "quick", False))
    profile = "tiny" if quick else "default"
    name = os.environ.get("GVAE_BENCH_TRAIN_SCENE") or list_scenes()[0]
    threads = int(os.environ.get("GVAE_BENCH_TRAIN_THREADS", "1"))
    try:
        t = time.perf_counter()
        scene = make_scene(name, profile=profile)
        print(f"scene {name} ({profile} profile) ready in {time.perf_counter() - t:.1f} s: {scene}")
    except BlenderNotAvailable as exc:
        print(f"skipped: no benchmark scene ({exc})")
        return
    config = TrainConfig.profile(profile)
    print(f"training profile {profile}: resolutions {config.resolutions}, iterations {config.iterations}, "
          f"torch threads {threads}")
    with tempfile.TemporaryDirectory(prefix="gvae-bench-train-") as out:
        t = time.perf_counter()
        result = train_progressive(scene, config, out_dir=out, progress=False, threads=threads)
        total = time.perf_counter() - t
    print(f"| {'res (px)':>8} | {'iters':>5} | {'s/iter':>7} | {'stage s':>7} | {'Gaussians':>9} | "
          f"{'train dB':>8} | {'test dB':>7} | {'peak RSS MB':>11} | {'rise MB':>7} |")
    print("|" + "|".join("-" * (w + 2) for w in (8, 5, 7, 7, 9, 8, 7, 11, 7)) + "|")
    for e in result.log:
        test = e["test_psnr"] if e["test_psnr"] is not None else float("nan")
        print(f"| {e['resolution']:>8} | {e['iterations']:>5} | {e['seconds_per_iteration']:>7.3f} | "
              f"{e['seconds']:>7.1f} | {e['n_gaussians']:>9} | {e['train_psnr']:>8.2f} | {test:>7.2f} | "
              f"{e['peak_rss_mb']:>11.0f} | {e['peak_rss_mb'] - e['rss_start_mb']:>7.0f} |")
    print(f"total {total:.1f} s including evaluation and writing (load average at end "
          f"{os.getloadavg()[0]:.2f})")
