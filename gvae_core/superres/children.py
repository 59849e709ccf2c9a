"""Children that fade in with the octave: where the fit's higher-resolution loss asks for more
Gaussians than the cloud has (the 3DGS densification rule on its view-space gradients), new
Gaussians that draw nothing at the training sampling rate and appear above it.

A child's opacity logit is CHILD_LOGIT at its training rate: its opacity is below 1/255 there, so
the renderer (like every 3DGS renderer) skips it and the training-resolution picture is kept
exactly. Its change per octave brings it in: one octave up it is drawn as its parent would be split
or cloned by 3DGS at that resolution. A split parent is itself moved and shrunk by its change per
octave into the first of its two children, so the picture between octaves moves continuously.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import quaternions
from ..conventions import activate_scales
from ..densify import split_children

__all__ = ["CHILD_LOGIT", "Densified", "densify"]

#: A child's opacity logit at its training rate: sigmoid(-6) = 0.0025 < 1/255, so it draws nothing.
CHILD_LOGIT = -6.0


@dataclass
class Densified:
    """One round's decisions: `rows` (the Gaussians, input rows then children, that densify),
    `split` (which of them split rather than clone), the new children's state one octave up
    (field -> tensor) and, for the split ones, the parent's new state one octave up (means, scales)."""

    rows: torch.Tensor
    split: torch.Tensor
    children: dict[str, torch.Tensor]
    parent_means: torch.Tensor
    parent_scales: torch.Tensor


def densify(state: dict[str, torch.Tensor], grads: torch.Tensor, threshold: float, room: int, extent: float,
            generator: torch.Generator, percent_dense: float = 0.01) -> Densified:
    """The reference 3DGS rule on every Gaussian's state one octave up (`state`: field -> (R, ...)
    tensors) and its mean view-space gradient `grads` (NDC): those at or above `threshold` densify,
    at most `room` of them (the highest first); larger than `percent_dense` x `extent` they split in
    two (centres drawn from the Gaussian, scale / 1.6), smaller they are cloned."""
    high = grads >= threshold
    rows = torch.nonzero(high).flatten()
    if len(rows) > room:
        rows = rows[torch.topk(grads[rows], max(room, 0)).indices]
    rows = torch.sort(rows).values
    scales = state["scales"][rows]
    split = activate_scales(scales).max(1).values > percent_dense * extent
    children = {f: v[rows].clone() for f, v in state.items()}
    parent_means, parent_scales = children["means"].clone(), scales.clone()
    if bool(split.any()):
        rot = quaternions.to_rotmat(quaternions.normalize(children["quats"][split]))
        normals = torch.randn((2,) + tuple(scales[split].shape), generator=generator)
        means, log_scales = split_children(children["means"][split], scales[split], rot, normals[0], 2)
        other, _ = split_children(children["means"][split], scales[split], rot, normals[1], 2)
        children["means"][split] = other
        children["scales"][split] = log_scales
        parent_means[split] = means
        parent_scales[split] = log_scales
    return Densified(rows=rows, split=split, children=children, parent_means=parent_means,
                     parent_scales=parent_scales)

