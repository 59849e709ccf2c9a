"""Training through the renderer: changes per octave rendered at the resolution they stand for,
against real images.

An `Example` is one transition a refine stands for: a cloud trained at some resolution (with its
anti-aliasing size and lineage, `features`) and the real training views at 1.5x and 2x that
resolution. Every optimiser step draws an example, a scale, a view and a square patch of it,
renders the cloud with its changes (`gvae_core.octaves`: each Gaussian takes the octaves above its
training rate that the view samples it at) and back-propagates 0.8 L1 + 0.2 (1 - SSIM) of the
patch into what made the changes:
- `fit_model`: the detail model's weights (one model for every Gaussian of every example);
- `fit_changes`: every Gaussian's own changes, free parameters: the oracle, the bound a model of
  the same quantities cannot pass on the views it was fitted to.
At 1x nothing is drawn changed (by construction), so the training-resolution picture needs no loss
term of its own.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from ..datasets import Views
from ..octaves import with_octaves
from ..rendering import RenderSettings, render
from ..train.photometric import photometric_loss
from .features import DetailInputs
from .model import DetailModel

__all__ = ["Example", "FitConfig", "fit_model", "fit_changes", "crop", "ORACLE_LEARNING_RATES"]

#: Adam learning rates of the oracle's free changes: the reference 3DGS's for each field (positions
#: times the scene extent, without decay).
ORACLE_LEARNING_RATES = {"scales": 5e-3, "opacities": 5e-2, "sh_dc": 2.5e-3, "sh_rest": 2.5e-3 / 20, "quats": 1e-3,
                         "means": 1.6e-4}


@dataclass
class Example:
    """One cloud (numpy, with its anti-aliasing size), its model inputs, and real views of what it
    should draw at higher resolutions (scale label -> Views, e.g. "1.5x", "2x")."""

    cloud: GaussianCloud
    inputs: DetailInputs | None
    views: dict[str, Views]
    name: str = ""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    _torch: dict = field(default_factory=dict, repr=False)

    def torch_cloud(self) -> GaussianCloud:
        if "cloud" not in self._torch:
            self._torch["cloud"] = self.cloud.to_torch()
        return self._torch["cloud"]

    def target(self, scale: str) -> torch.Tensor:
        key = "target_" + scale
        if key not in self._torch:
            self._torch[key] = torch.from_numpy(self.views[scale].composite(self.background))
        return self._torch[key]

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if "inputs" not in self._torch:
            self._torch["inputs"] = tuple(torch.from_numpy(a) for a in (self.inputs.shared, self.inputs.axis,
                                                                        self.inputs.nodes))
        return self._torch["inputs"]


@dataclass
class FitConfig:
    """steps: optimiser steps; lr: Adam's; patch: square patch edge in pixels (0: whole views);
    scales: the view scales drawn from, uniformly; lambda_dssim: the SSIM weight of the loss."""

    steps: int = 3000
    lr: float = 1e-3
    patch: int = 96
    scales: tuple[str, ...] = ("1.5x", "2x")
    lambda_dssim: float = 0.2
    seed: int = 0
    antialias: str = "matched"


def crop(camera: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The camera that sees only the pixels [y0, y0+height) x [x0, x0+width) of `camera`."""
    return dataclasses.replace(camera, cx=camera.cx - x0, cy=camera.cy - y0, width=width, height=height)


def _through_renderer(examples: Sequence[Example], changes_of: Callable[[int, Example], dict], parameters,
                      config: FitConfig, lr: float | list[dict], progress=None, extra_loss=None) -> list[float]:
    """The shared loop: returns the loss of every step. `extra_loss(example)`: a term added to it."""
    groups = lr if isinstance(lr, list) else [{"params": list(parameters), "lr": lr}]
    opt = torch.optim.Adam(groups, eps=1e-15)
    rng = np.random.default_rng(config.seed)
    settings = RenderSettings(antialias=config.antialias)
    losses = []
    for step in range(config.steps):
        i = int(rng.integers(len(examples)))
        ex = examples[i]
        scales = [s for s in config.scales if s in ex.views]
        scale = scales[int(rng.integers(len(scales)))]
        views = ex.views[scale]
        v = int(rng.integers(len(views)))
        cam, target = views.cameras[v], ex.target(scale)[v]
        if config.patch and config.patch < min(cam.width, cam.height):
            x0 = int(rng.integers(cam.width - config.patch + 1))
            y0 = int(rng.integers(cam.height - config.patch + 1))
            cam = crop(cam, x0, y0, config.patch, config.patch)
            target = target[y0:y0 + config.patch, x0:x0 + config.patch]
        cloud = with_octaves(ex.torch_cloud(), changes_of(i, ex))
        out = render(cloud, cam, background=ex.background, settings=settings)
        loss = photometric_loss(out.image, target, config.lambda_dssim, compiled=settings.kernels != "torch")
        if extra_loss is not None:
            loss = loss + extra_loss(ex)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        losses.append(float(loss.detach()))
        if progress is not None:
            progress(step + 1, losses[-1])
    return losses


def fit_model(model: DetailModel, examples: Sequence[Example], config: FitConfig | None = None,
              progress=None) -> dict:
    """Train `model` on `examples` (which need `inputs`); returns the history (losses, seconds)."""
    config = config or FitConfig()
    model.train()
    t0 = time.perf_counter()
    losses = _through_renderer(examples, lambda i, ex: model(*ex.tensors()), model.parameters(), config, config.lr,
                               progress, extra_loss=lambda ex: model.auxiliary_loss(ex.tensors()[2]))
    model.eval()
    return {"losses": losses, "seconds": time.perf_counter() - t0, "steps": config.steps,
            "examples": [ex.name for ex in examples]}


def fit_changes(example: Example, fields: Sequence[str], config: FitConfig | None = None, extent: float = 1.0,
                progress=None) -> dict[str, np.ndarray]:
    """The oracle: each Gaussian's own changes per octave of `fields`, fitted to the example's real
    views (Adam at `ORACLE_LEARNING_RATES` times config.lr / 1e-3; positions times `extent`)."""
    config = config or FitConfig()
    tc = example.torch_cloud()
    params = {f: torch.zeros_like(getattr(tc, f), requires_grad=True) for f in fields}
    mult = config.lr / 1e-3
    groups = [{"params": [p], "lr": ORACLE_LEARNING_RATES[f] * mult * (extent if f == "means" else 1.0)}
              for f, p in params.items()]
    _through_renderer([example], lambda i, ex: params, params.values(), config, groups, progress)
    return {f: p.detach().numpy().copy() for f, p in params.items()}
