"""`gvae fit-vae RUN_DIR... --out MODEL_DIR` and `gvae refine IN.ply OUT.ply --steps K [--budget B]`."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS
from ..progress import progress_bar
from . import progress_lines
from .sfm import prepare_capture


def register(subparsers) -> None:
    _register_fit(subparsers)
    _register_refine(subparsers)


def _register_fit(subparsers) -> None:
    p = subparsers.add_parser(
        "fit-vae", help="train the geometry and appearance lineage VAEs from training runs",
        description="Train both lineage VAEs on the stage transitions of one or more progressive "
        "training runs (each RUN_DIR holds the lineage.npz that `gvae train` writes; a path to a "
        ".npz works too) and save them to MODEL_DIR as safetensors weights plus config.json.")
    p.add_argument("runs", nargs="*", type=Path, metavar="RUN_DIR", help="training runs to learn from")
    p.add_argument("--out", type=Path, required=True, metavar="MODEL_DIR", help="where to save the model")
    p.add_argument("--holdout", nargs="*", type=Path, default=[], metavar="RUN_DIR",
                   help="runs kept out of training, evaluated after it (written into config.json) (default: none)")
    p.add_argument("--synthetic", type=int, default=0, metavar="N",
                   help="also train on N synthetic lineages per stage, for a start without runs (default: %(default)s)")
    p.add_argument("--steps", type=int, default=3000, help="optimiser steps (default: %(default)s)")
    p.add_argument("--batch", type=int, default=256, help="lineages per step (default: %(default)s)")
    p.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (default: %(default)s)")
    p.add_argument("--d-model", type=int, default=None, help="transformer width of both models "
                   "(default: the bundled models')")
    p.add_argument("--layers", type=int, default=None, help="encoder layers (default: the bundled models')")
    p.add_argument("--decoder-hidden", type=int, default=None,
                   help="decoder hidden width (default: the bundled models')")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_fit)


def _register_refine(subparsers) -> None:
    r = subparsers.add_parser(
        "refine", help="refine a 3DGS PLY past its training resolution",
        description="detail (default): the detail model says how each Gaussian changes per octave above its "
        "training resolution, stored in the PLY (gvae_octave_* properties) and applied by the renderer, so the "
        "training-resolution picture is kept; K octaves. vae (the paper's): score the Gaussians (Hessian), pick "
        "the budget's share and run the lineage VAEs for K sequential steps (input Gaussians first, then the "
        "added ones).")
    r.add_argument("input", type=Path, metavar="IN.ply", help="a splat file: 3DGS or compressed PLY, .splat, .spz")
    r.add_argument("output", type=Path, metavar="OUT.ply",
                   help="where the refined cloud goes, in the format its name asks for (.ply, .spz, .splat)")
    r.add_argument("--method", choices=("detail", "vae"), default=None,
                   help="detail (the default) or vae (the paper's lineage VAEs; default with a --model folder "
                   "holding only them)")
    r.add_argument("--steps", type=int, default=1,
                   help="detail: octaves above the training resolution the changes run to; vae: sequential steps "
                   "(default: 1)")
    r.add_argument("--budget", default=None,
                   help="'all', 'auto' (from the Hessian score distribution), a fraction (0.1 or 10%%) or a count "
                   "(default: all for detail, auto for vae)")
    r.add_argument("--bake", type=float, default=None, metavar="FACTOR",
                   help="detail: write a plain cloud, drawn as the refined one is at FACTOR times the training "
                   "resolution, for other tools (default: keep the changes in a .ply; the other formats, which keep no "
                   "extra properties, are baked at 2^K)")
    r.add_argument("--model", type=Path, default=None, help="model directory (default: the bundled one)")
    r.add_argument("--lineage", type=Path, default=None,
                   help="lineage.npz of the run IN.ply comes from (default: one-node lineages); its stages up to "
                   "IN.ply's are used")
    r.add_argument("--stage", type=int, default=None, metavar="K",
                   help="the lineage stage IN.ply is (default: found from its gvae_id values and positions)")
    _add_hessian_arguments(r)
    _add_image_arguments(r)
    r.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    r.add_argument("--sanitize", action="store_true", help="drop non-finite Gaussians of IN.ply first")
    r.set_defaults(func=run_refine)


def _add_hessian_arguments(r) -> None:
    """refine's options of the Hessian scoring (--method vae) and of the fidelity check."""
    r.add_argument("--cameras", type=Path, default=None, metavar="PATH",
                   help="the capture's cameras for the Hessian: a transforms*.json file or a COLMAP sparse model "
                   "(folder with cameras/images .bin or .txt); default: views placed around the cloud")
    r.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                   help="views the Hessian is computed from (of the capture's cameras, spread out; 0: all of "
                   "them) (default: %(default)s)")
    r.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION,
                   help="Hessian view height in pixels (capture cameras are scaled down to it) (default: %(default)s)")
    r.add_argument("--fidelity", default=None, metavar="TOL|off",
                   help="largest colour change (0..1) a refined lineage may make at the training sampling rate; "
                   "those above are put back as they were (default: the method's, fidelity.DEFAULT_TOLERANCES; "
                   "off: keep everything the models did)")


