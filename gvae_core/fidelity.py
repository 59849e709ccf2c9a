"""Keep only the refinements that leave the training-resolution picture as it was.

The training images are the only ground truth a refine has, and the input cloud is fitted to
them: whatever a refinement adds should show above the training resolution, not change what the
cloud already shows at it. So every lineage the refine grew (a selected input Gaussian, its
in-place update and its descendants) is judged by rendering the input and the refined cloud from
the scoring views, rescaled to the sampling rate the cloud was trained at (from its stored
anti-aliasing size, `gvae_core.antialias`), and taking the largest colour change near the
lineage's Gaussians; lineages above the tolerance are put back as they were. Measured on the
validation scenes (BENCHMARKS.md, "Fidelity check"), this is what keeps the default refine from
lowering PSNR at twice the training resolution.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .antialias import DILATION_KEY, FILTER_KEY, max_sampling_rate
from .budget import DEFAULT_FIDELITY
from .camera import Camera
from .cloud import PARAMETER_FIELDS, GaussianCloud
from .conventions import NEAR_PLANE
from .octaves import LIMIT_KEY, octaves_seen, stored_keys, training_rate
from .parallel import in_threads
from .rendering import RenderSettings
from .rendering.frames import Frame, make_frame, redraw

__all__ = ["DEFAULT_TOLERANCES", "training_rate_views", "changed_rows", "lineage_changes", "revert_lineages"]

#: Largest mean absolute colour change (0..1, over a 3x3 pixel window at the training sampling
#: rate) a lineage may make, per refine method. Chosen on the validation scenes only (chair,
#: tableware; refine's default views; BENCHMARKS.md "Fidelity check"):
#: - "vae" (seeds 0-2; +1 and +2 of the bundled VAEs with each run's lineage;
#:   `tools/tune_fidelity.py`): the largest tolerance tried (0.0025 .. 0.04) at which no pair loses
#:   more than 0.01 dB PSNR at 2x: worst -0.003 dB, 1.9% of the lineages kept at +1. At 0.02 pairs
#:   lost up to 0.067 dB, at 0.04 up to 0.46 dB; without the check Ours-∇² +1 lost 0.48 dB on the mean.
#: - "detail": its changes are none at each Gaussian's own training rate, but the check's views are
#:   scaled to the median rate of what they see, so Gaussians nearer than the median show part of
#:   theirs; the smallest tolerance tried (0.01 .. 0.08) that keeps what the model gains at 2x
#:   within 0.01 dB on every validation pair (0.01 put back 25% of the chair's changes and 0.06 dB).
DEFAULT_TOLERANCES = DEFAULT_FIDELITY


def training_rate_views(cloud: GaussianCloud, cameras: Sequence[Camera], min_height: int = 16,
                        max_height: int = 1024) -> list[Camera]:
    """`cameras` rescaled so that each samples the Gaussians it sees as the training cameras did:
    image height times the median over those Gaussians of (training rate / this camera's rate),
    the training rate read from the cloud's `filter_3D` or `gvae_dilation_3D` (rate = sqrt(variance)
    / size), kept within [min_height, max_height] (a capture trained at 4K is checked at 1024 px:
    coarser than its training, so the check is more lenient there, and affordable). Without
    either size the cameras are returned as they are."""
    rate_of = training_rate(cloud)
    if rate_of is None:
        return list(cameras)
    means = np.asarray(cloud.means, np.float64)
    train_rate = np.where(np.isfinite(rate_of) & (rate_of < 1e29), rate_of, 0.0)
    out = []
    for cam in cameras:
        rate = max_sampling_rate(means, [cam], margin=0.0)
        seen = (rate > 0) & (train_rate > 0) & np.isfinite(train_rate)
        factor = float(np.median(train_rate[seen] / rate[seen])) if seen.any() else 1.0
        out.append(cam.scaled(min(max_height, max(min_height, int(round(cam.height * factor))))))
    return out


def _change_map(before: torch.Tensor, after: torch.Tensor, window: int) -> np.ndarray:
    """(H,W) mean over channels of |after - before|, averaged over a window x window box."""
    diff = (after - before).abs().mean(-1)[None, None]
    return F.avg_pool2d(diff, window, stride=1, padding=window // 2, count_include_pad=False)[0, 0].numpy()


def _sample(change: np.ndarray, cam: Camera, points: np.ndarray) -> np.ndarray:
    """The change map at each point's pixel; 0 where the point is not in the image. In ranges of
    points run in threads (`parallel.in_threads`)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros(len(points))

    def part(a: int, b: int) -> None:
        px, depth = cam.project(points[a:b])
        ok = np.isfinite(px).all(1) & (depth > NEAR_PLANE)
        col = np.where(ok, np.floor(np.nan_to_num(px[:, 0])), -1).astype(np.int64)
        row = np.where(ok, np.floor(np.nan_to_num(px[:, 1])), -1).astype(np.int64)
        ok &= (col >= 0) & (col < change.shape[1]) & (row >= 0) & (row < change.shape[0])
        out[a:b][ok] = change[row[ok], col[ok]]

    in_threads(len(points), part)
    return out


def changed_rows(before: GaussianCloud, after: GaussianCloud) -> np.ndarray:
    """Rows of `after` that draw differently from `before`'s row of the same index: the rows whose
    parameters, anti-aliasing size or changes per octave (`gvae_core.octaves`) differ, and the rows
    past `before`'s end."""
    everywhere, octaves_only = _changes(before, after)
    return np.union1d(everywhere, octaves_only)


