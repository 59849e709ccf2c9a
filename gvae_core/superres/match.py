"""The capture's images for a fit, at the resolution the cloud was trained at, and the check that
they are the images the cloud was trained on: refused with a clear error before any fit, the cloud
untouched, when they are not (another scene, other cameras, missing files, another resolution).

The training resolution comes from the height asked for, else from the cloud's anti-aliasing size
against the capture's cameras (`octaves.training_height`: exact for a cloud whose size those
cameras made), else it is the images' own. Then the cloud, drawn through a few of the cameras at
that resolution, must reproduce their images clearly better than the images' mean colour does,
over the background it was trained over (stored with it), else over the one of white and black
it reproduces them better over: the one the fit uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..antialias import DILATION_KEY, FILTER_KEY, with_dilation_3d
from ..capture import load_cameras, load_capture_images
from ..cloud import GaussianCloud
from ..datasets import DatasetError, Views
from ..losses import psnr
from ..octaves import training_height
from ..rendering import RenderSettings, render

__all__ = ["CaptureImages", "ImageMismatchError", "capture_images", "match_images", "MIN_MATCH_PSNR",
           "MATCH_MARGIN", "HEIGHT_TOLERANCE"]

#: The cloud must reproduce the images at MIN_MATCH_PSNR dB or more, and MATCH_MARGIN dB better than
#: the images' mean colour: far below what a cloud trained on them draws, far above another scene's.
MIN_MATCH_PSNR = 15.0
MATCH_MARGIN = 3.0
#: A height asked for may differ from the one the cloud's anti-aliasing size says by this share.
HEIGHT_TOLERANCE = 0.1
_BACKGROUNDS = ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))


class ImageMismatchError(ValueError):
    """The images are not the ones the cloud was trained on (the message says how it was told)."""


@dataclass
class CaptureImages:
    """The images to fit (`views`, at the training resolution), the cloud with the anti-aliasing
    size the fit draws it by (its own, or the capture cameras' at that resolution), where the
    resolution came from, and how well the unrefined cloud reproduces the images (`match`)."""

    views: Views
    cloud: GaussianCloud
    height_source: str
    match: ImageMatch


@dataclass
class ImageMatch:
    """PSNR of the cloud's render against the images over the background it matches best, of the
    images' mean colour against them, on `views` images."""

    background: tuple[float, float, float]
    psnr: float
    constant_psnr: float
    views: int


def capture_images(cloud: GaussianCloud, images, height: int | None = None, *, check_views: int = 6,
                   before_loading=None, test_every: int | None = None) -> CaptureImages:
    """The capture's images for fitting `cloud` (numpy): `images` a capture (a path
    `capture.read_capture` reads: COLMAP, transforms.json, NeRF-Synthetic; its training views, every
    `test_every`-th held out as the training held it out) or `Views` already loaded at the
    training resolution; `height` the training image height if known. `before_loading(count,
    height, width)`: called once the images' number and size are known, before they are read (a
    memory check). Raises DatasetError (files) or ImageMismatchError / ValueError (content) naming
    the dataset."""
    name = "the images given" if isinstance(images, Views) else str(images)
    cams = images.cameras if isinstance(images, Views) else load_cameras(images, test_every)
    if height is not None and int(height) <= 0:
        raise ValueError(f"{name}: the image height must be positive, got {height}")
    sized = {FILTER_KEY, DILATION_KEY} & set(cloud.extra)
    implied, agree = training_height(cloud, cams) if sized else (float("nan"), 0.0)
    if sized and (not math.isfinite(implied) or agree < 0.5):
        seen = "none" if not math.isfinite(implied) else "few"
        raise ImageMismatchError(
            f"{name}: the capture's cameras do not match the cloud: they see {seen} of its Gaussians at the rates "
            f"its anti-aliasing size says it was trained at ({agree:.0%} agree); "
            f"another capture, or a cloud moved since training?")
    if height is not None:
        height = int(height)
        if sized and abs(height / implied - 1.0) > HEIGHT_TOLERANCE:
            raise ValueError(f"{name}: the cloud was trained at about {implied:.0f} px high images (its anti-aliasing "
                             f"size against the capture's cameras), not the {height} px asked for")
        source = f"{height} px, as asked"
    elif sized:
        height = int(round(implied))
        source = f"{height} px, from the cloud's anti-aliasing size against the capture's cameras"
    else:
        source = "the images' own size (the cloud carries no anti-aliasing size)"
    if before_loading is not None:
        size = cams[0] if height is None else cams[0].scaled(height)
        before_loading(len(cams), size.height, size.width)
    if isinstance(images, Views):
        views = images if height is None else images.at_resolution(height)
    else:
        views = load_capture_images(Path(images), height, test_every)
    got = views.cameras[0].height
    if height is not None and got != height:
        raise DatasetError(f"{name}: the images are {got} px high, fewer than the {height} px the fit needs "
                           f"(images are not scaled up)")
    if not sized:
        cloud = with_dilation_3d(cloud, views.cameras)
        source = f"{got} px, " + source
    match = match_images(cloud, views, name, check_views)
    return CaptureImages(views=views, cloud=cloud, height_source=source, match=match)


def match_images(cloud: GaussianCloud, views: Views, name: str = "the images", count: int = 6) -> ImageMatch:
    """How well `cloud`, drawn through `count` of the views' cameras, reproduces their images, over
    the background it was trained over (`GaussianCloud.background`), else the one of white and black
    that fits best; ImageMismatchError when it does not (module docstring)."""
    pick = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    renders = {bg: [] for bg in ((cloud.background,) if cloud.background is not None else _BACKGROUNDS)}
    for v in pick:
        out = render(cloud, views.cameras[v], settings=RenderSettings())
        colour, alpha = out.image.numpy(), out.alpha.numpy()[..., None]
        for bg in renders:
            renders[bg].append(colour + (1.0 - alpha) * np.asarray(bg, np.float32))
    scores = {}
    for bg, images in renders.items():
        target = views.composite(bg)[pick]
        scores[bg] = float(np.mean([min(psnr(a, b), 100.0) for a, b in zip(images, target)]))
    background = max(scores, key=scores.get)
    target = views.composite(background)[pick]
    constant = float(np.mean([psnr(np.broadcast_to(t.mean((0, 1)), t.shape), t) for t in target]))
    match = ImageMatch(background=background, psnr=scores[background], constant_psnr=constant, views=len(pick))
    if not (match.psnr >= MIN_MATCH_PSNR and match.psnr >= constant + MATCH_MARGIN):
        raise ImageMismatchError(
            f"{name}: these are not the images the cloud was trained on: drawn through their cameras, the cloud "
            f"reproduces {len(pick)} of them at {match.psnr:.1f} dB PSNR (their mean colour alone: {constant:.1f} dB; "
            f"a cloud trained on its images: 25 dB and more); another scene, or cameras in another frame?")
    return match
