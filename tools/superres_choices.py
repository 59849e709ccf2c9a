"""The choices of refine with the capture's images (`refine(images=...)`, `gvae_core.superres`), made on
the validation scenes: each variant of the fit beside the same steps of plain training at 1x and the
detail model alone, as PSNR change at 2x / at 1x against the unrefined cloud, seconds of the whole
refine and Gaussians added (docs/benchmarks/refine-images.md, "Choices").

The runs are the quick protocol's trained to the training resolution only (`Protocol.data()`, the
runs `make train-model` learns and validates on; cached), scored on its 8 test views with its
`matched` render over white. `--optimizer adam` runs the fit with torch's plain Adam, as it was before
`superres.optim.VisibleAdam` (the table's earlier rows); `--smoke` runs everything at the smallest size
(`experiment.SMOKE`: 64 px scenes, 10 fit steps), to show that it runs.

Usage: python tools/superres_choices.py [--scenes chair tableware] [--seed 0] [--variants NAME ...]
                                        [--optimizer visible|adam] [--steps 400] [--smoke]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

from gvae_core.benchmarks.superres import optimizer_used
from gvae_core.capture import load_nerf_synthetic
from gvae_core.detail import load_detail
from gvae_core.experiment import PROTOCOLS, SMOKE, Evaluator, image_config, prepare_scene
from gvae_core.metrics.image import image_scores
from gvae_core.refinement import refine
from gvae_core.scenes import SPLITS
from gvae_core.superres import CHILD_GRADIENT, EXPOSURE_WEIGHT, POSE_WEIGHT
from gvae_core.train import fine_tune

FOUR = ("scales", "opacities", "sh_dc", "means")
#: name -> (what the table calls it, `SuperResConfig` changes); "plain" and "detail" are not fits.
VARIANTS = {
    "plain": ("the same steps of plain 1x training", None),
    "detail": ("the detail model alone (no images)", None),
    "four": ("four fields (log-scales, opacity, DC colour, positions)", {"fields": FOUR}),
    "four-zero": ("four fields, starting from zero", {"fields": FOUR, "start": "zero"}),
    "four-size-kept": ("four fields, the anti-aliasing size kept (not halved per octave)",
                       {"fields": FOUR, "size_change": None}),
    "four-twice": ("four fields, twice the steps (800)", {"fields": FOUR}),
    "four-children": ("four fields + children", {"fields": FOUR, "children": CHILD_GRADIENT}),
    "six": ("six fields (+ rotations, SH bands): the default", {}),
    "six-children": ("six fields + children", {"children": CHILD_GRADIENT}),
    "whole-images": ("six fields, whole images instead of 96 px patches", {"patch": 0}),
    "pose": ("six fields, pose correction, exact cameras", {"pose": POSE_WEIGHT}),
    "exposure": ("six fields, exposure correction, exact exposure", {"exposure": EXPOSURE_WEIGHT}),
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
                        help="fit steps per octave (default: the fit's, 400; 10 with --smoke)")
    parser.add_argument("--smoke", action="store_true", help="the smallest size (experiment.SMOKE)")
    args = parser.parse_args(argv)
    protocol = (SMOKE if args.smoke else PROTOCOLS["quick"]).data(0)
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
        for name in args.variants:
            config = image_config(protocol, args.seed, **({} if steps is None else {"steps": steps}))
            t0 = time.perf_counter()
            added = 0
            if name == "plain":
                cloud = fine_tune(base, views, config.steps, seed=args.seed)
            elif name == "detail":
                cloud = refine(base, lineage=lineage, model=detail).cloud
            else:
                changes = {**VARIANTS[name][1], **({"steps": 2 * config.steps} if name == "four-twice" else {})}
                with optimizer_used(args.optimizer):
                    r = refine(base, images=views, lineage=lineage, model=detail,
                               fit=dataclasses.replace(config, **changes))
                cloud, added = r.cloud, len(r.added)
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
