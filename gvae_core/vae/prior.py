"""The latent prior p_psi(z): a RealNVP-style normalising flow (affine coupling layers with an
exact inverse), and the cyclic KL annealing schedule."""

from __future__ import annotations

import math

import torch
from torch import nn


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
        return std_normal_logpdf(eps) + logdet

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        eps = torch.randn(n, self.dim, generator=generator)
        return self.forward(eps)[0]


def std_normal_logpdf(x: torch.Tensor) -> torch.Tensor:
    return -0.5 * (x * x).sum(-1) - 0.5 * x.shape[-1] * math.log(2.0 * math.pi)


def cyclic_beta(t: int, alpha: float, period: int) -> float:
    """Cyclic KL annealing beta(t) = min(alpha * (t mod R), 1)."""
    return min(alpha * (t % max(int(period), 1)), 1.0)
