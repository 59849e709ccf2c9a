"""GaussianVAE core: Blender-free, importable without torch.

`import gvae_core` and the numpy parts (clouds, PLY, cameras, datasets) never import torch; the
torch-based stages (render, train, lineage, vae, hessian, refine, compact, metrics) load on first use.
"""

from __future__ import annotations

import importlib

from .camera import Camera, orbit
from .cloud import GaussianCloud, ValidationReport

__version__ = "0.1.0"

# name -> module that defines it; resolved lazily so that torch is imported only when needed.
_LAZY = {
    "read_ply": "gvae_core.ply",
    "write_ply": "gvae_core.ply",
    "PlyError": "gvae_core.ply",
    "read_splat_file": "gvae_core.formats",
    "write_splat_file": "gvae_core.formats",
    "write_spz": "gvae_core.formats",
    "load_nerf_synthetic": "gvae_core.capture",
    "DatasetError": "gvae_core.datasets",
    "Views": "gvae_core.datasets",
    "render": "gvae_core.rendering",
    "RenderOutput": "gvae_core.rendering",
    "RenderSettings": "gvae_core.rendering",
    "GaussianVAE": "gvae_core.vae",
    "hessian_scores": "gvae_core.hessian",
    "refine": "gvae_core.refinement",
    "RefineResult": "gvae_core.refinement",
    "compact": "gvae_core.compaction",
    "CompactResult": "gvae_core.compaction",
    "train_progressive": "gvae_core.train",
    "TrainConfig": "gvae_core.train",
    "TrainResult": "gvae_core.train",
    "train_capture": "gvae_core.train",
    "Lineage": "gvae_core.lineage",
    "make_scene": "gvae_core.scenes",
    "list_scenes": "gvae_core.scenes",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'gvae_core' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__all__ = ["Camera", "orbit", "GaussianCloud", "ValidationReport", *_LAZY]
