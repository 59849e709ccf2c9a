"""Lineage transformer VAEs (DESIGN.md step 3): geometry (11 features per node) and appearance (50).

Modules, one job each: `features` (what the models see of a lineage), `prior` (the flow prior
and KL annealing), `model` (the VAEs and the pair refinement runs), `data` (transitions from runs
and a synthetic generator), `losses` (slot matching and the training objective), `fit` (training
and evaluation), `persistence` (safetensors + JSON, the bundled model).
"""

from .data import lineage_transitions, load_runs, synthetic_transitions
from .features import ParentFrame, clean_nodes, encoder_inputs
from .fit import FitConfig, FitResult, copy_parent_baseline, evaluate, fit
from .losses import LossWeights, match_slots, match_slots_reference, transition_loss
from .model import DEFAULT_SIZE, EncoderBlock, GaussianVAE, LineageVAE, SlotPrediction, VAEConfig, model_bytes
from .persistence import default_model_dir, load_default_model, load_model, save_model
from .prior import FlowPrior, cyclic_beta

__all__ = ["DEFAULT_SIZE", "EncoderBlock", "FitConfig", "FitResult", "FlowPrior", "GaussianVAE", "LineageVAE",
           "LossWeights", "ParentFrame", "SlotPrediction", "VAEConfig", "clean_nodes",
           "copy_parent_baseline", "cyclic_beta", "default_model_dir", "encoder_inputs", "evaluate", "fit",
           "lineage_transitions", "load_default_model", "load_model", "load_runs", "match_slots",
           "match_slots_reference", "model_bytes", "save_model", "synthetic_transitions", "transition_loss"]
