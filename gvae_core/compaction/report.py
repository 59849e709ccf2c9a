"""What a compaction reports: the result, the PSNR of the compacted cloud's renders against the
input's from views that see what was removed, how many removed Gaussians those views did not see,
and a warning when the views miss more than a small share of the cloud.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from ..losses import psnr
from ..rendering import RenderSettings, render

#: PSNR reported when the compacted renders equal the input's.
PSNR_CAP = 100.0
#: A compaction warns when the views see no more than this share of the cloud less than all of it
#: (what they miss is dropped as unseen: the project's trained objects leave 0.04-0.34% unseen from
#: four placed views, 0.06-1.05% from all 24 training cameras; a closed head scored from inside it half).
UNSEEN_WARNING = 0.02


@dataclass
class CompactResult:
    """The compacted cloud and what happened to the input's Gaussians.

    rows (M,): the input row each output row stands for (its own row, or for a merged Gaussian
    the row of its most massive member), ascending; groups (N,): the output row each input row
    went into, -1 where it was dropped; scores (N,): the input's scores (the first round's with
    images); psnr: PSNR (dB) of the compacted cloud's renders against the input's, over white, from
    `psnr_views` views: the scoring views and the other views that see the most removed Gaussians
    the scoring views do not; timings: seconds per part; rounds: per fine-tuning round, its count,
    seconds and PSNR against the training images (or the input's own renders) before and after;
    unseen: input Gaussians no view saw (dropped as unseen); missed: removed Gaussians (dropped, or
    merged into another's row) that the PSNR's views did not see; views_seen: the share of the
    input that some view saw; warnings: what the user should know (`UNSEEN_WARNING`)."""

    cloud: GaussianCloud
    rows: np.ndarray
    groups: np.ndarray
    scores: np.ndarray
    psnr: float
    timings: dict[str, float] = field(default_factory=dict)
    rounds: list[dict] = field(default_factory=list)
    #: The PSNR tolerance the count was found for (None: a fraction or count was asked for).
    tolerance: float | None = None
    psnr_views: int = 0
    unseen: int = 0
    missed: int = 0
    warnings: list[str] = field(default_factory=list)

    @property
    def n_input(self) -> int:
        return len(self.groups)

    @property
    def removed(self) -> np.ndarray:
        """(N,) bool: input rows dropped, or merged into another one's row."""
        return (self.groups < 0) | (self.rows[np.maximum(self.groups, 0)] != np.arange(self.n_input))

    @property
    def merged(self) -> int:
        """Input Gaussians that went into another one's row."""
        return int(((self.groups >= 0) & (self.rows[np.maximum(self.groups, 0)] != np.arange(self.n_input))).sum())

    @property
    def dropped(self) -> int:
        return int((self.groups < 0).sum())

    def summary(self) -> str:
        times = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items() if k != "total")
        tuned = f", {len(self.rounds)} fine-tuning round(s)" if self.rounds else ""
        kept = len(self.cloud) / max(self.n_input, 1)
        unseen = f" ({self.unseen:,} of them seen by no view)" if self.unseen else ""
        missed = f"; {self.missed:,} removed Gaussians not seen by those views" if self.missed else \
            "; they see every removed Gaussian"
        return (f"{self.n_input:,} Gaussians in, {len(self.cloud):,} out ({kept:.1%}): "
                f"{self.dropped:,} dropped{unseen}, {self.merged:,} merged into others{tuned}; PSNR against the "
                f"input's render {self.psnr:.2f} dB from {self.psnr_views} views{missed}; "
                f"{self.timings.get('total', 0.0):.2f} s ({times})")


def unseen_warning(n: int, unseen: int, placed: bool) -> list[str]:
    """The warning for `unseen` of `n` Gaussians that no view saw, when more than UNSEEN_WARNING."""
    if n == 0 or unseen <= UNSEEN_WARNING * n:
        return []
    where = ("the views placed around it" if placed else "the capture's cameras")
    advice = ("; if the cloud is a scene seen from inside or has parts hidden from every side, give the capture's "
              "cameras (--cameras)" if placed else "; are they the cameras of this cloud?")
    return [f"{unseen:,} of the {n:,} Gaussians ({unseen / n:.1%}) are seen by none of {where} and were dropped as "
            f"unseen{advice}"]


def report_psnr(frames_or_images, cloud: GaussianCloud, cams: Sequence[Camera], settings: RenderSettings) -> float:
    """Mean PSNR of `cloud`'s renders from `cams` (over white) against the input's images."""
    values = []
    with torch.no_grad():
        for ref, cam in zip(frames_or_images, cams):
            img = render(cloud, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1)
            values.append(min(psnr(img, ref), PSNR_CAP))
    return float(np.mean(values)) if values else PSNR_CAP


def input_images(src: GaussianCloud, cams: Sequence[Camera], settings: RenderSettings, frames=None) -> list:
    """The input's renders (over white) from `cams`: from the Hessian's frames when it made them
    (the first ones, in order)."""
    frames = list(frames or [])[:len(cams)]
    images = [f.image((1.0, 1.0, 1.0)).clamp(0, 1) for f in frames]
    with torch.no_grad():
        for cam in cams[len(images):]:
            images.append(render(src, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1))
    return images
