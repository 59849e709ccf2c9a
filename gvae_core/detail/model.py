"""The detail model: each Gaussian's change per octave of sampling rate (`gvae_core.octaves`), from
its inputs (`features`).

A shared network reads the Gaussian's own values; one small network, the same for each of the
three axes, reads that and one axis's values and gives the axis's log-scale change; another gives
the opacity-logit change (and, when asked, the DC colour's). The last layers start at zero: an
untrained model changes nothing, so a trained one is judged only on what it learned. Changes are
bounded by tanh. Weights are a few tens of kilobytes.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ..rendering.compiled import numba_missing
from ..parallel import in_threads
from ..vae.model import EncoderBlock
from .features import AXIS, CONTEXT_COLUMNS, LINEAGE_COLUMNS, NODE, SHARED, DetailInputs

__all__ = ["DetailConfig", "DetailModel", "MAX_LOG_SCALE_CHANGE", "MAX_OPACITY_CHANGE", "MAX_DC_CHANGE"]

#: Bounds of one octave's change (tanh-limited).
MAX_LOG_SCALE_CHANGE = 2.0
MAX_OPACITY_CHANGE = 8.0
MAX_DC_CHANGE = 1.0


@dataclass
class DetailConfig:
    """Architecture and inputs. `lineage` / `context`: read the lineage's changes / the `neighbours`
    nearest Gaussians (off: those columns are zero; the neighbours measured worse on the
    validation scenes, BENCHMARKS.md, so they are off by default); `colour`: also change the DC
    colour;
    `encoder`: "transformer" adds the paper's lineage encoding (self-attention across the last
    lineage nodes, `vae.model.EncoderBlock`) to the inputs, and `masked_node` > 0 trains it also to
    predict the last node's change from the nodes before (the paper's masked-node objective, as an
    auxiliary loss of that weight)."""

    hidden: int = 64
    neighbours: int = 8
    lineage: bool = True
    context: bool = False
    colour: bool = False
    encoder: str = "features"
    masked_node: float = 0.0

    def __post_init__(self):
        if self.encoder not in ("features", "transformer"):
            raise ValueError(f"DetailConfig.encoder must be 'features' or 'transformer', got {self.encoder!r}")

    @property
    def inputs_neighbours(self) -> int:
        """How many neighbours the inputs need (0: none, the k-d tree is not built)."""
        return self.neighbours if self.context else 0

    def masks(self) -> tuple[np.ndarray, np.ndarray]:
        """(len(SHARED),), (len(AXIS),) float32: 1 for the input columns this model reads."""
        off = {"shared": set(), "axis": set()}
        for on, columns in ((self.lineage, LINEAGE_COLUMNS), (self.context, CONTEXT_COLUMNS)):
            if not on:
                for part in off:
                    off[part] |= set(columns[part])
        return (np.array([c not in off["shared"] for c in SHARED], np.float32),
                np.array([c not in off["axis"] for c in AXIS], np.float32))


class DetailModel(nn.Module):
    def __init__(self, config: DetailConfig | None = None):
        super().__init__()
        self.config = c = config or DetailConfig()
        self.meta: dict = {}  # how it was trained (saved with it)
        h = c.hidden
        shared_mask, axis_mask = c.masks()
        self.register_buffer("shared_mask", torch.from_numpy(shared_mask))
        self.register_buffer("axis_mask", torch.from_numpy(axis_mask))
        self.shared = nn.Sequential(nn.Linear(len(SHARED), h), nn.GELU(), nn.Linear(h, h), nn.GELU())
        self.axis = nn.Sequential(nn.Linear(h + len(AXIS), h), nn.GELU(), nn.Linear(h, 1))
        self.rest = nn.Sequential(nn.Linear(h + 2 * len(AXIS), h), nn.GELU(), nn.Linear(h, 1 + 3 * c.colour))
        for last in (self.axis[-1], self.rest[-1]):
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        if c.encoder == "transformer":
            self.node_embed = nn.Linear(len(NODE), h)
            self.age = nn.Embedding(3, h)
            self.encoder = EncoderBlock(h, 4, 2 * h)
            self.summary = nn.Sequential(nn.LayerNorm(2 * h), nn.Linear(2 * h, h))
            self.next_node = nn.Linear(2 * h, 4)  # the masked node: its log-scale (3) and opacity changes

    def _encode(self, nodes: torch.Tensor) -> torch.Tensor:
        """(M,T,len(NODE)) nodes -> (M,2h): the last node's encoding and the mean."""
        t = nodes.shape[1]
        age = torch.arange(t - 1, -1, -1, device=nodes.device)
        x = self.encoder(self.node_embed(nodes) + self.age(age)[None])
        return torch.cat([x[:, -1], x.mean(1)], -1)

    def auxiliary_loss(self, nodes: torch.Tensor) -> torch.Tensor:
        """The masked-node objective: the last node's change (log-scales, opacity) predicted from the
        nodes before it, mean squared error (0 without the transformer or a weight)."""
        if self.config.encoder != "transformer" or not self.config.masked_node:
            return nodes.new_zeros(())
        before = nodes[:, :-1].clone()
        before[..., :3] = before[..., :3] - before[:, -1:, :3]  # relative to the last node they see
        truth = torch.cat([nodes[:, -1, :3] - nodes[:, -2, :3], nodes[:, -1, 3:4] - nodes[:, -2, 3:4]], -1)
        return self.config.masked_node * ((self.next_node(self._encode(before)) - truth) ** 2).mean()

    def forward(self, shared: torch.Tensor, axis: torch.Tensor, nodes: torch.Tensor | None = None
                ) -> dict[str, torch.Tensor]:
        """(N,S), (N,3,A) [, (N,3,len(NODE)) with the transformer] inputs -> field -> change per
        octave: scales (N,3), opacities (N,) [, sh_dc (N,3)]."""
        shared = shared * self.shared_mask
        axis = axis * self.axis_mask
        h = self.shared(shared)
        if self.config.encoder == "transformer":
            h = h + self.summary(self._encode(nodes))
        ds = self.axis(torch.cat([h[:, None].expand(-1, 3, -1), axis], -1))[..., 0]
        rest = self.rest(torch.cat([h, axis.mean(1), axis.amax(1)], -1))
        out = {"scales": MAX_LOG_SCALE_CHANGE * torch.tanh(ds / MAX_LOG_SCALE_CHANGE),
               "opacities": MAX_OPACITY_CHANGE * torch.tanh(rest[:, 0] / MAX_OPACITY_CHANGE)}
        if self.config.colour:
            out["sh_dc"] = MAX_DC_CHANGE * torch.tanh(rest[:, 1:4] / MAX_DC_CHANGE)
        return out

    @torch.no_grad()
    def changes(self, inputs: DetailInputs, batch: int = 1 << 18) -> dict[str, np.ndarray]:
        """Changes per octave for every Gaussian of `inputs` (numpy float32), no gradient: by the
        compiled kernel (`kernels.model_rows`, rows in threads) where it applies (the `features`
        encoder, float32 weights on the CPU, Numba loads), else by `forward` in batches."""
        if self._compiled():
            return self._changes_compiled(inputs)
        parts: dict[str, list] = {}
        for i in range(0, max(len(inputs), 1), batch):
            out = self(*(torch.from_numpy(a[i:i + batch]) for a in (inputs.shared, inputs.axis, inputs.nodes)))
            for k, v in out.items():
                parts.setdefault(k, []).append(v.numpy())
        return {k: np.concatenate(v).astype(np.float32) for k, v in parts.items()}

    def _compiled(self) -> bool:
        p = self.shared[0].weight
        return (self.config.encoder == "features" and p.device.type == "cpu" and p.dtype == torch.float32
                and numba_missing() is None)

    def _changes_compiled(self, inputs: DetailInputs) -> dict[str, np.ndarray]:
        def weights(layer: nn.Linear) -> tuple[np.ndarray, np.ndarray]:  # (in, out) and (out,), float32
            return (np.ascontiguousarray(layer.weight.detach().numpy().T),
                    np.ascontiguousarray(layer.bias.detach().numpy()))

        h = self.config.hidden
        s1, s1b = weights(self.shared[0])
        s2, s2b = weights(self.shared[2])
        a1, a1b = weights(self.axis[0])
        a2, a2b = weights(self.axis[2])
        r1, r1b = weights(self.rest[0])
        r2, r2b = weights(self.rest[2])
        args = (self.shared_mask.numpy(), self.axis_mask.numpy(), s1, s1b, s2, s2b, np.ascontiguousarray(a1[:h]),
                np.ascontiguousarray(a1[h:]), a1b, np.ascontiguousarray(a2[:, 0]), a2b, r1, r1b, r2, r2b,
                np.float32(MAX_LOG_SCALE_CHANGE), np.float32(MAX_OPACITY_CHANGE), np.float32(MAX_DC_CHANGE))
        m = len(inputs)
        shared = np.ascontiguousarray(inputs.shared, np.float32)
        axis = np.ascontiguousarray(inputs.axis, np.float32)
        scales = np.empty((m, 3), np.float32)
        rest = np.empty((m, r2b.shape[0]), np.float32)
        kern = importlib.import_module(".kernels", __package__).model_rows
        in_threads(m, lambda a, b: kern(shared, axis, *args, a, b, scales, rest), chunk=1 << 14)
        out = {"scales": scales, "opacities": rest[:, 0].copy()}
        if self.config.colour:
            out["sh_dc"] = np.ascontiguousarray(rest[:, 1:4])
        return out

    def size_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())
