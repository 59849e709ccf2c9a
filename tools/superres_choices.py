"""The choices of refine with the capture's images (`refine(images=...)`, `gvae_core.superres`), made on
the validation scenes: each variant of the fit beside the same steps of plain training at 1x and the
detail model alone, as PSNR change at 2x / at 1x against the unrefined cloud, seconds of the whole
refine and Gaussians added (docs/benchmarks/refine-images.md, "Choices").

The runs are the quick protocol's trained to the training resolution only (`Protocol.fits()`,
cached), scored on its 8 test views with its `matched` render over white. Two sets of rows: the fit
as it is beside what was tried for it (the default: whole images judged on every 8th image held
out); and the first patch fit's (`PATCH_FIT`: 400 steps of 96 px patches, no image held out; its
patches tile each image rather than fall at random, so its rows come near the figures measured
with it, not exactly). `--optimizer adam` runs the fit with torch's plain Adam instead of
`superres.optim.VisibleAdam`; `--smoke` runs everything at the smallest size
(`experiment.SMOKE`: 64 px scenes, 10 fit steps), to show that it runs.

Usage: python tools/superres_choices.py [--scenes chair tableware] [--seed 0] [--variants NAME ...]
                                        [--optimizer visible|adam] [--steps N] [--smoke]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

from gvae_core.capture import load_nerf_synthetic
from gvae_core.detail import load_detail
from gvae_core.experiment import PROTOCOLS, SMOKE, Evaluator, image_config, prepare_scene
from gvae_core.metrics.image import image_scores
from gvae_core.refinement import refine
from gvae_core.scenes import SPLITS
from gvae_core.superres import CHILD_GRADIENT, EXPOSURE_WEIGHT, POSE_WEIGHT
from gvae_core.train import fine_tune

FOUR = ("scales", "opacities", "sh_dc", "means")
#: The first patch fit: 400 steps of 96 px patches, no image held out (its own images judged it).
PATCH_FIT = {"steps": 400, "patch": 96, "holdout": 0}
#: name -> (what the table calls it, `SuperResConfig` changes); "plain" and "detail" are not fits.
VARIANTS = {
    "plain": ("the same steps of plain 1x training (the default fit's)", None),
    "detail": ("the detail model alone (no images)", None),
    # the fit judged on held-out images
    "default": ("the default: whole images, every 8th held out, 20 passes up to 300 steps, rates x1", {}),
    "lr0.3": ("every learning rate x0.3", {"lr": 0.3}),
    "tiles96": ("96 px tiles covering each image instead of whole images", {"patch": 96}),
    "two-views": ("two images a step", {"views_per_step": 2}),
    "pull": ("each step pulls a change 1% of the way back to its start", {"pull": 0.01}),
    "zero": ("starting from zero instead of the detail model", {"start": "zero"}),
    "no-holdout": ("no image held out (the fit judged on its own images)", {"holdout": 0}),
    "pose": ("pose correction, exact cameras", {"pose": POSE_WEIGHT}),
    "exposure": ("exposure correction, exact exposure", {"exposure": EXPOSURE_WEIGHT}),
    "children": ("children", {"children": CHILD_GRADIENT}),
    # the first patch fit and its variants
    "four": ("patch fit: four fields (log-scales, opacity, DC colour, positions)", {**PATCH_FIT, "fields": FOUR}),
    "four-zero": ("patch fit: four fields, starting from zero", {**PATCH_FIT, "fields": FOUR, "start": "zero"}),
    "four-size-kept": ("patch fit: four fields, the anti-aliasing size kept (not halved per octave)",
                       {**PATCH_FIT, "fields": FOUR, "size_change": None}),
    "four-twice": ("patch fit: four fields, twice the steps (800)", {**PATCH_FIT, "fields": FOUR, "steps": 800}),
    "four-children": ("patch fit: four fields + children", {**PATCH_FIT, "fields": FOUR, "children": CHILD_GRADIENT}),
    "six": ("patch fit: six fields (+ rotations, SH bands): its default", PATCH_FIT),
    "six-children": ("patch fit: six fields + children", {**PATCH_FIT, "children": CHILD_GRADIENT}),
    "whole-images": ("patch fit: six fields, whole images instead of 96 px patches", {**PATCH_FIT, "patch": 0}),
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SPLITS["validation"]),
                        help="scenes (default: the validation split)")
    parser.add_argument("--seed", type=int, default=0, help="3DGS seed (default: %(default)s)")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
                        help="which rows (default: all)")
    parser.add_argument("--optimizer", choices=("visible", "adam"), default="visible",
                        help="the fit's optimiser (default: visible, superres.optim.VisibleAdam)")
    parser.add_argument("--steps", type=int, default=None,
                        help="fit steps per octave (default: each variant's; 10 with --smoke)")
    parser.add_argument("--smoke", action="store_true", help="the smallest size (experiment.SMOKE)")
    args = parser.parse_args(argv)
    protocol = (SMOKE if args.smoke else PROTOCOLS["quick"]).fits()
    steps = args.steps if args.steps is not None else (10 if args.smoke else None)
    detail = load_detail()
    print(f"{protocol.name}: training {protocol.resolutions} px, scored at 1x / 2x ({protocol.resolutions[-1]} / "
          f"{protocol.higher[-1]} px), {protocol.antialias} render; fit optimiser {args.optimizer}, steps "
          f"{steps or 'default'}; PSNR change at 2x / at 1x, seconds, Gaussians added", flush=True)
    table = {name: {} for name in args.variants}
    for scene in args.scenes:
        run = prepare_scene(scene, protocol, seed=args.seed, threads=1)
        k = protocol.train_stage
        base, lineage = run.stage_cloud(k), run.lineage(k + 1)
        views = load_nerf_synthetic(run.scene_dir, "train", resolution=run.log()[k]["resolution"])
        evaluate = Evaluator(run)

        def psnr(cloud, label, _evaluate=evaluate):
            return image_scores(cloud, _evaluate.views[label], _evaluate.background, no_reference=False,
                                antialias=protocol.antialias).psnr

        start = {label: psnr(base, label) for label in ("2x", "1x")}
        print(f"{scene}: unrefined {start['2x']:.2f} / {start['1x']:.2f} dB ({len(base):,} Gaussians)", flush=True)
        plain_steps = steps or image_config(protocol).max_steps  # the default fit's, once it has run
        for name in sorted(args.variants, key=lambda n: n != "default"):  # the default first
            config = image_config(protocol, args.seed, **({} if steps is None else {"steps": steps}))
            t0 = time.perf_counter()
            added = 0
            if name == "plain":
                cloud = fine_tune(base, views, plain_steps, seed=args.seed)
            elif name == "detail":
                cloud = refine(base, lineage=lineage, model=detail).cloud
            else:
                changes = {**VARIANTS[name][1], **({} if steps is None else {"steps": steps})}
                r = refine(base, images=views, lineage=lineage, model=detail,
                           fit=dataclasses.replace(config, **changes, optimizer=args.optimizer))
                cloud, added = r.cloud, len(r.added)
                if name == "default":  # (one image a step)
                    plain_steps = r.fit.steps_run
            seconds = time.perf_counter() - t0
            cell = (f"{psnr(cloud, '2x') - start['2x']:+.2f} / {psnr(cloud, '1x') - start['1x']:+.3f} / "
                    f"{seconds:.0f} s" + (f" / {added:,}" if added else ""))
            table[name][scene] = cell
            print(f"  {name}: {cell}", flush=True)
    print("\n| variant | " + " | ".join(args.scenes) + " |\n|---|" + "---|" * len(args.scenes))
    for name, cells in table.items():
        print(f"| {VARIANTS[name][0]} | " + " | ".join(cells.get(s, "-") for s in args.scenes) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
