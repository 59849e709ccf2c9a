"""What the models see of a lineage: its node features (layout in `gvae_core.lineage`), cleaned,
bounded and expressed relative to the last node (the parent of the next stage).

Geometry inputs are in the last node's local frame (rotation-invariant): positions as offsets in
units of its per-axis standard deviations, rotations relative to its rotation, log-scales as
differences, plus its absolute log-scale in the scene-normalised frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import quaternions
from ..lineage import (APP_EXIST, APP_OPACITY, APP_SH_DC, APP_SH_REST, APPEARANCE_DIM, GEO_EXIST, GEO_LOG_SCALE,
                       GEO_POSITION, GEO_QUAT, GEOMETRY_DIM)

#: Node features per model.
FEATURES = {"geometry": GEOMETRY_DIM, "appearance": APPEARANCE_DIM}
#: Encoder inputs per node: geometry has the relative and the absolute log-scale.
INPUTS = {"geometry": GEOMETRY_DIM + 3, "appearance": APPEARANCE_DIM}

# Bounds on features on use (normalised frame): a few wild Gaussians must not dominate a batch.
FEATURE_LOG_SCALE_RANGE = (-20.0, 10.0)
FEATURE_OPACITY_RANGE = (-12.0, 12.0)
FEATURE_POSITION_LIMIT = 1e6
SH_REST_LIMIT = 5.0


def clean_nodes(nodes: torch.Tensor) -> torch.Tensor:
    """Finite, bounded copies of node features (non-finite -> 0, huge values clamped)."""
    nodes = torch.nan_to_num(nodes.float(), nan=0.0, posinf=FEATURE_POSITION_LIMIT, neginf=-FEATURE_POSITION_LIMIT)
    return nodes.clamp(-FEATURE_POSITION_LIMIT, FEATURE_POSITION_LIMIT)


@dataclass
class ParentFrame:
    """The last node of each lineage, as the decoder's reference: centre, rotation, per-axis
    standard deviations, mean size (all in the normalised frame)."""

    pos: torch.Tensor      # (M,3)
    quat: torch.Tensor     # (M,4) unit
    rot: torch.Tensor      # (M,3,3)
    log_scale: torch.Tensor  # (M,3) clamped
    sigma: torch.Tensor    # (M,3)
    size: torch.Tensor     # (M,) exp(mean log-scale)

    @classmethod
    def of(cls, last: torch.Tensor) -> ParentFrame:
        quat = quaternions.canonical(last[:, GEO_QUAT])
        ls = last[:, GEO_LOG_SCALE].clamp(*FEATURE_LOG_SCALE_RANGE)
        return cls(pos=last[:, GEO_POSITION], quat=quat, rot=quaternions.to_rotmat(quat), log_scale=ls,
                   sigma=ls.exp(), size=ls.mean(-1).exp())

    def relative(self, pos: torch.Tensor) -> torch.Tensor:
        """Positions (M,...,3) as offsets from the parent in units of its mean size."""
        shape = (-1,) + (1,) * (pos.dim() - 2) + (3,)
        return (pos - self.pos.view(shape)) / self.size.view(shape[:-1] + (1,))

    def local(self, pos: torch.Tensor) -> torch.Tensor:
        """Positions (M,T,3) in the parent's local frame, in units of its per-axis sigmas."""
        d = torch.einsum("mji,mtj->mti", self.rot, pos - self.pos[:, None])
        return d / self.sigma[:, None]


def encoder_inputs(kind: str, nodes: torch.Tensor) -> torch.Tensor:
    """Model inputs (M,T,INPUTS[kind]) from clean node features (M,T,F), relative to the last node."""
    if kind == "geometry":
        frame = ParentFrame.of(nodes[:, -1])
        rel = torch.asinh(frame.local(nodes[..., GEO_POSITION]))
        q = quaternions.canonical(quaternions.multiply(quaternions.conjugate(frame.quat)[:, None],
                                                       quaternions.canonical(nodes[..., GEO_QUAT])))
        ls = nodes[..., GEO_LOG_SCALE].clamp(*FEATURE_LOG_SCALE_RANGE)
        rel_ls = (ls - frame.log_scale[:, None]).clamp(-10.0, 10.0)
        abs_ls = ls.clamp(-15.0, 5.0) / 5.0
        return torch.cat([rel, q, rel_ls, abs_ls, nodes[..., GEO_EXIST, None]], -1)
    sh = nodes[..., APP_SH_REST].clamp(-SH_REST_LIMIT, SH_REST_LIMIT)
    dc = nodes[..., APP_SH_DC].clamp(-10.0, 10.0) / 3.0
    op = nodes[..., APP_OPACITY, None].clamp(*FEATURE_OPACITY_RANGE) / 4.0
    return torch.cat([sh, dc, op, nodes[..., APP_EXIST, None]], -1)
