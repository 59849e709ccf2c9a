"""Lineage transformer VAEs (DESIGN.md step 3): geometry (11 features per node) and appearance (50).

Each model encodes a lineage (its nodes, oldest first) with self-attention across stages into a
latent z, and decodes z, conditioned on the last node and on whether the Gaussian densifies at
this step, into a fixed number of child slots for the next stage: a state per slot (a change
relative to the last node) and an existence logit. The geometry model also predicts the
probability that the Gaussian densifies (spawns new Gaussians) at the next stage: refinement
samples it where the model decides alone ("Ours") and sets it where the Hessian budget has
chosen the Gaussians to densify ("Ours-∇²").
The prior p_psi(z) is a RealNVP-style normalising flow (affine coupling layers with an exact
inverse); the KL term is Monte-Carlo: log q(z|x) - log p_psi(z) at the sampled z.

Parametrisation (so that one model serves every scene and every scale):
- geometry inputs are in the last node's local frame (rotation-invariant): positions as offsets
  in units of its per-axis standard deviations, rotations relative to its rotation, log-scales as
  differences, plus its absolute log-scale in the scene-normalised frame;
- a child's centre is the last node's centre plus an offset in its local frame, in units of its
  per-axis standard deviations (how 3DGS itself places split children), bounded by tanh; its
  rotation is the last node's composed with a predicted relative rotation (so the geometry model
  is rotation-equivariant);
- log-scale and appearance changes are bounded; quaternions are renormalised.
Losses are computed in the same parent-relative frame (see `transition_loss`).
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from .cloud import SH_C0, normalize_quats, quat_to_rotmat

GEOMETRY_FEATURES = 11
APPEARANCE_FEATURES = 50
FEATURES = {"geometry": GEOMETRY_FEATURES, "appearance": APPEARANCE_FEATURES}
_INPUTS = {"geometry": 14, "appearance": 50}

# Bounds on what the decoder may change in one step (tanh-limited), and on inputs.
MAX_OFFSET_SIGMAS = 4.0       # child centre offset, in parent standard deviations per axis
OFFSET_SPREAD_RANGE = (0.02, 3.0)  # spread of a child's offset around its slot's mean, same units
MAX_LOG_SCALE_CHANGE = 3.0
MAX_SH_CHANGE = 2.0
MAX_DC_CHANGE = 5.0
MAX_OPACITY_CHANGE = 8.0
FEATURE_LOG_SCALE_RANGE = (-20.0, 10.0)   # log-scales in the normalised frame, on use
FEATURE_OPACITY_RANGE = (-12.0, 12.0)
FEATURE_POSITION_LIMIT = 1e6


# ----------------------------------------------------------------------------- features

def _canonical_quats(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions with w >= 0 (q and -q are the same rotation)."""
    q = normalize_quats(q)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a*b of (...,4) w,x,y,z quaternions (rotation b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


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
    def of(cls, last: torch.Tensor) -> "ParentFrame":
        quat = _canonical_quats(last[:, 3:7])
        ls = last[:, 7:10].clamp(*FEATURE_LOG_SCALE_RANGE)
        return cls(pos=last[:, 0:3], quat=quat, rot=quat_to_rotmat(quat), log_scale=ls, sigma=ls.exp(),
                   size=ls.mean(-1).exp())

    def relative(self, pos: torch.Tensor) -> torch.Tensor:
        """Positions (M,...,3) as offsets from the parent in units of its mean size."""
        shape = (-1,) + (1,) * (pos.dim() - 2) + (3,)
        return (pos - self.pos.view(shape)) / self.size.view(shape[:-1] + (1,))

    def local(self, pos: torch.Tensor) -> torch.Tensor:
        """Positions (M,T,3) in the parent's local frame, in units of its per-axis sigmas."""
        d = torch.einsum("mji,mtj->mti", self.rot, pos - self.pos[:, None])
        return d / self.sigma[:, None]


def encoder_inputs(kind: str, nodes: torch.Tensor) -> torch.Tensor:
    """Model inputs (M,T,F_in) from clean node features (M,T,F), relative to the last node."""
    if kind == "geometry":
        frame = ParentFrame.of(nodes[:, -1])
        rel = torch.asinh(frame.local(nodes[..., 0:3]))
        q = _canonical_quats(quat_multiply(quat_conjugate(frame.quat)[:, None], _canonical_quats(nodes[..., 3:7])))
        ls = nodes[..., 7:10].clamp(*FEATURE_LOG_SCALE_RANGE)
        rel_ls = (ls - frame.log_scale[:, None]).clamp(-10.0, 10.0)
        abs_ls = ls.clamp(-15.0, 5.0) / 5.0
        return torch.cat([rel, q, rel_ls, abs_ls, nodes[..., 10:11]], -1)
    sh = nodes[..., 0:45].clamp(-5.0, 5.0)
    dc = nodes[..., 45:48].clamp(-10.0, 10.0) / 3.0
    op = nodes[..., 48:49].clamp(*FEATURE_OPACITY_RANGE) / 4.0
    return torch.cat([sh, dc, op, nodes[..., 49:50]], -1)


# ----------------------------------------------------------------------------- flow prior

class AffineCoupling(nn.Module):
    """One RealNVP coupling layer: the masked half conditions a scale and shift of the other."""

    def __init__(self, dim: int, hidden: int, mask: torch.Tensor):
        super().__init__()
        self.register_buffer("mask", mask)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
                                 nn.Linear(hidden, 2 * dim))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def _st(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, t = self.net(x * self.mask).chunk(2, -1)
        keep = 1.0 - self.mask
        return 2.0 * torch.tanh(s / 2.0) * keep, t * keep

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, t = self._st(x)
        return x * s.exp() + t, s.sum(-1)

    def inverse(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, t = self._st(y)  # the masked half is unchanged, so s, t are recomputed exactly
        return (y - t) * (-s).exp(), -s.sum(-1)


class FlowPrior(nn.Module):
    """p_psi(z) = N(T^-1(z); 0, I) |det dT^-1/dz| with T a stack of affine couplings."""

    def __init__(self, dim: int, layers: int = 4, hidden: int = 64):
        super().__init__()
        masks = [(torch.arange(dim) % 2 == (i % 2)).float() for i in range(layers)]
        self.layers = nn.ModuleList(AffineCoupling(dim, hidden, m) for m in masks)
        self.dim = dim

    def forward(self, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """z = T(eps) and log|det dT/deps|."""
        logdet = eps.new_zeros(eps.shape[:-1])
        for layer in self.layers:
            eps, ld = layer(eps)
            logdet = logdet + ld
        return eps, logdet

    def inverse(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """eps = T^-1(z) and log|det dT^-1/dz|."""
        logdet = z.new_zeros(z.shape[:-1])
        for layer in reversed(self.layers):
            z, ld = layer.inverse(z)
            logdet = logdet + ld
        return z, logdet

    def log_prob(self, z: torch.Tensor) -> torch.Tensor:
        eps, logdet = self.inverse(z)
        return _std_normal_logpdf(eps) + logdet

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        eps = torch.randn(n, self.dim, generator=generator)
        return self.forward(eps)[0]


def _std_normal_logpdf(x: torch.Tensor) -> torch.Tensor:
    return -0.5 * (x * x).sum(-1) - 0.5 * x.shape[-1] * math.log(2.0 * math.pi)


def cyclic_beta(t: int, alpha: float, period: int) -> float:
    """Cyclic KL annealing beta(t) = min(alpha * (t mod R), 1)."""
    return min(alpha * (t % max(int(period), 1)), 1.0)


# ----------------------------------------------------------------------------- the model

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
        n_in = _INPUTS[c.kind]
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
            d = MAX_OFFSET_SIGMAS * torch.tanh(raw[..., 0:3] / MAX_OFFSET_SIGMAS)
            lo, hi = (math.log(v) for v in OFFSET_SPREAD_RANGE)
            spread = torch.exp(lo + (hi - lo) * torch.sigmoid(out[..., self.state_dim + 1:]))
            local = d
            if sample_offsets:
                eps = torch.randn(d.shape, generator=generator, device=d.device, dtype=d.dtype)
                local = (d + spread * eps).clamp(-MAX_OFFSET_SIGMAS, MAX_OFFSET_SIGMAS)
            world = torch.einsum("mij,mcj->mci", frame.rot, local * frame.sigma[:, None])
            pos = frame.pos[:, None] + world
            delta = normalize_quats(raw[..., 3:7] + raw.new_tensor([1.0, 0.0, 0.0, 0.0]))
            quat = _canonical_quats(quat_multiply(frame.quat[:, None], delta))
            ls = frame.log_scale[:, None] + MAX_LOG_SCALE_CHANGE * torch.tanh(raw[..., 7:10] / MAX_LOG_SCALE_CHANGE)
            children = torch.cat([pos, quat, ls, torch.sigmoid(logit)[..., None]], -1)
            return SlotPrediction(children, logit, world / frame.size[:, None, None], local_mean=d,
                                  local_spread=spread)
        sh = last[:, None, 0:45] + MAX_SH_CHANGE * torch.tanh(raw[..., 0:45] / MAX_SH_CHANGE)
        dc = last[:, None, 45:48] + MAX_DC_CHANGE * torch.tanh(raw[..., 45:48] / MAX_DC_CHANGE)
        op = (last[:, None, 48:49].clamp(*FEATURE_OPACITY_RANGE)
              + MAX_OPACITY_CHANGE * torch.tanh(raw[..., 48:49] / MAX_OPACITY_CHANGE))
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
        log_q = _std_normal_logpdf(eps) - 0.5 * logvar.sum(-1)
        return log_q - self.prior.log_prob(z)


def model_bytes(model: nn.Module) -> int:
    """Size of the float32 weights in bytes."""
    return sum(p.numel() * p.element_size() for p in model.state_dict().values())


# ----------------------------------------------------------------------------- data

@dataclass
class TransitionData:
    """One stage transition as plain arrays (the fields of `gvae_core.lineage.Transition`), plus
    whether each Gaussian densified (spawned a Gaussian that is not itself)."""

    history_geometry: np.ndarray    # (M,T,11)
    history_appearance: np.ndarray  # (M,T,50)
    child_geometry: np.ndarray      # (M,C,11)
    child_appearance: np.ndarray    # (M,C,50)
    child_mask: np.ndarray          # (M,C) bool
    stage: int = 1
    source: str = ""
    densified: np.ndarray | None = None  # (M,) bool; default: two or more children

    def __post_init__(self):
        m, t = self.history_geometry.shape[:2]
        shapes = {"history_geometry": (m, t, 11), "history_appearance": (m, t, 50),
                  "child_geometry": (m, None, 11), "child_appearance": (m, None, 50), "child_mask": (m, None)}
        for name, shape in shapes.items():
            got = getattr(self, name).shape
            if len(got) != len(shape) or any(s is not None and s != g for s, g in zip(shape, got)):
                raise ValueError(f"TransitionData.{name} has shape {got}, expected {shape} (None = any)")
        if self.densified is None:
            self.densified = self.child_mask.sum(1) >= 2
        self.densified = np.asarray(self.densified, bool).reshape(m)

    @classmethod
    def from_transition(cls, tr: Any, stage: int = 1, source: str = "") -> "TransitionData":
        """From a `gvae_core.lineage.Transition` (duck-typed)."""
        new_child = (np.asarray(tr.child_ids) != np.asarray(tr.history.ids)[:, None]) & np.asarray(tr.child_mask, bool)
        return cls(np.asarray(tr.history.geometry, np.float32), np.asarray(tr.history.appearance, np.float32),
                   np.asarray(tr.child_geometry, np.float32), np.asarray(tr.child_appearance, np.float32),
                   np.asarray(tr.child_mask, bool), stage, source, new_child.any(1))

    def __len__(self) -> int:
        return len(self.history_geometry)

    def subset(self, index: np.ndarray) -> "TransitionData":
        return TransitionData(self.history_geometry[index], self.history_appearance[index],
                              self.child_geometry[index], self.child_appearance[index], self.child_mask[index],
                              self.stage, self.source, self.densified[index])


def synthetic_transitions(n: int = 512, stages: int = 3, *, seed: int = 0,
                          split_prob: float = 0.35, clone_prob: float = 0.15) -> list[TransitionData]:
    """Synthetic lineages that densify like 3DGS: per stage each Gaussian survives with jitter,
    splits into two children (scale / 1.6, centres sampled from the parent) or clones itself
    (the parent stays, a copy appears next to it). Features as in DESIGN.md, normalised frame."""
    rng = np.random.default_rng(seed)
    geom = np.zeros((n, 11), np.float32)
    geom[:, 0:3] = rng.uniform(-1, 1, (n, 3))
    q = rng.normal(size=(n, 4))
    geom[:, 3:7] = q / np.linalg.norm(q, axis=1, keepdims=True)
    geom[:, 7:10] = np.log(0.06) + rng.normal(0, 0.3, (n, 3))
    geom[:, 10] = 1
    app = np.zeros((n, 50), np.float32)
    app[:, 0:45] = rng.normal(0, 0.05, (n, 45))
    app[:, 45:48] = rng.normal(0, 1.0, (n, 3))
    app[:, 48] = rng.normal(1.0, 1.0, n)
    app[:, 49] = 1
    hist_g, hist_a = geom[:, None].copy(), app[:, None].copy()
    out = []
    for stage in range(1, stages):
        m = len(hist_g)
        last_g, last_a = hist_g[:, -1], hist_a[:, -1]
        u = rng.uniform(size=m)
        split, clone = u < split_prob, (u >= split_prob) & (u < split_prob + clone_prob)
        cg = np.zeros((m, 2, 11), np.float32)
        ca = np.zeros((m, 2, 50), np.float32)
        mask = np.zeros((m, 2), bool)
        rot = quat_to_rotmat(last_g[:, 3:7].astype(np.float64))
        sig = np.exp(last_g[:, 7:10].astype(np.float64))
        for c in range(2):
            cg[:, c] = last_g
            ca[:, c] = last_a
            local = rng.normal(size=(m, 3)) * sig
            off = np.einsum("mij,mj->mi", rot, local)
            jitter = np.einsum("mij,mj->mi", rot, rng.normal(0, 0.05, (m, 3)) * sig)
            cg[:, c, 0:3] += np.where(split[:, None], off, jitter if c == 0 else 0.5 * off)
            cg[:, c, 7:10] += np.where(split[:, None], -math.log(1.6), 0.0) + rng.normal(0, 0.02, (m, 3))
            ca[:, c, 45:48] += rng.normal(0, 0.05, (m, 3))
            ca[:, c, 48] += np.where(split, -0.3, 0.1)
        mask[:, 0] = True
        mask[:, 1] = split | clone
        out.append(TransitionData(hist_g, hist_a, cg, ca, mask, stage, "synthetic", split | clone))
        # Next stage's lineages: every child, its history the parent's (exist = 0 for new ones).
        parent = np.concatenate([np.arange(m), np.flatnonzero(mask[:, 1])])
        slot = np.concatenate([np.zeros(m, int), np.ones(int(mask[:, 1].sum()), int)])
        new_g, new_a = hist_g[parent].copy(), hist_a[parent].copy()
        new_g[slot == 1, :, 10] = 0
        new_a[slot == 1, :, 49] = 0
        hist_g = np.concatenate([new_g, cg[parent, slot][:, None]], 1)
        hist_a = np.concatenate([new_a, ca[parent, slot][:, None]], 1)
    return out


def lineage_transitions(lineage: Any, source: str = "", max_children: int = 4) -> list[TransitionData]:
    """Every stage transition of a `gvae_core.lineage.Lineage` (children beyond `max_children`
    per parent are dropped, as `Lineage.transitions` reports)."""
    return [TransitionData.from_transition(lineage.transitions(s, max_children=max_children), s, source)
            for s in range(1, lineage.n_stages)]


# ----------------------------------------------------------------------------- matching and loss

_PERMS: dict[int, torch.Tensor] = {}


def _permutations(c: int) -> torch.Tensor:
    if c not in _PERMS:
        _PERMS[c] = torch.tensor(list(itertools.permutations(range(c))), dtype=torch.long)
    return _PERMS[c]


def match_slots(cost: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Optimal assignment of true children to predicted slots, exhaustively over permutations
    (C is small). cost (M,S,C) slot-to-child cost, mask (M,C) which children exist (C <= S).
    Returns (M,C) the slot of each child (meaningless where mask is False)."""
    m, s, c = cost.shape
    perms = _permutations(s)[:, :c]                              # (P,C): child j -> slot perms[p,j]
    picked = cost[:, perms, torch.arange(c)[None, :]]            # (M,P,C)
    total = (picked * mask[:, None, :].to(cost.dtype)).sum(-1)
    best = total.argmin(1)
    return perms[best]


def match_slots_reference(cost: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Slow reference of `match_slots`: the Hungarian algorithm per lineage (scipy)."""
    from scipy.optimize import linear_sum_assignment  # noqa: PLC0415

    out = np.zeros(mask.shape, np.int64)
    for i in range(len(cost)):
        cols = np.flatnonzero(mask[i])
        if len(cols):
            rows, js = linear_sum_assignment(cost[i][:, cols].T)
            out[i, cols[rows]] = js
    return out


@dataclass
class LossWeights:
    """Loss weights: the paper's 1e-6 KL, 1.0 MSE (colour, opacity) and 0.01 Chamfer; the terms
    the paper leaves implicit (existence, matched log-scale/rotation, densification, the
    likelihood of child centres under the slots' offset distributions) share the geometry weight."""

    kl: float = 1e-6
    mse: float = 1.0
    chamfer: float = 0.01
    exist: float = 0.01
    geometry_state: float = 0.01
    appearance_exist: float = 0.01
    densify: float = 0.01
    offset_nll: float = 0.01


def _pad_children(arr: np.ndarray | torch.Tensor, slots: int) -> torch.Tensor:
    t = torch.as_tensor(arr)
    c = t.shape[1]
    if c >= slots:
        return t[:, :slots]
    pad = torch.zeros((t.shape[0], slots - c) + tuple(t.shape[2:]), dtype=t.dtype)
    return torch.cat([t, pad], 1)


def transition_loss(geometry: LineageVAE, appearance: LineageVAE, batch: TransitionData, *, beta: float = 1.0,
                    weights: LossWeights = LossWeights(), generator: torch.Generator | None = None,
                    sample: bool = True) -> dict[str, torch.Tensor]:
    """Both models' losses on one batch of transitions. True children are matched to the
    geometry model's slots (centres and log-scales in the parent frame); the appearance model
    is supervised on the same slots, so that slot k of both models describes one Gaussian."""
    slots = geometry.config.slots
    hg = clean_nodes(torch.as_tensor(batch.history_geometry))
    ha = clean_nodes(torch.as_tensor(batch.history_appearance))
    cg = clean_nodes(_pad_children(batch.child_geometry, slots))
    ca = clean_nodes(_pad_children(batch.child_appearance, slots))
    mask = _pad_children(batch.child_mask, slots).bool()
    c = mask.shape[1]
    maskf = mask.float()
    n_child = maskf.sum().clamp(min=1.0)

    densified = torch.as_tensor(batch.densified)
    pg, mu_g, lv_g, z_g = geometry(hg, densified, sample=sample, generator=generator)
    densify = F.binary_cross_entropy_with_logits(pg.densify_logit, densified.float())
    frame = ParentFrame.of(geometry._prepare(hg)[:, -1])
    true_rel = frame.relative(cg[..., 0:3])                                  # (M,C,3)
    pred_rel = pg.offsets                                                    # (M,S,3)
    d2 = ((pred_rel[:, :, None] - true_rel[:, None]) ** 2).sum(-1)          # (M,S,C)
    true_ls = cg[..., 7:10].clamp(*FEATURE_LOG_SCALE_RANGE)
    ls2 = ((pg.children[:, :, None, 7:10] - true_ls[:, None]) ** 2).sum(-1)
    with torch.no_grad():  # DETR-style: a slot that believes it exists is cheaper to match
        exist_cost = -F.logsigmoid(pg.exist_logit)[:, :, None]
        assign = match_slots(d2 + ls2 + exist_cost, mask)                    # (M,C)
    rows = torch.arange(len(mask))[:, None]
    target_exist = torch.zeros_like(pg.exist_logit)
    target_exist[rows.expand_as(assign)[mask], assign[mask]] = 1.0
    exist_g = F.binary_cross_entropy_with_logits(pg.exist_logit, target_exist)

    # Existence-weighted Chamfer on child centres (parent frame), both directions. The weights
    # are detached: existence is learned from the matching alone (BCE), else a slot placed badly
    # would be taught not to exist rather than to move.
    prob = torch.sigmoid(pg.exist_logit).detach()
    big = torch.finfo(d2.dtype).max / 4
    to_pred = torch.where(mask[:, None], d2, big).min(2).values              # (M,S) slot -> nearest child
    to_true = d2.min(1).values                                              # (M,C) child -> nearest slot
    has_child = mask.any(1, keepdim=True)
    chamfer = ((to_true * maskf).sum() / n_child
               + (prob * to_pred * has_child).sum() / (prob * has_child).sum().clamp(min=1e-6))

    # Matched log-scale and rotation (quaternion sign-invariant) of the geometry slots.
    slot_of = assign.clamp(max=slots - 1)
    mg = torch.gather(pg.children, 1, slot_of[..., None].expand(-1, -1, 11))
    qdot = (mg[..., 3:7] * _canonical_quats(cg[..., 3:7])).sum(-1).abs().clamp(max=1.0)
    state = ((((mg[..., 7:10] - true_ls) ** 2).sum(-1) + 4.0 * (1.0 - qdot)) * maskf).sum() / n_child
    # Likelihood of each matched child's centre under its slot's offset distribution (parent
    # frame, sigma units; residuals clamped at 10 spreads so that a few far jumps do not rule).
    true_local = frame.local(cg[..., 0:3]).clamp(-1e3, 1e3)
    mean_local = torch.gather(pg.local_mean, 1, slot_of[..., None].expand(-1, -1, 3))
    spread = torch.gather(pg.local_spread, 1, slot_of[..., None].expand(-1, -1, 3))
    z2 = (((true_local - mean_local) / spread) ** 2).clamp(max=100.0)
    offset_nll = ((0.5 * z2 + spread.log()).sum(-1) * maskf).sum() / n_child
    kl_g = geometry.kl(mu_g, lv_g, z_g).mean()

    pa, mu_a, lv_a, z_a = appearance(ha, densified, sample=sample, generator=generator)
    ma = torch.gather(pa.children, 1, slot_of[..., None].expand(-1, -1, 50))
    colour = ((SH_C0 * (ma[..., 45:48] - ca[..., 45:48])) ** 2).sum(-1)
    sh = ((ma[..., 0:45] - ca[..., 0:45].clamp(-5, 5)) ** 2).sum(-1)
    opac = (torch.sigmoid(ma[..., 48]) - torch.sigmoid(ca[..., 48].clamp(*FEATURE_OPACITY_RANGE))) ** 2
    mse = ((colour + sh + opac) * maskf).sum() / n_child
    exist_a = F.binary_cross_entropy_with_logits(pa.exist_logit, target_exist)
    kl_a = appearance.kl(mu_a, lv_a, z_a).mean()

    w = weights
    total = (w.kl * beta * (kl_g + kl_a) + w.mse * mse + w.chamfer * chamfer + w.exist * exist_g
             + w.geometry_state * state + w.appearance_exist * exist_a + w.densify * densify
             + w.offset_nll * offset_nll)
    with torch.no_grad():
        pred_exist = pg.exist_logit > 0
        exist_acc = (pred_exist == target_exist.bool()).float().mean()
        p_both = 0.5 * (torch.sigmoid(pg.exist_logit) + torch.sigmoid(pa.exist_logit))
        exist_acc_a = ((pa.exist_logit > 0) == target_exist.bool()).float().mean()
        exist_acc_both = ((p_both > 0.5) == target_exist.bool()).float().mean()
        matched_pos = ((torch.gather(pred_rel, 1, slot_of[..., None].expand(-1, -1, 3)) - true_rel) ** 2).sum(-1)
        pos_err = ((matched_pos * maskf).sum() / n_child).sqrt()
        densify_acc = ((pg.densify_logit > 0) == densified).float().mean()
    return {"total": total, "kl_geometry": kl_g, "kl_appearance": kl_a, "mse": mse, "chamfer": chamfer,
            "densify": densify, "densify_accuracy": densify_acc, "offset_nll": offset_nll,
            "exist": exist_g, "state": state, "exist_accuracy": exist_acc, "position_rmse": pos_err,
            "count_error": (pred_exist.float().sum(1) - maskf.sum(1)).abs().mean(),
            "expected_count_bias": (torch.sigmoid(pg.exist_logit).sum(1) - maskf.sum(1)).mean(),
            "exist_accuracy_appearance": exist_acc_a, "exist_accuracy_combined": exist_acc_both,
            "expected_count_bias_combined": (p_both.sum(1) - maskf.sum(1)).mean()}


# ----------------------------------------------------------------------------- the pair

@dataclass
class GaussianVAE:
    """The geometry and appearance models plus what is known about their training."""

    geometry: LineageVAE
    appearance: LineageVAE
    meta: dict = field(default_factory=dict)

    @classmethod
    def create(cls, geometry: VAEConfig | None = None, appearance: VAEConfig | None = None,
               seed: int = 0, **size) -> "GaussianVAE":
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
        g = join(outs_g) if len(hg) else torch.zeros((0, self.slots, 11))
        a = join(outs_a) if len(hg) else torch.zeros((0, self.slots, 50))
        source = self.meta.get("existence", "geometry")
        p = {"geometry": g[..., 10], "appearance": a[..., 49]}.get(source, 0.5 * (g[..., 10] + a[..., 49]))
        return g, a, p.clone(), flags

    # -- persistence (safetensors + JSON: nothing is unpickled on load)
    def save(self, directory: str | Path) -> Path:
        from safetensors.torch import save_file  # noqa: PLC0415

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        for name, model in (("geometry", self.geometry), ("appearance", self.appearance)):
            state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
            save_file(state, str(directory / f"{name}.safetensors"))
        config = {"format": "gaussianvae-1", "geometry": asdict(self.geometry.config),
                  "appearance": asdict(self.appearance.config), "meta": self.meta}
        (directory / "config.json").write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
        return directory

    @classmethod
    def load(cls, directory: str | Path) -> "GaussianVAE":
        from safetensors.torch import load_file  # noqa: PLC0415

        directory = Path(directory)
        cfg_path = directory / "config.json"
        if not cfg_path.is_file():
            raise FileNotFoundError(f"{cfg_path}: no model config (expected config.json, "
                                    f"geometry.safetensors, appearance.safetensors)")
        try:
            config = json.loads(cfg_path.read_text())
            g = LineageVAE(VAEConfig(**config["geometry"]))
            a = LineageVAE(VAEConfig(**config["appearance"]))
        except (KeyError, TypeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{cfg_path}: not a GaussianVAE model config ({exc})") from exc
        for name, model in (("geometry", g), ("appearance", a)):
            path = directory / f"{name}.safetensors"
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing model weights")
            try:
                model.load_state_dict(load_file(str(path)))
            except Exception as exc:  # a truncated file or a mismatched architecture
                raise ValueError(f"{path}: cannot load weights ({exc})") from exc
        return cls(g.eval(), a.eval(), dict(config.get("meta", {})))

    def sizes(self) -> dict[str, int]:
        return {"geometry": model_bytes(self.geometry), "appearance": model_bytes(self.appearance)}


def default_model_dir() -> Path:
    """The bundled model: $GVAE_MODEL_DIR, else models/ beside the package (repository or extension)."""
    import os  # noqa: PLC0415

    env = os.environ.get("GVAE_MODEL_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parent
    for candidate in (here.parent / "models", here / "models"):
        if (candidate / "config.json").is_file():
            return candidate
    return here.parent / "models"


def load_default_model() -> GaussianVAE:
    return GaussianVAE.load(default_model_dir())


# ----------------------------------------------------------------------------- training

@dataclass
class FitConfig:
    """Training of both models (coarse stages first, cyclic KL annealing)."""

    steps: int = 3000
    batch: int = 256
    lr: float = 2e-3
    weight_decay: float = 1e-4
    seed: int = 0
    anneal_alpha: float = 0.01     # beta(t) = min(alpha * (t mod R), 1)
    anneal_period: int = 500
    coarse_fraction: float = 0.3   # first part of training sees only the coarsest transitions
    weights: LossWeights = field(default_factory=LossWeights)


@dataclass
class FitResult:
    model: GaussianVAE
    history: list[dict[str, float]]
    seconds: float


def fit(transitions: Sequence[TransitionData], config: FitConfig = FitConfig(), *,
        model: GaussianVAE | None = None, progress: Callable[[int, int, dict], None] | None = None) -> FitResult:
    """Train both models on stage transitions by predicting each lineage's masked last stage.
    Coarse-to-fine: the first `coarse_fraction` of steps draws only from the lowest stage, then
    every transition is drawn from in proportion to its size."""
    import time  # noqa: PLC0415

    transitions = [t for t in transitions if len(t)]
    if not transitions:
        raise ValueError("fit: no transitions to train on (every lineage set is empty)")
    start = time.perf_counter()
    model = model or GaussianVAE.create(seed=config.seed)
    params = list(model.geometry.parameters()) + list(model.appearance.parameters())
    opt = torch.optim.AdamW(params, lr=config.lr, weight_decay=config.weight_decay)
    # One-cycle schedule; too short a run for its warm-up phase keeps the learning rate constant.
    sched = (torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=config.lr, total_steps=config.steps, pct_start=0.1)
             if config.steps >= 20 else None)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    sizes = np.array([len(t) for t in transitions], float)
    coarsest = min(t.stage for t in transitions)
    coarse = np.array([t.stage == coarsest for t in transitions])
    model.geometry.train()
    model.appearance.train()
    history = []
    for step in range(config.steps):
        p = sizes * (coarse if step < config.coarse_fraction * config.steps else 1.0)
        k = rng.choice(len(transitions), p=p / p.sum())
        tr = transitions[k]
        idx = rng.choice(len(tr), size=min(config.batch, len(tr)), replace=False)
        beta = cyclic_beta(step, config.anneal_alpha, config.anneal_period)
        losses = transition_loss(model.geometry, model.appearance, tr.subset(idx), beta=beta,
                                 weights=config.weights, generator=gen)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        for part in (model.geometry, model.appearance):  # apart: one model's large gradients must
            torch.nn.utils.clip_grad_norm_(part.parameters(), 1.0)  # not shrink the other's steps
        opt.step()
        if sched is not None:
            sched.step()
        record = {k: float(v.detach()) for k, v in losses.items()}
        record["beta"] = beta
        history.append(record)
        if progress is not None:
            progress(step + 1, config.steps, record)
    model.geometry.eval()
    model.appearance.eval()
    return FitResult(model, history, time.perf_counter() - start)


@torch.no_grad()
def evaluate(model: GaussianVAE, transitions: Sequence[TransitionData], *, seed: int = 0,
             batch: int = 4096) -> dict[str, float]:
    """Reconstruction error on transitions (posterior means, no sampling), averaged by lineage:
    matched child-centre RMSE (parent sizes), existence accuracy, child-count error, appearance MSE,
    Chamfer, and the same for the trivial 'copy the parent' prediction as a yardstick."""
    totals: dict[str, float] = {}
    count = 0
    for tr in transitions:
        for i in range(0, len(tr), batch):
            sub = tr.subset(np.arange(i, min(i + batch, len(tr))))
            losses = transition_loss(model.geometry, model.appearance, sub, sample=False)
            for k, v in losses.items():
                totals[k] = totals.get(k, 0.0) + float(v) * len(sub)
            count += len(sub)
    return {k: v / max(count, 1) for k, v in totals.items()}


def copy_parent_baseline(transitions: Sequence[TransitionData]) -> dict[str, float]:
    """The yardstick for `evaluate`: predict one child equal to the parent. Child-centre RMSE
    (parent sizes; every true child against the parent), appearance MSE (same terms as the
    loss), child-count error."""
    sq_pos, mse, count_err, n_child, n_lin = 0.0, 0.0, 0.0, 0, 0
    for tr in transitions:
        hg = clean_nodes(torch.as_tensor(tr.history_geometry))
        ha = clean_nodes(torch.as_tensor(tr.history_appearance))
        cg = clean_nodes(torch.as_tensor(tr.child_geometry))
        ca = clean_nodes(torch.as_tensor(tr.child_appearance))
        mask = torch.as_tensor(tr.child_mask).float()
        frame = ParentFrame.of(hg[:, -1])
        d2 = (frame.relative(cg[..., 0:3]) ** 2).sum(-1)
        last = ha[:, -1:]
        colour = ((SH_C0 * (last[..., 45:48] - ca[..., 45:48])) ** 2).sum(-1)
        sh = ((last[..., 0:45].clamp(-5, 5) - ca[..., 0:45].clamp(-5, 5)) ** 2).sum(-1)
        opac = (torch.sigmoid(last[..., 48].clamp(*FEATURE_OPACITY_RANGE))
                - torch.sigmoid(ca[..., 48].clamp(*FEATURE_OPACITY_RANGE))) ** 2
        sq_pos += float((d2 * mask).sum())
        mse += float(((colour + sh + opac) * mask).sum())
        count_err += float((mask.sum(1) - 1.0).abs().sum())
        n_child += int(mask.sum())
        n_lin += len(tr)
    return {"position_rmse": math.sqrt(sq_pos / max(n_child, 1)), "mse": mse / max(n_child, 1),
            "count_error": count_err / max(n_lin, 1)}
