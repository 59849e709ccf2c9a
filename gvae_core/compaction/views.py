"""The views compaction looks from, and what they see.

A Gaussian is dropped as unseen only when every view misses it: every camera of the capture when
its cameras are given, else views all around (`capture.placed_views`: outside an object, inside
and outside a scene that surrounds its centre). The scores come from a few of them (`scoring`);
the others (`others`) only say what they see (one forward sweep each, `sight`). The summary's
PSNR comes from the scoring views and, where they miss Gaussians that were removed, from the
other views that see the most of those (`report_views`). (`sight`: what the other views see of
what the scoring views do not.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from ..capture import DEFAULT_VIEWS, inside_views, placed_views, scoring_views
from ..cloud import GaussianCloud
from ..rendering import RenderSettings
from ..rendering.frames import Frame
from .removal import PICTURE_SCORES
from .report import UNSEEN_WARNING, CompactResult, input_images, report_psnr
from .scoring import UNSEEN, frame_hits, pixel_hits


@dataclass
class CompactionViews:
    """`scoring`: the views the scores and the summary's PSNR come from; `others`: the views that
    only say what they see (the capture's other cameras, a placed scene's extra views), at most
    the scoring resolution; `placed`: whether they were placed (no capture cameras); `inside`: for
    views placed around an object, what gives views from inside it (`capture.inside_views`), for
    when they leave much of it unseen (`sight`); else None."""

    scoring: list[Camera]
    others: list[Camera]
    placed: bool
    inside: Callable[[], list[Camera]] | None = None


def compaction_views(src: GaussianCloud, cameras: Sequence[Camera] | None, views: int, resolution: int,
                     normalization=None) -> CompactionViews:
    """With the capture's `cameras`: `views` of them to score from (`capture.scoring_views`; all
    when 0), the rest, scaled to at most `resolution` px high, as others. Without: the views
    `capture.placed_views` places (`views` of them to score from, DEFAULT_VIEWS when 0) and, for an
    object, views from inside it to look through should those leave much of it unseen."""
    if cameras is not None:
        cameras = list(cameras)
        scoring = scoring_views(cameras, views, resolution, src)
        chosen = [c.world_to_cam for c in scoring]
        others = [c.scaled(resolution) if c.height > resolution else c for c in cameras
                  if not any(np.array_equal(c.world_to_cam, w) for w in chosen)]
        return CompactionViews(scoring, others, False)
    placed = placed_views(src, views or DEFAULT_VIEWS, resolution, normalization=normalization)
    inside = None
    if placed.surround is None:
        def inside() -> list[Camera]:
            return inside_views(src, views or DEFAULT_VIEWS, resolution, normalization)
    return CompactionViews(placed.scoring, placed.extra, True, inside)


@dataclass
class Sight:
    """What the views see of a cloud: `hidden` (K,), the rows the scoring views draw into no pixel;
    `others`, the other views looked through, and `by_other` (len(others), K) bool, which of them
    draws each hidden row; `seen` (N,) bool, the rows some view draws."""

    hidden: np.ndarray
    others: list[Camera]
    by_other: np.ndarray
    seen: np.ndarray


def sight(cloud: GaussianCloud, scores: np.ndarray, score: str, frames: Sequence[Frame], others: Sequence[Camera],
          settings: RenderSettings | None = None, inside: Callable[[], list[Camera]] | None = None) -> Sight:
    """`Sight` of `cloud` scored with `scores` (for a score that is not of the picture, every row
    counts as drawn by the scoring views). A row whose score is above UNSEEN is drawn; the others
    (a Gaussian so large and even that moving or scaling it changes no pixel has no score, yet it is
    drawn) are looked for in the scoring views' `frames` (the Hessian's: only the tiles that draw
    them are swept, `scoring.frame_hits`), then in the other views (one sweep each,
    `scoring.pixel_hits`). `inside`: where views placed around an object leave more than
    UNSEEN_WARNING of it unseen, the views it gives (`capture.inside_views`) are looked through
    too (a scene taken for an object)."""
    n = len(cloud)
    hidden = np.flatnonzero(np.asarray(scores) <= UNSEEN) if score in PICTURE_SCORES else np.zeros(0, np.int64)
    drawn = np.zeros(len(hidden), bool)
    for frame in frames:
        drawn |= frame_hits(frame, n, hidden) > 0
    hidden = hidden[~drawn]
    others = list(others)
    by_other = _drawn_by(cloud, others, hidden, settings)
    if inside is not None and (~by_other.any(0)).sum() > UNSEEN_WARNING * n:
        more = inside()
        others += more
        by_other = np.concatenate([by_other, _drawn_by(cloud, more, hidden, settings)])
    seen = np.ones(n, bool)
    seen[hidden] = by_other.any(0)
    return Sight(hidden, others, by_other, seen)


def _drawn_by(cloud: GaussianCloud, cameras: Sequence[Camera], rows: np.ndarray, settings) -> np.ndarray:
    """(len(cameras), len(rows)) bool: which view draws each of `rows` into some pixel."""
    out = np.zeros((len(cameras), len(rows)), bool)
    if len(rows):
        for v, cam in enumerate(cameras):
            out[v] = pixel_hits(cloud, [cam], settings)[rows] > 0
    return out


def report_views(scoring: Sequence[Camera], others: Sequence[Camera], sight: np.ndarray, removed: np.ndarray,
                 limit: int) -> tuple[list[Camera], np.ndarray]:
    """The views the summary's PSNR comes from: the scoring views and, one at a time, the other view
    that sees the most removed Gaussians no chosen view sees yet (at most `limit` of them).
    `sight` (len(others), K): what each other view sees of K Gaussians the scoring views do not
    draw (`Sight.by_other`), `removed` (K,) which of those were removed. Returns the views and which of the K removed
    ones they still miss."""
    chosen = list(scoring)
    missed = np.asarray(removed, bool).copy()
    for _ in range(max(int(limit), 0)):
        if not missed.any() or len(others) == 0:
            break
        gain = (sight & missed).sum(1)
        best = int(np.argmax(gain))
        if gain[best] == 0:
            break
        chosen.append(others[best])
        missed &= ~sight[best]
    return chosen, missed


def compare(result: CompactResult, src: GaussianCloud, reference: list, cams: Sequence[Camera], seen: Sight,
            settings: RenderSettings, limit: int) -> CompactResult:
    """Fill in `result`'s PSNR against the input's renders (`reference`, from the scoring views
    `cams`) from `report_views` (the scoring views and up to `limit` other views that see what was
    removed), how many removed Gaussians those did not see, and how many were dropped as seen by no
    view at all (`seen`: what the views saw of `src`)."""
    psnr_cams, missed = report_views(cams, seen.others, seen.by_other, result.removed[seen.hidden], limit)
    reference = list(reference) + input_images(src, psnr_cams[len(cams):], settings)
    result.psnr = report_psnr(reference, result.cloud, psnr_cams, settings)
    result.psnr_views, result.missed = len(psnr_cams), int(missed.sum())
    result.unseen = int((~seen.seen & (result.groups < 0)).sum())
    return result