def _add_image_arguments(r) -> None:
    """refine's options of the fit to the capture's images (--images)."""
    r.add_argument("--images", type=Path, default=None, metavar="DATASET",
                   help="detail: the capture's training images (a COLMAP capture, a transforms.json with its images "
                   "or a NeRF-Synthetic folder: what gvae train reads): every Gaussian's changes per octave are fitted "
                   "so that the cloud drawn at 2^k times their resolution and averaged back down reproduces them "
                   "(multi-view super-resolution; checked against the cloud first) (default: none: the detail model)")
    r.add_argument("--image-height", type=int, default=None, metavar="H",
                   help="the height the cloud was trained at, the images are fitted at (default: what the cloud's "
                   "anti-aliasing size says against the capture's cameras, else the images as they are)")
    r.add_argument("--test-every", type=int, default=None, metavar="N",
                   help="with --images: every N-th image of the capture (by name) was held out from training "
                   "(gvae train --test-every N): never fitted, as it was not trained on (default: none)")
    r.add_argument("--fit-steps", type=int, default=None, metavar="N",
                   help="with --images: steps per octave, one whole image each (default: 20 passes over the fitted "
                   "images, at most 300)")
    r.add_argument("--children", action="store_true",
                   help="with --images: add Gaussians that fade in above the training resolution where the fit's "
                   "gradients ask for them (more detail at 2x, a little less at 1.5x; BENCHMARKS.md)")
    r.add_argument("--pose-correction", action="store_true",
                   help="with --images: fit a small rigid correction per image (for cameras a quarter pixel or "
                   "more off; on exact cameras it costs a little)")
    r.add_argument("--exposure-correction", action="store_true",
                   help="with --images: fit an affine colour per image (exposure or white balance that varies)")


def run_fit(args: argparse.Namespace) -> int:
    from ..vae import (FitConfig, GaussianVAE, copy_parent_baseline, evaluate, fit, load_runs, save_model,
                       synthetic_transitions)

    if not args.runs and args.synthetic <= 0:
        raise ValueError("fit-vae: give at least one RUN_DIR (or --synthetic N)")
    size = {k: v for k, v in (("d_model", args.d_model), ("layers", args.layers),
                              ("decoder_hidden", args.decoder_hidden)) if v is not None}
    model = GaussianVAE.create(seed=args.seed, **size)
    train = load_runs(args.runs, model.slots)
    for run in args.holdout:  # fail early on a missing held-out run; they are read after training
        if not (run.is_file() or run.is_dir()):
            raise FileNotFoundError(f"{run}: held-out run not found")
    if args.synthetic > 0:
        train += synthetic_transitions(args.synthetic, 4, seed=args.seed)
    n_lineages = sum(len(t) for t in train)
    print(f"training on {len(train)} transitions, {n_lineages} lineages "
          f"({len(args.runs)} run(s){', + synthetic' if args.synthetic > 0 else ''}); "
          f"{len(args.holdout)} held-out run(s)")
    config = FitConfig(steps=args.steps, batch=args.batch, lr=args.lr, seed=args.seed)
    bar = progress_bar(config.steps, "fit-vae", enabled=not args.quiet, unit="step")

    def progress(step: int, total: int, record: dict) -> None:
        if step % 50 == 0 or step == total:
            bar.set_postfix(loss=f"{record['total']:.4g}", mse=f"{record['mse']:.3g}",
                            pos=f"{record['position_rmse']:.3g}")
        bar.update(1)

    with bar:
        result = fit(train, config, model=model, progress=progress)
    model = result.model
    t0 = time.perf_counter()
    metrics = {"train": evaluate(model, train)}
    held = load_runs(args.holdout, model.slots)
    if held:
        metrics["holdout"] = evaluate(model, held)
        metrics["holdout_copy_parent"] = copy_parent_baseline(held)
    # Existence probabilities at refinement: the source most accurate on held-out runs (else training).
    judge = metrics.get("holdout", metrics["train"])
    existence = max((("geometry", judge["exist_accuracy"]), ("appearance", judge["exist_accuracy_appearance"]),
                     ("combined", judge["exist_accuracy_combined"])), key=lambda kv: kv[1])[0]
    model.meta = {
        "existence": existence,
        "trained_on": [_display(r) for r in args.runs] + (["synthetic"] if args.synthetic > 0 else []),
        "held_out": [_display(r) for r in args.holdout], "lineages": n_lineages, "steps": config.steps,
        "train_scenes": [_scene_name(r) for r in args.runs], "held_out_scenes": [_scene_name(r) for r in args.holdout],
        "seed": args.seed, "seconds": round(result.seconds, 1), "metrics": metrics,
    }
    save_model(model, args.out)
    sizes = model.sizes()
    print(f"existence probabilities from: {existence}")
    print(f"trained in {result.seconds:.1f} s (+{time.perf_counter() - t0:.1f} s evaluation); saved to {args.out}: "
          f"geometry {sizes['geometry'] / 1e6:.2f} MB, appearance {sizes['appearance'] / 1e6:.2f} MB")
    for split, m in metrics.items():
        print(f"  {split}: " + json.dumps({k: round(v, 4) for k, v in m.items()}))
    return 0


