"""Refine from the capture's images (`refine(images=...)`, `gvae_core.superres`) at capture scale:
seconds for one octave of the default fit, seconds per step, peak memory against the estimate, and
the error of the same run (PSNR of the averaged-down 2x render against the images the fit held out:
the input's, where the fit started and where it ended, and what was kept; the training picture
kept: its largest change at 1x).

The capture is synthetic, so that any size can be made: `example_cloud(N)` (SH 3) as the scene,
its renders at twice the image height averaged down as the training images (from cameras on a ring
around it, looking at it), and the same cloud with every Gaussian 25% larger, carrying the cameras'
anti-aliasing size, as the trained cloud. Each size runs in a fresh process (its peak memory is its
own). Quality is measured on the benchmark scenes (`make report`), not here.

`python -m gvae_core.benchmarks.superres [--sizes N:VIEWS:HEIGHT ...] [--fit KEY=VALUE ...]
[--optimizer adam] [--crop-check]` runs the table for other sizes and fits (BENCHMARKS' capture-scale
rows: `--fit lr=0.3`, `--fit patch=0 --fit steps=100`, `--fit fields=scales,opacities,sh_dc,means`,
`--fit children=0.0002`, `--optimizer adam` for plain Adam instead of `superres.optim.VisibleAdam`),
or with `--crop-check` instead the largest difference between a patch's render and the same region of
the whole image."""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

from ..antialias import with_dilation_3d
from ..camera import Camera
from ..datasets import Views
from ..examples import example_cloud
from ..refinement import refine
from ..rendering import render
from ..resources import estimate_image_fit_memory
from ..superres import SuperResConfig

#: The capture sizes the benchmark runs: (Gaussians, images, image height); the first two are the
#: speed goals (one octave of 50k Gaussians and 43 photos of 240 px within 2 minutes on 2 cores,
#: of 100k Gaussians and 100 photos of 500x375 within 5), then 1M measured.
SIZES = ((50_000, 43, 240), (100_000, 100, 375), (1_000_000, 40, 540))


def synthetic_capture(n: int, views: int, height: int, seed: int = 1):
    """(trained cloud, training images) of the synthetic capture (module docstring)."""
    truth = example_cloud(n, seed=seed)
    width = int(round(height * 4 / 3))
    cams = []
    for i in range(views):
        a = 2 * math.pi * i / views
        eye = (3.2 * math.cos(a), 3.2 * math.sin(a), 0.6 + 1.2 * ((i * 0.618) % 1.0))
        cams.append(Camera.look_at(eye, (0, 0, 0), width=width, height=height, fov_x=math.radians(50)))
    big = [c.scaled(2 * height) for c in cams]
    sharp = with_dilation_3d(truth, big)
    images = np.empty((views, height, width, 3), np.float32)
    with torch.no_grad():
        for i, c in enumerate(big):
            img = render(sharp, c, background=(1.0, 1.0, 1.0)).image
            images[i] = F.avg_pool2d(img.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0).clamp(0, 1).numpy()
    trained = with_dilation_3d(truth.replace(scales=truth.scales + np.float32(math.log(1.25))), cams)
    return trained, Views(cams, images)


def one(n: int, views: int, height: int, fit: dict | None = None, optimizer: str = "visible") -> dict:
    """The child process: make the capture, refine one octave from its images; times and checks."""
    t0 = time.perf_counter()
    trained, images = synthetic_capture(n, views, height)
    made = time.perf_counter() - t0
    config = {**(fit or {}), "optimizer": optimizer}
    c0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    r = refine(trained, images=images, fit=config)
    seconds = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    fit = r.fit
    cam = images.cameras[0]
    with torch.no_grad():  # the training picture: the refined cloud's 1x render against the input's
        kept = float((render(r.cloud, cam).image - render(trained, cam).image).abs().max())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    conf = SuperResConfig(**config)
    estimate = estimate_image_fit_memory(n, trained.sh_degree, images=views, height=height, width=cam.width,
                                         extra_values=len(trained.extra),
                                         children=conf.max_children if conf.children is not None else 0.0,
                                         patch=conf.patch, views_per_step=conf.views_per_step)
    return {"n": n, "views": views, "height": height, "width": cam.width, "made_s": made, "seconds": seconds,
            "fit_s": r.timings.get("fit", float("nan")), "steps": len(fit.losses),
            "cpu": c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime, "before": fit.psnr_before,
            "after": fit.psnr_after,
            "holdout": [fit.holdout_input, fit.holdout_start, fit.holdout_begin, fit.holdout_fit],
            "kept": fit.kept, "checks": fit.checks, "added": len(r.added), "kept_1x": kept, "peak": peak,
            "estimate": estimate, "nonfinite": len(r.cloud.nonfinite_rows()), "timings": r.timings}


