"""Saving and loading the detail model: `detail.safetensors` plus `detail.json` (nothing is
unpickled), beside the lineage VAEs in the model directory."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from safetensors.torch import save

from ..atomic import atomic_write, atomic_write_text
from ..vae.persistence import default_model_dir, load_weights
from .model import DetailConfig, DetailModel

FORMAT = "gvae-detail-1"
WEIGHTS, CONFIG = "detail.safetensors", "detail.json"


def save_detail(model: DetailModel, directory) -> Path:
    """Write the weights and the config (and `model.meta`: how it was trained) into `directory`."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    atomic_write(directory / WEIGHTS, lambda f: f.write(save(state)))
    doc = {"format": FORMAT, "config": asdict(model.config), "meta": model.meta}
    atomic_write_text(directory / CONFIG, json.dumps(doc, indent=2, sort_keys=True) + "\n")
    return directory


def load_detail(directory=None) -> DetailModel:
    """The model in `directory` (default: the bundled one); missing or bad files raise an error
    naming them."""
    directory = Path(directory) if directory is not None else default_detail_dir()
    path = directory / CONFIG
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no detail model config (expected {CONFIG} and {WEIGHTS})")
    try:
        doc = json.loads(path.read_text())
        if doc.get("format") != FORMAT:
            raise KeyError("format")
        config = DetailConfig(**doc["config"])
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a detail model config ({exc})") from exc
    model = DetailModel(config)
    model.meta = dict(doc.get("meta", {}))
    load_weights(model, directory / WEIGHTS)
    return model.eval()


def default_detail_dir() -> Path:
    """Where the bundled detail model lives: the model directory of the VAEs ($GVAE_MODEL_DIR, else
    models/)."""
    return default_model_dir()


__all__ = ["save_detail", "load_detail", "default_detail_dir", "FORMAT"]
