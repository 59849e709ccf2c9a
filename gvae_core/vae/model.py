"""The lineage VAEs (DESIGN.md step 3) and the pair that refinement runs.

Each model encodes a lineage (its nodes, oldest first) with self-attention across stages into a
latent z, and decodes z, conditioned on the last node and on whether the Gaussian densifies at
this step, into a fixed number of child slots for the next stage: a state per slot (a change
relative to the last node) and an existence logit. The geometry model also predicts the
probability that the Gaussian densifies (spawns new Gaussians) at the next stage: refinement
samples it where the model decides alone ("Ours") and sets it where the Hessian budget has
chosen the Gaussians to densify ("Ours-∇²"). The prior is a normalising flow (`prior`).

Decoding: a child's centre is the last node's centre plus an offset in its local frame, in units
of its per-axis standard deviations (how 3DGS itself places split children), bounded by tanh;
its rotation is the last node's composed with a predicted relative rotation (so the geometry
model is rotation-equivariant); log-scale and appearance changes are bounded.

Files are `persistence`'s: `save_model` and `load_model` (this module knows none).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from .. import quaternions
from ..lineage import APP_EXIST, APP_OPACITY, APP_SH_DC, APP_SH_REST, GEO_EXIST, GEO_LOG_SCALE, GEO_POSITION, GEO_QUAT
from .features import FEATURE_OPACITY_RANGE, FEATURES, INPUTS, ParentFrame, clean_nodes, encoder_inputs
from .prior import FlowPrior, std_normal_logpdf

# Bounds on what the decoder may change in one step (tanh-limited).
MAX_OFFSET_SIGMAS = 4.0       # child centre offset, in parent standard deviations per axis
OFFSET_SPREAD_RANGE = (0.02, 3.0)  # spread of a child's offset around its slot's mean, same units
MAX_LOG_SCALE_CHANGE = 3.0
MAX_SH_CHANGE = 2.0
MAX_DC_CHANGE = 5.0
MAX_OPACITY_CHANGE = 8.0


@dataclass
class VAEConfig:
    """Architecture of one lineage VAE."""

    kind: str = "geometry"     # "geometry" | "appearance"
    d_model: int = 48
    heads: int = 4
    layers: int = 2
    latent: int = 16
    slots: int = 4
    decoder_hidden: int = 128
    flow_layers: int = 4
    flow_hidden: int = 64
    max_nodes: int = 8         # lineages longer than this keep their last max_nodes nodes (the
                               # longest history seen in training: older ones have no trained age)

    def __post_init__(self):
        if self.kind not in FEATURES:
            raise ValueError(f"VAEConfig.kind must be one of {sorted(FEATURES)}, got {self.kind!r}")


#: The size of the bundled models (both of them); `GaussianVAE.create` and `gvae fit-vae` default to it.
DEFAULT_SIZE = {"d_model": 32, "layers": 1, "decoder_hidden": 96, "max_nodes": 4}


@dataclass
class SlotPrediction:
    """Decoded next stage: per lineage C slots of node features (the `exist` column holds the
    existence probability), the existence logits, and the logit of densifying."""

    children: torch.Tensor     # (M,C,F) absolute node features in the normalised frame
    exist_logit: torch.Tensor  # (M,C)
    offsets: torch.Tensor | None = None  # geometry: child centres relative to the parent (M,C,3)
    densify_logit: torch.Tensor | None = None  # (M,) the Gaussian spawns new ones at the next stage
    local_mean: torch.Tensor | None = None     # geometry: mean child offset, parent frame, sigma units (M,C,3)
    local_spread: torch.Tensor | None = None   # geometry: its per-axis spread (M,C,3)


class EncoderBlock(nn.Module):
    """Pre-norm transformer block: self-attention across a lineage's nodes, then an MLP.
    A one-node lineage attends only to itself, so attention reduces to the value projection.
    Lineages are a few nodes long: attention is written out with broadcast products, which on
    the CPU is about twice as fast as the fused kernel for such short sequences."""

    def __init__(self, d_model: int, heads: int, hidden: int):
        super().__init__()
        if d_model % heads:
            raise ValueError(f"d_model {d_model} must be a multiple of heads {heads}")
        self.heads = heads
        self.norm1 = nn.LayerNorm(d_model)
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.out = nn.Linear(d_model, d_model)
        self.norm2 = nn.LayerNorm(d_model)
        self.mlp = nn.Sequential(nn.Linear(d_model, hidden), nn.GELU(), nn.Linear(hidden, d_model))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        m, t, d = h.shape
        q, k, v = self.qkv(self.norm1(h)).chunk(3, -1)
        if t == 1:
            a = v
        else:
            dh = d // self.heads
            q, k, v = (x.view(m, t, self.heads, dh) for x in (q, k, v))
            w = torch.softmax((q[:, :, None] * k[:, None]).sum(-1) * dh ** -0.5, 2)  # (m,t,s,heads)
            a = (w[..., None] * v[:, None]).sum(2).reshape(m, t, d)
        h = h + self.out(a)
        return h + self.mlp(self.norm2(h))


class LineageVAE(nn.Module):
    """Transformer encoder over lineage nodes -> latent z (with flow prior) -> slot decoder."""

    def __init__(self, config: VAEConfig):
        super().__init__()
        self.config = config
        c = config
        n_in = INPUTS[c.kind]
        self.state_dim = FEATURES[c.kind] - 1
        self.spread_dim = 3 if c.kind == "geometry" else 0  # per-axis spread of a child's offset
        self.embed = nn.Linear(n_in, c.d_model)
        self.age = nn.Embedding(c.max_nodes, c.d_model)  # index = nodes before the last one
        self.encoder = nn.Sequential(*(EncoderBlock(c.d_model, c.heads, 2 * c.d_model) for _ in range(c.layers)))
        self.norm = nn.LayerNorm(c.d_model)
        self.to_latent = nn.Linear(2 * c.d_model, 2 * c.latent)
        self.to_densify = nn.Linear(2 * c.d_model, 1)
        self.cond = nn.Linear(n_in, c.d_model)
        self.densify_embed = nn.Embedding(2, c.d_model)
        self.decoder = nn.Sequential(
            nn.Linear(c.latent + c.d_model, c.decoder_hidden), nn.GELU(),
            nn.Linear(c.decoder_hidden, c.decoder_hidden), nn.GELU(),
            nn.Linear(c.decoder_hidden, c.slots * (self.state_dim + 1 + self.spread_dim)))
        self.prior = FlowPrior(c.latent, c.flow_layers, c.flow_hidden)

    # -- encoder
    def _prepare(self, nodes: torch.Tensor) -> torch.Tensor:
        nodes = clean_nodes(nodes)
        if nodes.shape[1] > self.config.max_nodes:
            nodes = nodes[:, -self.config.max_nodes:]
        return nodes

    def encode(self, nodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(M,T,F) clean nodes -> posterior mean and log-variance (M,latent), and the logit of the
        probability that the Gaussian densifies at the next stage (M,)."""
        x = encoder_inputs(self.config.kind, nodes)
        t = nodes.shape[1]
        age = torch.arange(t - 1, -1, -1, device=nodes.device).clamp(max=self.config.max_nodes - 1)
        h = self.embed(x) + self.age(age)[None]
        h = self.norm(self.encoder(h))
        summary = torch.cat([h[:, -1], h.mean(1)], -1)
        mu, logvar = self.to_latent(summary).chunk(2, -1)
        return mu, logvar.clamp(-8.0, 4.0), self.to_densify(summary)[:, 0]

    # -- decoder
    def decode(self, z: torch.Tensor, nodes: torch.Tensor, densify: torch.Tensor,
               generator: torch.Generator | None = None, sample_offsets: bool = False) -> SlotPrediction:
        """Latent (M,latent), the lineage's clean nodes and whether it densifies (M,) -> C child
        slots of the next stage. Geometry slots predict a distribution of the child's centre
        (a mean offset and a per-axis spread in the parent's frame); `sample_offsets` draws
        the centres from it (refinement), else they are the means (training, evaluation)."""
        c = self.config
        x_last = encoder_inputs(c.kind, nodes[:, -1:])[:, 0]  # relative to itself: the same without history
        cond = torch.cat([z, self.cond(x_last) + self.densify_embed(densify.long())], -1)
        out = self.decoder(cond).view(len(z), c.slots, self.state_dim + 1 + self.spread_dim)
        raw, logit = out[..., :self.state_dim], out[..., self.state_dim]
        last = nodes[:, -1]
        if c.kind == "geometry":
            frame = ParentFrame.of(last)
            d = MAX_OFFSET_SIGMAS * torch.tanh(raw[..., GEO_POSITION] / MAX_OFFSET_SIGMAS)
            lo, hi = (math.log(v) for v in OFFSET_SPREAD_RANGE)
            spread = torch.exp(lo + (hi - lo) * torch.sigmoid(out[..., self.state_dim + 1:]))
            local = d
            if sample_offsets:
                eps = torch.randn(d.shape, generator=generator, device=d.device, dtype=d.dtype)
                local = (d + spread * eps).clamp(-MAX_OFFSET_SIGMAS, MAX_OFFSET_SIGMAS)
            world = torch.einsum("mij,mcj->mci", frame.rot, local * frame.sigma[:, None])
            pos = frame.pos[:, None] + world
            delta = quaternions.normalize(raw[..., GEO_QUAT] + raw.new_tensor([1.0, 0.0, 0.0, 0.0]))
            quat = quaternions.canonical(quaternions.multiply(frame.quat[:, None], delta))
            change = MAX_LOG_SCALE_CHANGE * torch.tanh(raw[..., GEO_LOG_SCALE] / MAX_LOG_SCALE_CHANGE)
            ls = frame.log_scale[:, None] + change
            children = torch.cat([pos, quat, ls, torch.sigmoid(logit)[..., None]], -1)
            return SlotPrediction(children, logit, world / frame.size[:, None, None], local_mean=d,
                                  local_spread=spread)
        sh = last[:, None, APP_SH_REST] + MAX_SH_CHANGE * torch.tanh(raw[..., APP_SH_REST] / MAX_SH_CHANGE)
        dc = last[:, None, APP_SH_DC] + MAX_DC_CHANGE * torch.tanh(raw[..., APP_SH_DC] / MAX_DC_CHANGE)
        op = (last[:, None, APP_OPACITY, None].clamp(*FEATURE_OPACITY_RANGE)
              + MAX_OPACITY_CHANGE * torch.tanh(raw[..., APP_OPACITY, None] / MAX_OPACITY_CHANGE))
        children = torch.cat([sh, dc, op, torch.sigmoid(logit)[..., None]], -1)
        return SlotPrediction(children, logit)

    def forward(self, nodes: torch.Tensor, densify: torch.Tensor | None = None, *, sample: bool = True,
                generator: torch.Generator | None = None):
        """Encode, draw z ~ q(z|x) (or take its mean), decode given `densify` (M,) flags (default:
        the model's own prediction, probability > 1/2). Returns (prediction, mu, logvar, z); the
        prediction carries the densification logit."""
        nodes = self._prepare(nodes)
        mu, logvar, densify_logit = self.encode(nodes)
        if sample:
            eps = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
            z = mu + (0.5 * logvar).exp() * eps
        else:
            z = mu
        flags = densify_logit > 0 if densify is None else torch.as_tensor(densify, device=mu.device)
        pred = self.decode(z, nodes, flags.reshape(-1))
        pred.densify_logit = densify_logit
        return pred, mu, logvar, z

    def kl(self, mu: torch.Tensor, logvar: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Monte-Carlo KL(q(z|x) || p_psi(z)) per lineage: log q(z|x) - log p_psi(z)."""
        eps = (z - mu) * (-0.5 * logvar).exp()
        log_q = std_normal_logpdf(eps) - 0.5 * logvar.sum(-1)
        return log_q - self.prior.log_prob(z)


def model_bytes(model: nn.Module) -> int:
    """Size of the float32 weights in bytes."""
    return sum(p.numel() * p.element_size() for p in model.state_dict().values())


@dataclass
class GaussianVAE:
    """The geometry and appearance models plus what is known about their training."""

    geometry: LineageVAE
    appearance: LineageVAE
    meta: dict = field(default_factory=dict)

    @classmethod
    def create(cls, geometry: VAEConfig | None = None, appearance: VAEConfig | None = None,
               seed: int = 0, **size) -> GaussianVAE:
        """Untrained models. Configs not given are the bundled models' size (`DEFAULT_SIZE`),
        with `size` (VAEConfig fields, for both) overriding it."""
        torch.manual_seed(seed)
        size = {**DEFAULT_SIZE, **size}
        g = LineageVAE(geometry or VAEConfig(kind="geometry", **size))
        a = LineageVAE(appearance or VAEConfig(kind="appearance", **size))
        if g.config.slots != a.config.slots:
            raise ValueError("geometry and appearance models need the same number of slots")
        return cls(g.eval(), a.eval())

    @property
    def slots(self) -> int:
        return self.geometry.config.slots

    @torch.no_grad()
    def predict(self, history_geometry, history_appearance, densify=None, *, sample: bool = True,
                generator: torch.Generator | None = None, batch: int = 65536):
        """Next-stage slots for M lineages: child geometry (M,C,11), appearance (M,C,50), existence
        probability (M,C) (the geometry model's, the appearance model's or their mean, as
        `meta["existence"]` says; `fit-vae` picks the most accurate on held-out runs) and the
        densification flags (M,) the slots were decoded with: `densify` when given, else drawn
        from the geometry model's probability. Batched, no gradients."""
        hg = torch.as_tensor(history_geometry, dtype=torch.float32)
        ha = torch.as_tensor(history_appearance, dtype=torch.float32)
        given = None
        if densify is not None:
            given = torch.as_tensor(np.asarray(densify, bool)).reshape(-1)
            if len(given) != len(hg):
                raise ValueError(f"predict: {len(given)} densify flags for {len(hg)} lineages")
        outs_g, outs_a, used = [], [], []
        for i in range(0, max(len(hg), 1), batch):
            nodes = self.geometry._prepare(hg[i:i + batch])
            mu, logvar, logit = self.geometry.encode(nodes)
            if given is None:
                f = torch.rand(logit.shape, generator=generator) < torch.sigmoid(logit)
            else:
                f = given[i:i + batch]
            z = mu + (0.5 * logvar).exp() * torch.randn(mu.shape, generator=generator) if sample else mu
            outs_g.append(self.geometry.decode(z, nodes, f, generator, sample_offsets=sample).children)
            outs_a.append(self.appearance(ha[i:i + batch], f, sample=sample, generator=generator)[0].children)
            used.append(f)
        def join(parts):  # without a copy in the usual case of a single batch
            return parts[0] if len(parts) == 1 else torch.cat(parts)

        flags = join(used) if len(hg) else torch.zeros(0, dtype=torch.bool)
        g = join(outs_g) if len(hg) else torch.zeros((0, self.slots, FEATURES["geometry"]))
        a = join(outs_a) if len(hg) else torch.zeros((0, self.slots, FEATURES["appearance"]))
        source = self.meta.get("existence", "geometry")
        p = {"geometry": g[..., GEO_EXIST], "appearance": a[..., APP_EXIST]}.get(
            source, 0.5 * (g[..., GEO_EXIST] + a[..., APP_EXIST]))
        return g, a, p.clone(), flags

    def sizes(self) -> dict[str, int]:
        return {"geometry": model_bytes(self.geometry), "appearance": model_bytes(self.appearance)}
