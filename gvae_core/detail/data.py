"""Examples to learn from: the stages of progressive training runs, each with the real training
views at the higher resolutions it should be drawn at."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..antialias import DILATION_KEY, FILTER_KEY, with_training_cameras
from ..capture import load_nerf_synthetic
from ..lineage import Lineage
from ..ply import read_ply
from .features import detail_inputs
from .fit import Example

__all__ = ["SCALES", "run_examples"]

#: The higher resolutions a refine stands for, as factors of the training resolution.
SCALES = {"1.5x": 1.5, "2x": 2.0}


def run_examples(run_dir, scene_dir, stages: Sequence[int], *, scales: dict[str, float] | None = None,
                 neighbours: int = 8, name: str | None = None, inputs: bool = True,
                 without_lineage: bool = False) -> list[Example]:
    """One `Example` per stage of the run in `run_dir` (its `stage_<k>.ply` and `lineage.npz` cut
    there), with the scene's training views at `scales` times the stage's resolution (never
    upsampled: scales above the scene's images are left out). `without_lineage`: one more per
    stage, the same cloud and views with the inputs of a cloud without history (a user's PLY)."""
    run_dir, scene_dir = Path(run_dir), Path(scene_dir)
    full = Lineage.load(run_dir / "lineage.npz")
    native = load_nerf_synthetic(scene_dir, "train")
    out = []
    for k in stages:
        lineage = full.prefix(k + 1)
        res = lineage.resolutions[k]
        cloud = read_ply(run_dir / f"stage_{k}.ply")
        if not {DILATION_KEY, FILTER_KEY} & set(cloud.extra):
            cloud = with_training_cameras(cloud, native.cameras, resolution=res)
        views = {label: native.at_resolution(int(round(res * factor))) for label, factor in (scales or SCALES).items()
                 if int(round(res * factor)) <= native.images.shape[1]}
        label = f"{name or run_dir.name}/stage_{k}"
        feats = detail_inputs(cloud, lineage, neighbours=neighbours) if inputs else None
        out.append(Example(cloud, feats, views, name=label))
        if without_lineage:
            feats = detail_inputs(cloud, None, neighbours=neighbours) if inputs else None
            out.append(Example(cloud, feats, views, name=label + " (no lineage)"))
    return out
