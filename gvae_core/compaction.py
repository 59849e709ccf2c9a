"""Compaction: keep the Gaussians a cloud's picture uses, merge the ones it can do without.

Captures hold millions of Gaussians, many of which change no pixel, and many more that a few
larger ones would draw almost as well. `compact` brings a cloud down to a count (a fraction, a
number, or as few as keep the picture within a PSNR tolerance) in three parts:

1. **Score** every Gaussian by how much the picture depends on it: by default the exact
   Gauss-Newton block of position and log-scale over a few views (`gvae_core.hessian`; the
   capture's cameras or views placed around the cloud), scored as log det(I + H/lambda), the
   sensitivity of PUP 3D-GS. Baselines for comparison: LightGaussian's global significance
   (pixels hit x opacity x volume^0.1), opacity, random.
2. **Remove** down to the count. `merge` (the default): the Gaussians no view sees (score 0,
   they change no pixel) are dropped, and so are the lowest-scoring PRUNE_FRACTION of the input
   (those the picture depends on least: merged into a neighbour, they would change it for
   little; never more than the removal); the rest are merged pairwise, over a k-nearest-neighbour
   graph, pass after pass, each pass taking the cheapest disjoint pairs (mutually cheapest
   edges), until the count is reached. A pair becomes one Gaussian that matches its moments
   with mass weights (mass = opacity x mean projected area): position, covariance, colour (every
   SH coefficient), and an opacity that keeps the mass (never above what the two draw
   together). The cost of a pair is its mass times how much merging changes it (the mass-weighted
   KL divergence of the members from the merged Gaussian, plus their colour difference) times the
   two's scores summed: pairs the picture is insensitive to go first. `prune`: the lowest
   scores are dropped (PUP's pruning).
3. **Fine-tune** (with the capture's images, `images`, or against the input's own renders,
   `distill`): PUP's rounds, each removing part of the way to the count and then training the
   survivors for `iterations` with the project's trainer (`train.fine_tune`: its recipe, one
   stage's schedule, the cloud's anti-aliasing). Without either, compaction is steps 1 and 2 only.

What was measured (BENCHMARKS.md, "Compaction"): merging keeps the picture far better than any
pruning score without fine-tuning; the Hessian's weighting of the merges changes PSNR by less than
0.01 dB against an unweighted merge: its use is choosing what is dropped rather than merged (what
no view sees, and the lowest-scoring tenth); with fine-tuning, merging then fine-tuning also beats
pruning then fine-tuning.

Untouched Gaussians keep their values bit for bit, their rows in input order; a merged Gaussian
takes the row (and the extra properties) of its most massive member, with the anti-aliasing size
(`filter_3D`, `gvae_dilation_3D`) mass-averaged. The result says what happened to every input
row and how far the compacted picture is from the input's: PSNR of their renders from the scoring
views.

`merge_groups_reference` is the slow, obviously correct definition of a merge (a loop over the
groups) the tests hold the vectorised `merge_groups` to; `pixel_hits_reference` likewise for the
LightGaussian hit counts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from . import quaternions
from .antialias import DILATION_KEY, FILTER_KEY, resolve_antialias, with_dilation_3d
from .budget import select_budget
from .camera import Camera
from .capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS, default_views, scoring_views
from .cloud import GaussianCloud
from .conventions import LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_C0
from .fidelity import training_rate_views
from .hessian import hessian_scores, scoring_settings
from .losses import psnr
from .rendering import RenderSettings, prepare_view, render
from .rendering.rasterize import (T_MIN, _alpha_and_transmittance, _pixel_monomials, _tile_centres, _weights,
                                  live_blocks, pair_table, tile_groups)
from .resources import check_compact_memory, reuse_freed_memory

__all__ = ["SCORES", "REMOVALS", "CompactResult", "compact", "compaction_scores", "merge_groups",
           "merge_groups_reference", "own_renders", "pixel_hits", "pixel_hits_reference", "removal_groups",
           "target_count"]

#: Per-Gaussian scores `compact` can rank by: the default, then the baselines.
SCORES = ("hessian", "lightgaussian", "opacity", "random")
#: How Gaussians are removed: merged into neighbours, or dropped.
REMOVALS = ("merge", "prune")
#: Neighbours per Gaussian in the merge graph (4, 6 and 8 tried on the validation scenes: within
#: 0.05 dB of each other; 4 is the fastest).
NEIGHBOURS = 4
#: Weight of the colour difference (RGB of the SH DC term, squared) against the shape change
#: (nats of KL divergence) in the merge cost.
COLOUR_WEIGHT = 10.0
#: A Gaussian whose score is at most this changes no pixel of the scoring views.
UNSEEN = 1e-6
#: Fraction of the input that `merge` drops (the lowest scores among the seen ones, never more than
#: the removal) before merging the rest. On the validation and training scenes (6, seed 0), at 50 /
#: 30 / 10% kept: merging everything -0.44 / -0.84 / -2.19 dB, 0.05 -0.41 / -0.81 / -2.16, 0.1
#: -0.37 / -0.77 / -2.18 (no scene worse at 50 or 30%), 0.15 -0.35 / -0.78 / -2.18 (one scene
#: worse), 0.2 -0.39 / -0.82 / -2.20 (BENCHMARKS.md, "Compaction").
PRUNE_FRACTION = 0.1
#: LightGaussian's volume exponent (its v_pow) and the quantile its volumes are taken relative to.
LIGHTGAUSSIAN_POWER = 0.1
LIGHTGAUSSIAN_QUANTILE = 0.1
#: Fine-tuning iterations per round with images (PUP 3D-GS fine-tunes 5,000 after each pruning).
DEFAULT_ITERATIONS = 5000
#: Views of the input's own renders that `distill` fine-tunes against.
DISTILL_VIEWS = 32
#: PSNR reported when the compacted renders equal the input's.
PSNR_CAP = 100.0


@dataclass
class CompactResult:
    """The compacted cloud and what happened to the input's Gaussians.

    rows (M,): the input row each output row stands for (its own row, or for a merged Gaussian
    the row of its most massive member), ascending; groups (N,): the output row each input row
    went into, -1 where it was dropped; scores (N,): the input's scores (the first round's with
    images); psnr: PSNR (dB) of the compacted cloud's renders against the input's from the
    scoring views, over white; timings: seconds per part; rounds: per fine-tuning round, its count,
    seconds and PSNR against the training images (or the input's own renders) before and after."""

    cloud: GaussianCloud
    rows: np.ndarray
    groups: np.ndarray
    scores: np.ndarray
    psnr: float
    timings: dict[str, float] = field(default_factory=dict)
    rounds: list[dict] = field(default_factory=list)
    #: The PSNR tolerance the count was found for (None: a fraction or count was asked for).
    tolerance: float | None = None

    @property
    def n_input(self) -> int:
        return len(self.groups)

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
        return (f"{self.n_input:,} Gaussians in, {len(self.cloud):,} out ({kept:.1%}): "
                f"{self.dropped:,} dropped, {self.merged:,} merged into others{tuned}; PSNR against the input's "
                f"render {self.psnr:.2f} dB; {self.timings.get('total', 0.0):.2f} s ({times})")


# ------------------------------------------------------------------------------ checks

def target_count(n: int, keep=None, count=None) -> int:
    """The count `keep` (a fraction in (0, 1]) or `count` (1..n) asks for of `n` Gaussians."""
    if (keep is None) == (count is None):
        raise ValueError("compact: give one of keep (a fraction) or count")
    if keep is not None:
        try:
            keep = float(keep)
        except (TypeError, ValueError):
            raise ValueError(f"compact: keep must be a fraction in (0, 1], got {keep!r}") from None
        if not 0.0 < keep <= 1.0:
            raise ValueError(f"compact: keep must be a fraction in (0, 1], got {keep!r}")
        return max(1, min(n, round(keep * n)))
    if isinstance(count, (bool, np.bool_)) or not isinstance(count, (int, np.integer)):
        raise ValueError(f"compact: count must be a whole number of Gaussians, got {count!r}")
    if not 1 <= count <= n:
        raise ValueError(f"compact: count must be between 1 and the input's {n:,} Gaussians, got {count:,}")
    return int(count)


def _check_input(src: GaussianCloud, score: str, removal: str, prune: float) -> None:
    if len(src) == 0:
        raise ValueError("compact: the cloud is empty (nothing to compact)")
    if isinstance(prune, bool) or not isinstance(prune, (int, float, np.floating)) or not 0.0 <= prune < 1.0:
        raise ValueError(f"compact: prune must be a fraction in [0, 1), got {prune!r}")
    if score not in SCORES:
        raise ValueError(f"compact: score must be one of {', '.join(SCORES)}, got {score!r}")
    if removal not in REMOVALS:
        raise ValueError(f"compact: removal must be one of {', '.join(REMOVALS)}, got {removal!r}")
    bad = src.nonfinite_rows()
    if len(bad):
        rows = ", ".join(str(int(r)) for r in bad[:5])
        raise ValueError(f"compact: the cloud has non-finite values in {len(bad)} row(s) "
                         f"[{rows}{', ...' if len(bad) > 5 else ''}]; sanitize it first")


def _whole(value, name: str, low: int) -> int:
    """`value` as a whole number >= low, else ValueError naming it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
        raise ValueError(f"compact: {name} must be a whole number >= {low}, got {value!r}")
    return int(value)


def _check_arguments(n: int, keep, count, tolerance, images, distill, rounds, iterations) -> int | None:
    """The target count (None: found from the tolerance), or ValueError for arguments that do not
    go together or are out of range."""
    if distill:
        _whole(distill, "distill (iterations)", 0)
        if images is not None or tolerance is not None:
            raise ValueError("compact: distill fine-tunes against the input's own renders: without images or a "
                             "tolerance")
    if images is not None or distill:
        _whole(rounds, "rounds", 1)
        _whole(iterations, "iterations", 0)
        if images is not None and len(images) == 0:
            raise ValueError("compact: no images")
    if tolerance is None:
        return target_count(n, keep, count)
    if keep is not None or count is not None:
        raise ValueError("compact: give one of keep, count or tolerance")
    if images is not None:
        raise ValueError("compact: a tolerance works without images (the count is found from the input's own "
                         "render); with images give a fraction or a count")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating)) \
            or not math.isfinite(tolerance) or tolerance <= 0:
        raise ValueError(f"compact: tolerance must be a PSNR in dB > 0 (for example 40), got {tolerance!r}")
    return None


# ------------------------------------------------------------------------------ scores

def _views(src: GaussianCloud, cameras, views: int, resolution: int) -> list[Camera]:
    """The scoring views, as the Hessian picks them (`hessian_blocks`)."""
    if cameras is not None:
        return scoring_views(cameras, views, resolution, src)
    return default_views(src, views or DEFAULT_VIEWS, resolution)


def pixel_hits(cloud: GaussianCloud, cameras: Sequence[Camera], settings: RenderSettings | None = None) -> np.ndarray:
    """(N,) int64: the number of pixels, over `cameras`, that each Gaussian is composited into
    (alpha >= 1/255, before the pixel stops): LightGaussian's hit count. One sweep over each
    view's tile lists, as the renderer composites them."""
    settings = settings or RenderSettings()
    hits = torch.zeros(len(cloud) + 1, dtype=torch.int64)
    with torch.no_grad():
        for cam in cameras:
            _, binning, table = prepare_view(cloud, cam, settings)
            if binning.num_pairs == 0:
                continue
            pairs = pair_table(table, binning)
            ids_of_pairs = torch.cat([binning.gaussian_ids, binning.gaussian_ids.new_full((1,), len(cloud))])
            ts = binning.tile_size
            p = ts * ts
            local = torch.arange(p)
            mono = _pixel_monomials(ts, pairs.dtype, pairs.device)
            for tiles, kmax in tile_groups(binning, settings.block, settings.budget):
                b = tiles.shape[0]
                cx, cy = _tile_centres(tiles, binning, pairs.dtype)
                inside = (((tiles % binning.tiles_x)[:, None] * ts + local % ts < cam.width)
                          & ((tiles // binning.tiles_x)[:, None] * ts + local // ts < cam.height))
                start, count = binning.offsets[tiles], binning.counts[tiles]
                trans = torch.ones((b, p), dtype=pairs.dtype)
                done = torch.zeros((b, p), dtype=torch.bool)
                for active, k0, kb, ids in live_blocks(start, count, done, kmax, settings.block, pairs.shape[0] - 1):
                    gd = pairs.index_select(0, ids.reshape(-1)).reshape(kb, -1, pairs.shape[1])
                    was_done = done[active]
                    t_prev = trans[active]
                    t0 = torch.where(was_done, torch.zeros_like(t_prev), t_prev)
                    _, tr, _, _ = _alpha_and_transmittance(gd, cx[active], cy[active], mono, t0)
                    w, kept = _weights(tr)
                    if k0 + settings.block < kmax:
                        trans[active] = torch.where(was_done, t_prev, torch.minimum(t0, kept.amin(0)))
                        done[active] = was_done | (tr[-1] < T_MIN)
                    count_k = ((w > 0) & inside[active]).sum(-1).reshape(-1)
                    hits.index_add_(0, ids_of_pairs.index_select(0, ids.reshape(-1)), count_k)
    return hits[:-1].numpy()


def pixel_hits_reference(cloud: GaussianCloud, cameras: Sequence[Camera], antialias: str = "auto") -> np.ndarray:
    """Slow definition of `pixel_hits`: every pixel, every Gaussian in depth order, with the
    renderer's alpha, skip and stop rules (the float64 reference projection)."""
    from .rendering.reference import project_reference  # noqa: PLC0415 - tests only

    hits = np.zeros(len(cloud), np.int64)
    for cam in cameras:
        pr = project_reference(cloud, cam, antialias=antialias)
        idx = np.flatnonzero(pr["valid"])
        idx = idx[np.argsort(pr["depth"][idx], kind="stable")]
        for row in range(cam.height):
            for col in range(cam.width):
                d = np.array([col + 0.5, row + 0.5]) - pr["mean2d"][idx]
                alpha = np.minimum(0.99, pr["opacity"][idx] * np.exp(-0.5 * np.einsum("ni,nij,nj->n", d,
                                                                                        pr["conic"][idx], d)))
                trans = 1.0
                for i in np.flatnonzero(alpha >= 1.0 / 255.0):
                    if trans * (1.0 - alpha[i]) < 1e-4:
                        break
                    hits[idx[i]] += 1
                    trans *= 1.0 - alpha[i]
    return hits


def compaction_scores(cloud: GaussianCloud, score: str = "hessian", cameras: Sequence[Camera] | None = None, *,
                      settings: RenderSettings | None = None, seed: int = 0, frames: list | None = None,
                      timings: dict | None = None, progress=None) -> np.ndarray:
    """(N,) float64 scores >= 0 from `cameras` (views as given): "hessian" (log det(I + H/lambda),
    `hessian_scores`; `frames` gets each view's frame of the cloud), "lightgaussian" (pixels hit x
    opacity x (volume / the volume of the LIGHTGAUSSIAN_QUANTILE)^LIGHTGAUSSIAN_POWER, as in
    LightGaussian's global significance), "opacity" (activated), "random" (uniform, `seed`)."""
    src = cloud.numpy()
    if score == "hessian":
        return hessian_scores(src, cameras, views=0, render_settings=settings, frames=frames, timings=timings,
                              progress=progress).numpy().astype(np.float64)
    if score == "lightgaussian":
        hits = pixel_hits(src, cameras, settings).astype(np.float64)
        volume = np.exp(np.clip(src.scales.astype(np.float64), *LOG_SCALE_RANGE).sum(1))
        ref = max(float(np.quantile(volume, LIGHTGAUSSIAN_QUANTILE)), 1e-300)
        return hits * src.activated_opacities().astype(np.float64) * (volume / ref) ** LIGHTGAUSSIAN_POWER
    if score == "opacity":
        return src.activated_opacities().astype(np.float64)
    if score == "random":
        return np.random.default_rng(seed).random(len(src))
    raise ValueError(f"compact: score must be one of {', '.join(SCORES)}, got {score!r}")


def _merge_weights(scores: np.ndarray, score: str) -> np.ndarray:
    """How much the picture depends on each Gaussian, >= 0, 0 for one no view sees: the score
    itself (the Hessian's log det(I + H/lambda); its exponent, det(I + H/lambda) - 1, was tried
    and lost up to 0.36 dB at 10% kept on the validation scenes); ones for "random" (a merge that
    no score guides)."""
    if score == "random":
        return np.ones_like(scores)
    return np.maximum(scores, 0.0)


# ------------------------------------------------------------------------------ moments

@dataclass
class _Moments:
    """What merging needs of each Gaussian (float64): mass m, centre mu (relative to `origin`),
    covariance sigma (with `floor` of variance added on the diagonal, far below what a picture
    shows, so that flat Gaussians have a finite log det; symmetric 3x3 packed as xx, xy, xz, yy,
    yz, zz), its log det, the DC colour and the merge weight."""

    mass: np.ndarray
    mu: np.ndarray
    sigma: np.ndarray
    log_det: np.ndarray
    floor: float
    colour: np.ndarray
    weight: np.ndarray
    origin: np.ndarray


#: Packed (6) index of each entry of a symmetric 3x3 matrix, and of the diagonal.
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
_DIAG = np.array([0, 3, 5])


def _unpack(s: np.ndarray) -> np.ndarray:
    return s[:, _SYM]


def _outer(d: np.ndarray) -> np.ndarray:
    """Packed d dᵀ of (N,3) vectors."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack([x * x, x * y, x * z, y * y, y * z, z * z], 1)


def _det(s: np.ndarray) -> np.ndarray:
    """det of packed symmetric 3x3 matrices."""
    xx, xy, xz, yy, yz, zz = s.T
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def _e2(s: np.ndarray) -> np.ndarray:
    """The sum of the 2x2 principal minors of packed symmetric 3x3 matrices: 3 x the mean over
    directions of the determinant of the projection along them (projected area squared)."""
    xx, xy, xz, yy, yz, zz = s.T
    return xx * yy - xy * xy + xx * zz - xz * xz + yy * zz - yz * yz


def _log_det(s: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(_det(s), 1e-300))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, *OPACITY_LOGIT_RANGE)))


def _covariances(src: GaussianCloud) -> np.ndarray:
    """Packed covariances R diag(exp(2 log-scale)) Rᵀ (float64)."""
    rot = quaternions.to_rotmat(quaternions.normalize(src.quats.astype(np.float64)))
    scaled = rot * np.exp(np.clip(src.scales.astype(np.float64), *LOG_SCALE_RANGE))[:, None, :]
    return _pack(scaled @ scaled.transpose(0, 2, 1))


def _pack(full: np.ndarray) -> np.ndarray:
    """(N,6) packed upper triangles of (N,3,3) symmetric matrices."""
    return full.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]


def _moments(src: GaussianCloud, weight: np.ndarray) -> _Moments:
    """The stored Gaussians as they are (their anti-aliasing filter left out: adding it to the
    covariances, and Mip-Splatting's opacity compensation, lost 0.06-0.10 dB at 50-30% kept on
    the validation scenes); mass = opacity x sqrt(sum of the 2x2 principal minors)."""
    center, half = src.normalization()
    floor = (2.5e-4 * half) ** 2  # 1/4000 of the scene's size: far below a pixel of any view of it
    sigma = _covariances(src)
    sigma[:, _DIAG] += floor
    mass = _sigmoid(src.opacities.astype(np.float64)) * np.sqrt(np.maximum(_e2(sigma), 0.0))
    return _Moments(mass=mass, mu=src.means.astype(np.float64) - center, sigma=sigma, log_det=_log_det(sigma),
                    floor=floor, colour=SH_C0 * src.sh_dc.astype(np.float64), weight=np.asarray(weight, np.float64),
                    origin=center)


def _pair(m: _Moments, a: np.ndarray, b: np.ndarray):
    """Mass weights of a and b in each pair, the pair's total mass and its moment-matched covariance."""
    ma, mb = m.mass[a], m.mass[b]
    total = np.maximum(ma + mb, 1e-300)
    wa = ma / total
    wb = 1.0 - wa
    s = wa[:, None] * m.sigma[a] + wb[:, None] * m.sigma[b] + (wa * wb)[:, None] * _outer(m.mu[a] - m.mu[b])
    return wa, wb, total, s


def _pair_cost(m: _Moments, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cost of merging each pair (a[i], b[i]): (weight_a + weight_b) x (mass_a + mass_b) x (the
    mass-weighted KL divergence of the two from their moment match, 1/2 (log det S - w_a log det
    S_a - w_b log det S_b), plus COLOUR_WEIGHT x w_a w_b |colour_a - colour_b|²)."""
    wa, wb, total, s = _pair(m, a, b)
    shape = 0.5 * (_log_det(s) - wa * m.log_det[a] - wb * m.log_det[b])
    colour = wa * wb * np.square(m.colour[a] - m.colour[b]).sum(1)
    return (m.weight[a] + m.weight[b]) * total * (np.maximum(shape, 0.0) + COLOUR_WEIGHT * colour)


def _merge_pairs(m: _Moments, a: np.ndarray, b: np.ndarray) -> None:
    """Merge each b[i] into a[i] in place (moments and weights add; b's entries are left stale)."""
    wa, wb, total, s = _pair(m, a, b)
    m.sigma[a] = s
    m.log_det[a] = _log_det(s)
    m.mu[a] = wa[:, None] * m.mu[a] + wb[:, None] * m.mu[b]
    m.colour[a] = wa[:, None] * m.colour[a] + wb[:, None] * m.colour[b]
    m.mass[a] = total
    m.weight[a] = m.weight[a] + m.weight[b]


def _matching(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n: int, limit: int, rounds: int = 4) -> np.ndarray:
    """Edges (indices) of a matching: repeatedly every edge that is the cheapest of both its ends
    among the edges whose ends are both free (what greedy matching takes, found in parallel), for
    a few rounds or until `limit` edges; the `limit` cheapest of them."""
    order = np.argsort(cost, kind="stable")
    sa, sb = a[order], b[order]
    free = np.ones(n, bool)
    chosen: list[np.ndarray] = []
    total = 0
    for _ in range(rounds):
        live = np.flatnonzero(free[sa] & free[sb])  # ranks, ascending
        if len(live) == 0:
            break
        first = np.full(n, len(order), np.int64)
        np.minimum.at(first, sa[live], live)
        np.minimum.at(first, sb[live], live)
        pick = live[(first[sa[live]] == live) & (first[sb[live]] == live)]
        chosen.append(pick)
        free[sa[pick]] = False
        free[sb[pick]] = False
        total += len(pick)
        if total >= limit:
            break
    ranks = np.sort(np.concatenate(chosen))[:limit] if chosen else np.zeros(0, np.int64)
    return order[ranks]


def _knn_edges(mu: np.ndarray, nodes: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Edges (a < b, each once) between each of `nodes` and its `k` nearest others (by centre)."""
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import; only merging needs it

    k = min(k, len(nodes) - 1)
    if k < 1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    _, nb = cKDTree(mu[nodes]).query(mu[nodes], k + 1, workers=-1)
    a = np.repeat(np.arange(len(nodes)), k)
    b = nb[:, 1:].reshape(-1)
    ok = (b < len(nodes)) & (a != b)
    key = np.unique(np.minimum(a[ok], b[ok]) * len(nodes) + np.maximum(a[ok], b[ok]))
    return nodes[key // len(nodes)], nodes[key % len(nodes)]


def _merge_owner(m: _Moments, target: int, neighbours: int, progress=None) -> np.ndarray:
    """(N,) the group (0..target-1) of each Gaussian after merging pairs, cheapest first, pass
    after pass over the k-nearest-neighbour graph (contracted as groups form; made again among
    the groups if it runs out of edges), until `target` groups are left. Each pass recomputes
    only the costs of the edges whose ends changed."""
    n = len(m.mass)
    owner = np.arange(n)
    a, b = _knn_edges(m.mu, owner, neighbours)
    cost = _pair_cost(m, a, b)
    alive = n
    while alive > target:
        if len(a) == 0:
            a, b = _knn_edges(m.mu, np.flatnonzero(owner == np.arange(n)), neighbours)
            if len(a) == 0:
                break
            cost = _pair_cost(m, a, b)
        pick = _matching(a, b, cost, n, alive - target)
        pa, pb = a[pick], b[pick]
        _merge_pairs(m, pa, pb)
        owner[pb] = pa
        alive -= len(pick)
        touched = np.zeros(n, bool)
        touched[pa] = touched[pb] = True
        changed = touched[a] | touched[b]
        owner = owner_root(owner)
        a, b = owner[a], owner[b]  # contract the graph onto the groups' representatives
        keep = a != b
        a, b, cost, changed = np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep]), cost[keep], changed[keep]
        redo = np.flatnonzero(changed)
        cost[redo] = _pair_cost(m, a[redo], b[redo])
        if progress is not None:
            progress(1.0 - (alive - target) / max(n - target, 1), f"merging: {alive:,} Gaussians")
    _, groups = np.unique(owner, return_inverse=True)
    return groups


def owner_root(owner: np.ndarray) -> np.ndarray:
    """Each entry's root in a forest given by parent pointers (roots point at themselves)."""
    while True:
        nxt = owner[owner]
        if np.array_equal(nxt, owner):
            return owner
        owner = nxt


# ------------------------------------------------------------------------------ assembling

def merge_groups(cloud: GaussianCloud, groups: np.ndarray) -> tuple[GaussianCloud, np.ndarray]:
    """The cloud with the Gaussians of each group (groups[i] = output row of input row i, -1:
    dropped; every output row 0..G-1 used) merged into one, and the input row each output row
    takes (its most massive member's). Single-member groups keep their values bit for bit; a
    merged one matches its members' moments with mass weights (mass = opacity x sqrt(sum of the
    2x2 principal minors of the covariance): the mean over directions of its projected area, up
    to a constant): centre, covariance, every SH coefficient, the anti-aliasing size
    (`filter_3D`, `gvae_dilation_3D`; mass-weighted in variance), and the opacity that keeps the
    total mass, capped by what the members draw together (1 - prod(1 - o))."""
    src = cloud.numpy()
    groups = np.asarray(groups, np.int64)
    g = int(groups.max(initial=-1)) + 1
    member = groups >= 0
    size = np.bincount(groups[member], minlength=g)
    multi = np.flatnonzero(size > 1)
    idx = np.flatnonzero(member & (size[np.maximum(groups, 0)] > 1))
    idx = idx[np.argsort(groups[idx], kind="stable")]  # by group: each group's members one segment
    members = src.select(idx)
    m = _moments(members, np.zeros(len(idx)))
    rows = _representatives(groups, idx, m.mass)
    out = src.select(rows).copy()
    if len(multi):
        grp = np.repeat(np.arange(len(multi)), size[multi])  # (idx is sorted by group)
        starts = np.concatenate([[0], np.cumsum(size[multi])[:-1]])
        mass = np.add.reduceat(m.mass, starts)
        w = m.mass / np.maximum(mass[grp], 1e-300)
        mu = np.add.reduceat(w[:, None] * m.mu, starts)
        sigma = np.add.reduceat(w[:, None] * (m.sigma + _outer(m.mu - mu[grp])), starts)
        _write_merged(out, multi, members, grp, starts, w, mu + m.origin, sigma, mass, m.floor)
    return out, rows


def _representatives(groups: np.ndarray, idx: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """The input row each output row takes: its own, or the most massive of the rows `idx` (with
    `mass`) merged into it (ties: the lower row)."""
    g = int(groups.max(initial=-1)) + 1
    rows = np.zeros(g, np.int64)
    kept = np.flatnonzero(groups >= 0)
    rows[groups[kept]] = kept
    order = idx[np.lexsort((-idx, mass))]  # ascending mass: the heaviest written last
    rows[groups[order]] = order
    return rows


def _write_merged(out: GaussianCloud, multi, members: GaussianCloud, grp, starts, w, mu, sigma, mass,
                  floor: float) -> None:
    """Write the merged Gaussians (their moments given; `floor` on the covariances' diagonal)
    into rows `multi` of `out`; `members`: the rows merged, sorted by their group `grp` (each
    group's first row at `starts`), mass weight `w`."""
    k = len(multi)
    vals, vecs = np.linalg.eigh(_unpack(sigma))
    vecs[np.linalg.det(vecs) < 0, :, 0] *= -1.0  # a rotation, not a reflection
    log_scale = np.clip(0.5 * np.log(np.maximum(vals - floor, 1e-300)), *LOG_SCALE_RANGE)
    scaled = vecs * np.exp(log_scale)[:, None, :]
    stored = _pack(scaled @ scaled.transpose(0, 2, 1))  # as stored (scales clamped)
    stored[:, _DIAG] += floor
    opacity = mass / np.maximum(np.sqrt(np.maximum(_e2(stored), 0.0)), 1e-300)
    o = _sigmoid(members.opacities.astype(np.float64))
    together = -np.expm1(np.bincount(grp, np.log1p(-np.minimum(o, 1.0 - 1e-12)), k))
    opacity = np.clip(np.minimum(opacity, together), 1e-6, 1.0 - 1e-6)
    out.means[multi] = mu
    out.scales[multi] = log_scale
    out.quats[multi] = quaternions.from_rotmat(vecs)
    out.opacities[multi] = np.log(opacity / (1.0 - opacity))
    w32 = w.astype(np.float32)  # (the SH sums in the cloud's precision: they are most of the work)
    out.sh_dc[multi] = np.add.reduceat(w32[:, None] * members.sh_dc, starts)
    if members.sh_rest.shape[1]:
        out.sh_rest[multi] = np.add.reduceat(w32[:, None, None] * members.sh_rest, starts)
    for key in (FILTER_KEY, DILATION_KEY):
        if key in out.extra and np.asarray(out.extra[key]).ndim == 1:
            v = np.square(np.asarray(members.extra[key], np.float64))
            out.extra[key][multi] = np.sqrt(np.bincount(grp, w * v, k))


def merge_groups_reference(cloud: GaussianCloud, groups: np.ndarray) -> GaussianCloud:
    """Slow definition of `merge_groups` (one group at a time, plain formulas)."""
    src = cloud.numpy()
    groups = np.asarray(groups, np.int64)
    center, half = src.normalization()
    floor = (2.5e-4 * half) ** 2 * np.eye(3)
    minors = lambda s: sum(np.linalg.det(s[np.ix_(p, p)]) for p in ([0, 1], [0, 2], [1, 2]))  # noqa: E731
    parts = []
    for j in range(int(groups.max(initial=-1)) + 1):
        idx = np.flatnonzero(groups == j)
        if len(idx) == 1:
            parts.append(src.select(idx))
            continue
        mass, mus, sigmas, ops = [], [], [], []
        for i in idx:
            rot = quaternions.to_rotmat(quaternions.normalize(src.quats[i].astype(np.float64)))
            s = rot @ np.diag(np.exp(2 * np.clip(src.scales[i].astype(np.float64), *LOG_SCALE_RANGE))) @ rot.T
            o = 1.0 / (1.0 + math.exp(-float(np.clip(src.opacities[i], *OPACITY_LOGIT_RANGE))))
            mass.append(o * math.sqrt(minors(s + floor)))
            mus.append(src.means[i].astype(np.float64) - center)
            sigmas.append(s + floor)
            ops.append(o)
        mass = np.array(mass)
        w = mass / mass.sum()
        mu = sum(wi * x for wi, x in zip(w, mus))
        second = sum(wi * (s + np.outer(x - mu, x - mu)) for wi, s, x in zip(w, sigmas, mus))
        vals, vecs = np.linalg.eigh(second - floor)
        if np.linalg.det(vecs) < 0:
            vecs[:, 0] *= -1
        ls = np.clip(0.5 * np.log(np.maximum(vals, 1e-300)), *LOG_SCALE_RANGE)
        s = vecs @ np.diag(np.exp(2 * ls)) @ vecs.T
        o = min(mass.sum() / math.sqrt(minors(s + floor)), 1.0 - np.prod([1.0 - min(x, 1.0 - 1e-12) for x in ops]))
        o = min(max(o, 1e-6), 1.0 - 1e-6)
        one = src.select([idx[np.lexsort((-idx, mass))[-1]]]).copy()
        one.means[0] = mu + center
        one.scales[0] = ls
        one.quats[0] = quaternions.from_rotmat(vecs)
        one.opacities[0] = math.log(o / (1 - o))
        one.sh_dc[0] = sum(wi * src.sh_dc[i] for wi, i in zip(w, idx))
        one.sh_rest[0] = sum(wi * src.sh_rest[i] for wi, i in zip(w, idx))
        for key in (FILTER_KEY, DILATION_KEY):
            if key in one.extra:
                one.extra[key][0] = math.sqrt(sum(wi * float(src.extra[key][i]) ** 2 for wi, i in zip(w, idx)))
        parts.append(one)
    return GaussianCloud.concat(parts) if parts else GaussianCloud.empty(src.sh_degree)


def _groups_by_pruning(scores: np.ndarray, target: int) -> np.ndarray:
    kept = select_budget(scores, int(target))
    groups = np.full(len(scores), -1, np.int64)
    groups[kept] = np.arange(len(kept))
    return groups


def removal_groups(src: GaussianCloud, scores: np.ndarray, target: int, *, score: str = "hessian",
                   removal: str = "merge", neighbours: int = NEIGHBOURS, prune: float = PRUNE_FRACTION,
                   progress=None) -> np.ndarray:
    """(N,) the output row of each input row (-1: dropped) that brings `src` to `target` rows:
    removal "prune" keeps the `target` highest scores; "merge" drops what no view sees and, for a
    score of the picture ("hessian", "lightgaussian"), the lowest-scoring fraction `prune` of the
    input besides, and merges the rest pairwise (module docstring), weighted by `_merge_weights`."""
    n = len(src)
    if target >= n:
        return np.arange(n)
    if removal == "prune":
        return _groups_by_pruning(scores, target)
    weight = _merge_weights(scores, score)
    seen = np.arange(n)
    if score in ("hessian", "lightgaussian"):
        seen = np.flatnonzero(weight > UNSEEN)
        if len(seen) <= target:  # dropping what is not seen is enough: keep the highest scores
            return _groups_by_pruning(scores, target)
        drop = min(int(round(prune * n)), len(seen) - target)
        seen = np.sort(seen[np.argsort(scores[seen], kind="stable")[drop:]])
    m = _moments(src.select(seen), weight[seen])
    sub = _merge_owner(m, target, neighbours, progress)
    groups = np.full(n, -1, np.int64)
    groups[seen] = sub
    # output rows in input order of their representatives
    first = np.full(target, n, np.int64)
    np.minimum.at(first, sub, seen)
    remap = np.empty(target, np.int64)
    remap[np.argsort(first, kind="stable")] = np.arange(target)
    groups[seen] = remap[sub]
    return groups


def _ordered(groups: np.ndarray, rows: np.ndarray, cloud: GaussianCloud) -> tuple:
    """Output rows sorted by their representative's input row (the input's order kept)."""
    order = np.argsort(rows, kind="stable")
    if np.array_equal(order, np.arange(len(rows))):
        return groups, rows, cloud
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    return np.where(groups >= 0, inverse[np.maximum(groups, 0)], -1), rows[order], cloud.select(order)


# ------------------------------------------------------------------------------ compact

def _report_psnr(frames_or_images, cloud: GaussianCloud, cams: Sequence[Camera], settings: RenderSettings) -> float:
    """Mean PSNR of `cloud`'s renders from `cams` (over white) against the input's images."""
    values = []
    with torch.no_grad():
        for ref, cam in zip(frames_or_images, cams):
            img = render(cloud, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1)
            values.append(min(psnr(img, ref), PSNR_CAP))
    return float(np.mean(values)) if values else PSNR_CAP


def _input_images(src: GaussianCloud, cams: Sequence[Camera], settings: RenderSettings, frames=None) -> list:
    """The input's renders (over white) from `cams`: from the Hessian's frames when it made them."""
    if frames and len(frames) == len(cams):
        return [f.image((1.0, 1.0, 1.0)).clamp(0, 1) for f in frames]
    with torch.no_grad():
        return [render(src, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1) for cam in cams]


def compact(cloud: GaussianCloud, *, keep: float | None = None, count: int | None = None,
            tolerance: float | None = None, cameras: Sequence[Camera] | None = None, views: int = DEFAULT_VIEWS,
            resolution: int = DEFAULT_RESOLUTION, score: str = "hessian", removal: str = "merge",
            images=None, rounds: int = 2, iterations: int = DEFAULT_ITERATIONS, distill: int = 0, seed: int = 0,
            neighbours: int = NEIGHBOURS, prune: float = PRUNE_FRACTION,
            render_settings: RenderSettings | None = None,
            progress: Callable[[float, str], None] | None = None, check_memory: bool = True) -> CompactResult:
    """`cloud` with fewer Gaussians: `keep` a fraction in (0, 1], a `count`, or the fewest whose
    render from the scoring views, at the training sampling rate, stays at or above `tolerance`
    dB of PSNR against the input's (give exactly one). See the module docstring for how.

    `cameras`: the capture's cameras to score from (`capture.load_cameras`; `views` of them are
    used, spread out, scaled to `resolution` px high), else `views` views placed around the cloud.
    `score`: one of SCORES; `removal`: "merge" (default) or "prune"; `prune`: the fraction of the
    input that merging drops first, the lowest scores (`removal_groups`; 0: merge all that is
    seen); `neighbours`: of each Gaussian in the merge graph. `images`: the capture's training
    images (`datasets.Views`, in the cloud's frame, at the resolution to fine-tune at):
    `rounds` rounds of removal and `iterations` of fine-tuning each (`train.fine_tune`), the
    scores then come from `images`' cameras. `distill`: without images, fine-tune as with them,
    `distill` iterations a round, against the input's own renders (`own_renders`: DISTILL_VIEWS
    views, of `cameras` or placed around the cloud, at the training sampling rate); 0: prune and
    merge only. `seed`: the random score and the fine-tuning.
    `progress(fraction, message)` as the work goes on (an exception it raises stops the work:
    how the Blender job cancels). `check_memory`: refuse a cloud whose estimated peak memory
    exceeds what is free (`resources.NotEnoughMemoryError`). Every check on the arguments and the
    cloud is made before any work; the input is never modified."""
    t_start = time.perf_counter()
    say = progress or (lambda fraction, message: None)
    src = cloud.numpy()
    _check_input(src, score, removal, prune)
    n = len(src)
    target = _check_arguments(n, keep, count, tolerance, images, distill, rounds, iterations)
    if check_memory:
        extra = sum(int(np.prod(np.shape(v)[1:], dtype=np.int64)) for v in src.extra.values())
        check_compact_memory(n, src.sh_degree, extra_values=extra, views=views or DEFAULT_VIEWS,
                             resolution=resolution, neighbours=neighbours)
    settings = scoring_settings(render_settings)
    timings: dict[str, float] = {}
    how = {"score": score, "removal": removal, "neighbours": neighbours, "prune": prune}  # removal_groups'
    with reuse_freed_memory():
        if distill:
            say(0.0, "rendering the input for the fine-tuning")
            images, iterations = own_renders(src, cameras, resolution, settings), distill
        if images is not None:
            result = _compact_with_images(src, target, images, how, rounds, iterations, seed, views, resolution,
                                          settings, say, timings)
        else:
            cams = _views(src, cameras, views, resolution)
            t0 = time.perf_counter()
            frames: list = []
            say(0.0, f"scoring {n:,} Gaussians ({score})")
            scores = compaction_scores(src, score, cams, settings=settings, seed=seed, frames=frames,
                                       progress=lambda f, msg: say(0.6 * f, msg))
            timings["score"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            reference = _input_images(src, cams, settings, frames)
            del frames
            if target is None:
                target = _tolerance_count(src, scores, float(tolerance), cameras, cams, how, settings, say)
                timings["tolerance search"] = time.perf_counter() - t0
                t0 = time.perf_counter()
            say(0.65, f"removing {n - target:,} of {n:,} Gaussians ({removal})")
            groups = removal_groups(src, scores, target, **how, progress=lambda f, msg: say(0.65 + 0.25 * f, msg))
            out, rows = merge_groups(src, groups)
            groups, rows, out = _ordered(groups, rows, out)
            timings["remove"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            say(0.92, "comparing the pictures")
            value = _report_psnr(reference, out, cams, settings)
            timings["report"] = time.perf_counter() - t0
            result = CompactResult(out, rows, groups, scores, value, timings, tolerance=tolerance)
    timings["total"] = time.perf_counter() - t_start
    say(1.0, result.summary())
    return result


def _training_rate(src: GaussianCloud, cameras, cams: Sequence[Camera]) -> list[Camera]:
    """`cams` rescaled to the sampling rate the cloud was trained at (`fidelity.training_rate_views`:
    from its anti-aliasing size, else from the capture's `cameras` at their full size)."""
    rate_of = src
    if cameras is not None and not {FILTER_KEY, DILATION_KEY} & set(src.extra):
        rate_of = with_dilation_3d(src, list(cameras))
    return training_rate_views(rate_of, cams)


def own_renders(cloud: GaussianCloud, cameras=None, resolution: int = DEFAULT_RESOLUTION,
                settings: RenderSettings | None = None, views: int = DISTILL_VIEWS):
    """The cloud's own renders over white as training images (`datasets.Views`): `views` of the
    capture's `cameras` (spread out) or views placed around the cloud (`resolution` px high), all
    rescaled to one height, the lowest of the training sampling rate's (`_training_rate`)."""
    from .datasets import Views  # noqa: PLC0415

    src = cloud.numpy()
    cams = (scoring_views(cameras, views, 1 << 30, src) if cameras is not None
            else default_views(src, views, resolution))
    # one height for all: the lowest view's (the median lost 0.1-0.25 dB on the validation scenes)
    height = int(min(c.height for c in _training_rate(src, cameras, cams)))
    cams = [c.scaled(height) for c in cams]
    return Views(cams, np.stack([img.numpy() for img in _input_images(src, cams, settings or RenderSettings())]))


def _tolerance_count(src, scores, tolerance, cameras, cams, how: dict, settings, say) -> int:
    """The fewest Gaussians (to within 1% of the input's count) whose compaction keeps the
    picture at the training sampling rate at or above `tolerance` dB against the input's: a
    bisection on the count (the scoring views rescaled by `_training_rate`)."""
    check = _training_rate(src, cameras, cams)
    reference = _input_images(src, check, settings)
    n = len(src)

    def good(target: int) -> float:
        groups = removal_groups(src, scores, target, **how)
        return _report_psnr(reference, merge_groups(src, groups)[0], check, settings)

    lo, hi = 0, n  # good(hi) holds (the input itself); find the smallest count that holds
    step = 0
    while hi - lo > max(1, n // 100):
        mid = int(round(math.sqrt(max(lo, 1) * hi))) if lo == 0 or hi / max(lo, 1) > 4 else (lo + hi) // 2
        mid = min(max(mid, lo + 1), hi - 1)
        step += 1
        value = good(mid)
        say(0.1 + 0.5 * min(step / 12, 1.0), f"tolerance: {mid:,} Gaussians give {value:.2f} dB")
        if value >= tolerance:
            hi = mid
        else:
            lo = mid
    return hi


def _compact_with_images(src, target, images, how: dict, rounds, iterations, seed, views, resolution, settings, say,
                         timings) -> CompactResult:
    """PUP 3D-GS's rounds: remove part of the way (the fraction kept per round the same), fine-tune."""
    from .train import TrainConfig, fine_tune  # noqa: PLC0415 - training loads only with images

    n = len(src)
    mode = resolve_antialias(settings.antialias, src)
    config = TrainConfig(antialias="mip" if mode == "mip" else "classic", seed=seed)
    cur, groups = src, np.arange(n)
    first_scores = None
    records = []
    cams = scoring_views(images.cameras, views, resolution, src)
    reference = _input_images(src, cams, settings)
    for r in range(rounds):
        count = max(target, int(round(n * (target / n) ** ((r + 1) / rounds))))
        base = 0.9 * r / rounds
        t0 = time.perf_counter()
        say(base, f"round {r + 1}/{rounds}: scoring {len(cur):,} Gaussians ({how['score']})")
        scores = compaction_scores(cur, how["score"], cams, settings=settings, seed=seed + r)
        if first_scores is None:
            first_scores = scores
        step = removal_groups(cur, scores, count, **how)
        cur, _ = merge_groups(cur, step)
        groups = np.where(groups >= 0, step[np.maximum(groups, 0)], -1)
        timings["remove"] = timings.get("remove", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        before = _training_psnr(cur, images, config)
        cur = fine_tune(cur, images, iterations, config=config, seed=seed + r,
                        progress=lambda f, msg, b=base, k=r + 1: say(b + 0.9 / rounds * (0.2 + 0.8 * f),
                                                                     f"round {k}/{rounds}: {msg}"))
        seconds = time.perf_counter() - t0
        timings["fine-tune"] = timings.get("fine-tune", 0.0) + seconds
        records.append({"count": len(cur), "seconds": seconds, "psnr_before": before,
                        "psnr_after": _training_psnr(cur, images, config)})
    idx = np.flatnonzero(groups >= 0)
    rows = _representatives(groups, idx, _moments(src.select(idx), np.zeros(len(idx))).mass)
    groups, rows, cur = _ordered(groups, rows, cur)
    t0 = time.perf_counter()
    value = _report_psnr(reference, cur, cams, settings)
    timings["report"] = time.perf_counter() - t0
    return CompactResult(cur, rows, groups, first_scores, value, timings, records)


def _training_psnr(cloud: GaussianCloud, images, config) -> float:
    """Mean PSNR against (up to 8 of) the training images, over the trainer's background."""
    from .train import evaluate_psnr  # noqa: PLC0415

    return evaluate_psnr(cloud, images, config.background, cloud.sh_degree, 8,
                         RenderSettings(antialias=config.antialias if config.antialias == "mip" else "matched"))