def _display(run: Path) -> str:
    """A run path for the model's record: relative to the scene/run cache when inside it."""
    from ..scenes import cache_dir

    try:
        return "$GVAE_CACHE_DIR/" + str(Path(run).resolve().relative_to(cache_dir().resolve()))
    except ValueError:
        return str(run)


def _scene_name(run: Path) -> str:
    """A run's scene: the run folder's name (the experiment caches runs as .../<protocol>/<scene>)."""
    return (run.parent if run.suffix == ".npz" else run).name


def run_refine(args: argparse.Namespace) -> int:
    from ..budget import parse_budget
    from ..capture import load_cameras
    from ..lineage import Lineage
    from ..formats import output_format, read_splat_file, write_splat_file
    from ..octaves import bake, has_octaves
    from ..refinement import refine
    from ..superres import CHILD_GRADIENT, EXPOSURE_WEIGHT, POSE_WEIGHT

    output_format(args.output)  # a name no format is written under is refused before any work
    budget = parse_budget(args.budget) if args.budget is not None else None
    fidelity = _parse_fidelity(args.fidelity, "auto")
    for capture_path in (args.cameras, args.images):  # a folder of photos: its cameras by SfM first
        prepare_capture(capture_path)
    t0 = time.perf_counter()
    cloud = read_splat_file(args.input, sanitize=args.sanitize)
    lineage = Lineage.load(args.lineage) if args.lineage is not None else None
    cameras = load_cameras(args.cameras, args.test_every) if args.cameras is not None else None
    t_read = time.perf_counter() - t0
    if args.stage is not None and lineage is None:
        raise ValueError("--stage needs --lineage")
    if args.bake is not None and not args.bake > 0:
        raise ValueError(f"--bake must be a positive factor, got {args.bake}")
    fit = None
    guards = {"children": CHILD_GRADIENT if args.children else None, "pose": POSE_WEIGHT if args.pose_correction
              else None, "exposure": EXPOSURE_WEIGHT if args.exposure_correction else None}
    if args.images is None and (args.image_height is not None or args.fit_steps is not None
                                or args.test_every is not None or any(v is not None for v in guards.values())):
        raise ValueError("--image-height, --fit-steps, --test-every, --children, --pose-correction and "
                         "--exposure-correction need --images")
    if args.images is not None:
        fit = {"seed": args.seed, **({"steps": args.fit_steps} if args.fit_steps is not None else {}),
               **{k: v for k, v in guards.items() if v is not None}}
    result = refine(cloud, steps=args.steps, budget=budget, method=args.method, model=args.model, lineage=lineage,
                    stage=args.stage, cameras=cameras, seed=args.seed, fidelity=fidelity,
                    hessian_options={"views": args.views, "resolution": args.resolution}, images=args.images,
                    image_height=args.image_height, fit=fit, progress=progress_lines() if args.images else None,
                    test_every=args.test_every)
    t0 = time.perf_counter()
    out = result.cloud
    factor = args.bake
    if factor is None and has_octaves(out) and output_format(args.output) != "ply":  # the others keep no extras
        factor = 2.0 ** args.steps
    if factor is not None and has_octaves(out):
        out = bake(out, factor)
        print(f"baked for {factor:g}x the training resolution (a plain cloud for other tools)")
    write_splat_file(out, args.output)
    print(f"read {args.input} in {t_read:.2f} s"
          + (f"; {len(cameras)} capture cameras from {args.cameras}" if cameras is not None else ""))
    if lineage is not None:
        print(f"lineage: stages 0..{result.stage} of {lineage.n_stages} (IN.ply is stage {result.stage})")
    print(result.summary())
    print(f"wrote {args.output} ({len(result.cloud)} Gaussians) in {time.perf_counter() - t0:.2f} s")
    return 0


def _parse_fidelity(text: str | None, default: float | str) -> float | str | None:
    """--fidelity: a tolerance >= 0, or "off" (None)."""
    if text is None:
        return default
    if text.strip().lower() in ("off", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value >= 0.0:
        raise ValueError(f"--fidelity must be a tolerance >= 0 or 'off', got {text!r}")
    return value
