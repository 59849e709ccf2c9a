"""The detail model (DESIGN.md step 5): what each Gaussian should become per octave of sampling rate
above the one it was trained at, learned through the renderer against real higher-resolution
images: `features` (its inputs: own state, lineage, neighbours), `model`, `fit` (training and the
oracle), `persistence` (safetensors + JSON; the bundled weights)."""

from .features import DetailInputs, detail_inputs
from .fit import Example, FitConfig, fit_changes, fit_model
from .model import DetailConfig, DetailModel
from .persistence import default_detail_dir, load_detail, save_detail

__all__ = ["DetailInputs", "detail_inputs", "Example", "FitConfig", "fit_changes", "fit_model", "DetailConfig",
           "DetailModel", "default_detail_dir", "load_detail", "save_detail"]
