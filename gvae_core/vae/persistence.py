"""Saving and loading a `GaussianVAE`: safetensors weights plus a JSON config, so that nothing is
unpickled on load; and where the bundled model lives. The model's one door to files: `save_model`
and `load_model` (`model` imports nothing of this module)."""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

from safetensors.torch import load_file, save_file

from ..atomic import atomic_write_text
from .model import GaussianVAE, LineageVAE, VAEConfig

FORMAT = "gaussianvae-1"


def save_model(model: GaussianVAE, directory: str | Path) -> Path:
    """Write `geometry.safetensors`, `appearance.safetensors` and `config.json` into `directory`."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name, part in (("geometry", model.geometry), ("appearance", model.appearance)):
        state = {k: v.detach().contiguous() for k, v in part.state_dict().items()}
        save_file(state, str(directory / f"{name}.safetensors"))
    config = {"format": FORMAT, "geometry": asdict(model.geometry.config),
              "appearance": asdict(model.appearance.config), "meta": model.meta}
    atomic_write_text(directory / "config.json", json.dumps(config, indent=2, sort_keys=True) + "\n")
    return directory


def load_model(directory: str | Path) -> GaussianVAE:
    """Read a model written by `save_model`; missing or bad files raise an error naming them."""
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
    for name, part in (("geometry", g), ("appearance", a)):
        load_weights(part, directory / f"{name}.safetensors")
    return GaussianVAE(g.eval(), a.eval(), dict(config.get("meta", {})))


def load_weights(module, path: Path) -> None:
    """Load a safetensors file into `module`; a missing file or one that does not fit raises an
    error naming it."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing model weights")
    try:
        module.load_state_dict(load_file(str(path)))
    except Exception as exc:  # a truncated file or a mismatched architecture
        raise ValueError(f"{path}: cannot load weights ({exc})") from exc


def default_model_dir() -> Path:
    """The bundled model: $GVAE_MODEL_DIR, else models/ beside the gvae_core package (in the
    repository and in the Blender extension alike)."""
    env = os.environ.get("GVAE_MODEL_DIR")
    if env:
        return Path(env)
    package = Path(__file__).resolve().parents[1]
    for candidate in (package.parent / "models", package / "models"):
        if (candidate / "config.json").is_file():
            return candidate
    return package.parent / "models"


def load_default_model() -> GaussianVAE:
    return load_model(default_model_dir())
