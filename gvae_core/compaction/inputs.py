"""Where a compaction's cameras and photos come from, decided once for every front end
(`gvae compact`, Blender's Compact): the cameras asked for, else the training cameras found
beside the splat's file when they see it, else none (views placed around the cloud); the
capture's photos at the height they trained the cloud at when asked to fine-tune on them."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..camera import Camera
from ..capture import load_cameras, training_cameras
from ..cloud import GaussianCloud
from .finetune import fine_tune_images

__all__ = ["CompactInputs", "compaction_inputs"]


@dataclass
class CompactInputs:
    """What `compact` is given: `cameras` (None: views placed around the cloud), `images` (the
    photos to fine-tune on, `datasets.Views`, or None); `notes`: lines that tell the user where
    they come from; `found`: the cameras are the training cameras found beside the file."""

    cameras: list[Camera] | None
    images: object | None
    notes: list[str] = field(default_factory=list)
    found: bool = False


def compaction_inputs(cloud: GaussianCloud, *, source=None, cameras=None, images=None, placed_views: bool = False,
                      test_every: int | None = None, image_height: int | None = None) -> CompactInputs:
    """The cameras and photos to compact `cloud` (read from the file `source`, when known) with:
    the training views of the capture at `cameras` (every `test_every`-th held out), else, without
    `images` and unless `placed_views`, the training cameras found beside `source`
    (`capture.training_cameras`: when they see the cloud); `images`: the capture whose training
    photos it is fine-tuned on (`fine_tune_images`, at `image_height`, else at the height they
    trained it at). The photos' own cameras score then."""
    notes: list[str] = []
    cams = load_cameras(cameras, test_every) if cameras is not None else None
    views = None
    found = False
    if images is not None:
        views = fine_tune_images(cloud, images, test_every, image_height)
        notes.append(f"fine-tuning on {len(views)} photos of {images} at {views.cameras[0].height} px")
    elif cams is not None:
        notes.append(f"scoring from {len(cams)} cameras of {cameras}")
    elif source is not None and not placed_views:
        cams, lines = training_cameras(source, cloud)
        notes += lines
        found = cams is not None
    return CompactInputs(cams, views, notes, found)