def _changes(before: GaussianCloud, after: GaussianCloud) -> tuple[np.ndarray, np.ndarray]:
    """(rows of `after` that may draw differently through any camera: other parameters or
    anti-aliasing size, rows past `before`'s end; the other rows whose changes per octave differ)."""
    n = len(before)
    if len(after) < n:
        raise ValueError(f"fidelity: the refined cloud has fewer rows ({len(after)}) than the input ({n})")

    def differ(a, b) -> np.ndarray:
        return (np.asarray(a)[:n] != np.asarray(b)).reshape(n, -1).any(1)

    params = np.zeros(n, bool)
    for name in PARAMETER_FIELDS:
        params |= differ(getattr(after, name), getattr(before, name))
    octaves = np.zeros(n, bool)
    for key in dict.fromkeys((FILTER_KEY, DILATION_KEY, *stored_keys(before), *stored_keys(after))):
        mask = params if key in (FILTER_KEY, DILATION_KEY) else octaves
        if key in before.extra and key in after.extra:
            mask |= differ(after.extra[key], before.extra[key])
        elif key in before.extra or key in after.extra:
            mask[:] = True
    return (np.concatenate([np.flatnonzero(params), np.arange(n, len(after))]),
            np.flatnonzero(octaves & ~params))


def _seen_above_training_rate(cloud: GaussianCloud, rows: np.ndarray, camera: Camera) -> np.ndarray:
    """(len(rows),) whether `camera` draws each of `rows` of `cloud` with some of its changes per
    octave (t > 0, `octaves.octaves_seen`); none where the cloud has none or no training rate."""
    rate = training_rate(cloud)
    if LIMIT_KEY not in cloud.extra or rate is None or not len(rows):
        return np.zeros(len(rows), bool)
    limit = np.asarray(cloud.extra[LIMIT_KEY]).reshape(-1)
    return octaves_seen(np.asarray(cloud.means)[rows], np.asarray(rate)[rows],
                        limit[rows] if len(limit) > 1 else limit, camera) != 0


def lineage_changes(before: GaussianCloud, after: GaussianCloud, roots: np.ndarray, added: np.ndarray,
                    added_roots: np.ndarray, cameras: Sequence[Camera], *, settings: RenderSettings | None = None,
                    window: int = 3, frames: list[Frame | None] | None = None) -> np.ndarray:
    """(len(roots),) the largest colour change, over `cameras` and over the lineage's Gaussians
    (the root's input and refined centres, and every added row whose root it is), between renders
    of `before` and `after`. `roots`: input rows the refine grew; `added`, `added_roots`: rows of
    `after` it added and the input row each descends from. `frames`: `before`'s frames at `cameras`
    made already (None where not; the frames this makes are stored into it, a list); `after` is
    drawn by redrawing them. A camera through which no row draws differently (the rows whose only
    change is per octave all seen at or below their training rate, t = 0: their parameters are
    drawn as they were) changes no pixel, and is not drawn."""
    roots = np.asarray(roots, np.int64)
    index = np.full(len(before), -1, np.int64)
    index[roots] = np.arange(len(roots))
    owner = index[np.asarray(added_roots, np.int64)]
    added = np.asarray(added, np.int64)[owner >= 0]
    owner = owner[owner >= 0]
    m = len(roots)
    # the refined centres are sampled apart only where they moved (the detail method moves none)
    moved = np.flatnonzero((after.means[roots] != before.means[roots]).any(1))
    points = np.concatenate([before.means[roots], after.means[roots[moved]], after.means[added]]).astype(np.float64)
    worst = np.zeros(m)
    settings = settings or RenderSettings()
    frames = frames if frames is not None else [None] * len(cameras)
    everywhere, octaves_only = _changes(before, after)
    changed = np.union1d(everywhere, octaves_only)
    white = (1.0, 1.0, 1.0)
    with torch.no_grad():
        for i, cam in enumerate(cameras):
            if not len(everywhere) and not (_seen_above_training_rate(after, octaves_only, cam).any()
                                            or _seen_above_training_rate(before, octaves_only, cam).any()):
                continue  # both clouds draw the same parameters through this camera: no pixel changes
            frames[i] = frame = frames[i] or make_frame(before, cam, settings)
            img_b = frame.image(white)
            # every row changed (the detail method changes them all): a new frame, nothing to keep
            img_a = (make_frame(after, cam, settings) if len(changed) == len(after)
                     else redraw(frame, after, changed)).image(white)
            values = _sample(_change_map(img_b.clamp(0, 1), img_a.clamp(0, 1), window), cam, points)
            np.maximum(worst, values[:m], out=worst)
            worst[moved] = np.maximum(worst[moved], values[m:m + len(moved)])
            np.maximum.at(worst, owner, values[m + len(moved):])
    return worst


def revert_lineages(before: GaussianCloud, after: GaussianCloud, n_input: int, added_roots: np.ndarray,
                    reverted: np.ndarray) -> tuple[GaussianCloud, np.ndarray]:
    """`after` with the lineages of input rows `reverted` undone: those rows back to their values in
    `before` (their changes per octave too), the rows added from them dropped. Returns the cloud and
    the mask of added rows kept."""
    keep_added = ~np.isin(added_roots, reverted)
    rows = np.concatenate([np.arange(n_input), n_input + np.flatnonzero(keep_added)])
    out = after.select(rows)
    for name in PARAMETER_FIELDS:
        getattr(out, name)[reverted] = getattr(before, name)[reverted]
    for key in stored_keys(out):  # their changes per octave too
        if key != LIMIT_KEY:
            out.extra[key][reverted] = before.extra[key][reverted] if key in before.extra else 0
    return out, keep_added
