"""Refine from the capture's own images (DESIGN.md step 5b, multi-view super-resolution): `match`
(the images at the training resolution, checked against the cloud), `fit` (every Gaussian's
changes per octave fitted to them through an area-averaged higher-resolution render), `children`
(Gaussians that fade in above the training rate where the fit asks for more), `guards` (per-image
pose and exposure corrections), `optim` (an Adam that moves only the rows a step saw)."""

from .fit import CHILD_GRADIENT, DEFAULT_FIELDS, SuperResConfig, SuperResFit, fit_octaves
from .guards import EXPOSURE_WEIGHT, POSE_WEIGHT
from .match import CaptureImages, ImageMismatchError, capture_images, match_images

__all__ = ["CHILD_GRADIENT", "DEFAULT_FIELDS", "SuperResConfig", "SuperResFit", "fit_octaves", "CaptureImages",
           "ImageMismatchError", "capture_images", "match_images", "POSE_WEIGHT", "EXPOSURE_WEIGHT"]