def crop_check(n: int, views: int, height: int, patches: int = 8, patch: int = 96, seed: int = 0) -> float:
    """Largest difference between a `patch`-pixel patch drawn at 2x through a cropped camera (as
    the fit draws one) and the same region of the whole 2x render, over `patches` patches of the
    synthetic capture's trained cloud."""
    from ..detail.fit import crop  # noqa: PLC0415

    trained, images = synthetic_capture(n, views, height)
    rng = np.random.default_rng(seed)
    worst = 0.0
    with torch.no_grad():
        for k in range(patches):
            big = images.cameras[k % views].scaled(2 * height)
            whole = render(trained, big).image
            size = min(2 * patch, big.height // 2)  # (a patch of `patch` image pixels, or half a small image)
            x0, y0 = int(rng.integers(big.width - size + 1)), int(rng.integers(big.height - size + 1))
            part = render(trained, crop(big, x0, y0, size, size)).image
            worst = max(worst, float((part - whole[y0:y0 + size, x0:x0 + size]).abs().max()))
    return worst


def parse_fit(items) -> dict:
    """`KEY=VALUE` overrides of `SuperResConfig` (numbers, "none", comma-separated field lists)."""
    fit = {}
    for item in items or ():
        key, _, text = item.partition("=")
        if key not in SuperResConfig.__dataclass_fields__ or not text:
            raise ValueError(f"--fit {item!r}: expected KEY=VALUE with KEY a SuperResConfig field")
        if key in ("fields", "densify_at"):
            value = tuple(v for v in text.split(",") if v)
        elif text.lower() == "none":
            value = None
        else:
            try:
                value = int(text)
            except ValueError:
                try:
                    value = float(text)
                except ValueError:
                    value = text
        fit[key] = value
    SuperResConfig(**fit)  # refuse a bad value before any child process starts
    return fit


def run(args) -> None:
    quick = bool(getattr(args, "quick", False))
    sizes = getattr(args, "sizes", None) or (((20_000, 12, 200),) if quick else SIZES)
    fit, optimizer = getattr(args, "fit", None) or {}, getattr(args, "optimizer", "visible")
    if getattr(args, "crop_check", False):
        for n, views, height in sizes:
            print(f"{n:,} Gaussians: patches drawn at 2x through a cropped camera against the same region "
                  f"of the whole render: largest difference {crop_check(n, views, height):.2g}")
        return
    threads = os.environ.get("OMP_NUM_THREADS") or torch.get_num_threads()
    config = SuperResConfig(**{**fit, "optimizer": optimizer})
    print(f"Refine from the capture's images, one octave, the fit {config} "
          f"({'plain Adam' if optimizer == 'adam' else 'VisibleAdam'}), synthetic captures (module docstring), "
          f"torch threads {threads}; each size in a fresh process:")
    print("\n| Gaussians | images | refine s (fit s; steps; s/step) | process CPU s | held-out images, 2x averaged "
          "down: input / detail model / fit at step 0 -> its end (kept) | added | 1x largest change | "
          "peak RSS (estimate) | non-finite rows | load |")
    print("|---:|---|---|---:|---|---:|---:|---|---:|---|")
    for n, views, height in sizes:
        load0 = os.getloadavg()[0]
        command = [sys.executable, "-m", "gvae_core.benchmarks.superres", "--one", str(n), str(views), str(height),
                   "--optimizer", optimizer, *(a for k, v in fit.items() for a in ("--fit", f"{k}={_text(v)}"))]
        proc = subprocess.run(command, capture_output=True, text=True, timeout=6 * 3600)
        if proc.returncode != 0:
            why = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode
            print(f"| {n:,} | {views} x {height} px | failed: {why} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        ho = r["holdout"]
        print(f"| {n:,} | {views} x {r['width']}x{height} px | **{r['seconds']:.1f}** ({r['fit_s']:.1f}; "
              f"{r['steps']}; {r['fit_s'] / max(r['steps'], 1):.3f}) | {r['cpu']:.1f} | {ho[0]:.2f} / {ho[1]:.2f} / "
              f"{ho[2]:.2f} -> {ho[3]:.2f} dB ({r['kept']}) | "
              f"{r['added']:,} | {r['kept_1x']:.1e} | {r['peak'] / 2 ** 30:.2f} GiB ({r['estimate'] / 2 ** 30:.2f}) | "
              f"{r['nonfinite']} | {load0:.1f}-{os.getloadavg()[0]:.1f} |", flush=True)


def _text(value) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _size(text: str) -> tuple[int, int, int]:
    try:
        n, views, height = (int(v.replace("_", "")) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N:VIEWS:HEIGHT, got {text!r}") from None
    return n, views, height


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.superres",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", type=_size, metavar="N:VIEWS:HEIGHT",
                        help="synthetic captures to run (default: SIZES, 50000:43:240 100000:100:375 "
                        "1000000:40:540; with --quick 20000:12:200)")
    parser.add_argument("--fit", action="append", metavar="KEY=VALUE",
                        help="a SuperResConfig field for the fit, repeatable (default: none: the default fit)")
    parser.add_argument("--optimizer", choices=("visible", "adam"), default="visible",
                        help="visible: superres.optim.VisibleAdam; adam: plain Adam, as before it (default: visible)")
    parser.add_argument("--crop-check", action="store_true", help="the patch-against-whole-image check instead")
    parser.add_argument("--quick", action="store_true", help="one 20k capture (default: SIZES)")
    parser.add_argument("--one", nargs=3, type=int, metavar=("N", "VIEWS", "HEIGHT"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.fit = parse_fit(args.fit)
    if args.one:
        print(json.dumps(one(*args.one, fit=args.fit, optimizer=args.optimizer)))
    else:
        run(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
