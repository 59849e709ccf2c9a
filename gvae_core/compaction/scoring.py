"""Per-Gaussian scores of how much a cloud's picture depends on each Gaussian, from a few views:
the default, the exact Gauss-Newton block of position and log-scale (`gvae_core.hessian`), scored
as log det(I + H/lambda), the sensitivity of PUP 3D-GS; the baselines it is compared with:
LightGaussian's global significance (pixels hit x opacity x volume^0.1), opacity, random. And
which Gaussians a set of views sees at all (`pixel_hits`: LightGaussian's hit counts, one sweep
over each view's tile lists as the renderer composites them; `pixel_hits_reference`, the slow
per-pixel loop the tests hold it to). The sweep is a compiled kernel (`compiled.table_hits`) where
the renderer's compiled path draws (float32 on the CPU, Numba there), else torch code (`table_hits`,
its reference).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from ..conventions import LOG_SCALE_RANGE
from ..hessian import hessian_scores
from ..rendering import RenderSettings, prepare_view
from ..rendering.compiled import use_compiled
from ..rendering.frames import Frame
from ..rendering.rasterize import (T_MIN, alpha_and_transmittance, compositing_weights, live_blocks, pair_table,
                                   pixel_monomials, tile_centres, tile_groups)
from . import compiled

#: Per-Gaussian scores `compact` can rank by: the default, then the baselines.
SCORES = ("hessian", "lightgaussian", "opacity", "random")
#: A Gaussian whose score is at most this changes no pixel of the scoring views.
UNSEEN = 1e-6
#: LightGaussian's volume exponent (its v_pow) and the quantile its volumes are taken relative to.
LIGHTGAUSSIAN_POWER = 0.1
LIGHTGAUSSIAN_QUANTILE = 0.1


def pixel_hits(cloud: GaussianCloud, cameras: Sequence[Camera], settings: RenderSettings | None = None) -> np.ndarray:
    """(N,) int64: the number of pixels, over `cameras`, that each Gaussian is composited into
    (alpha >= 1/255, before the pixel stops): LightGaussian's hit count. One sweep over each
    view's tile lists, as the renderer composites them."""
    settings = settings or RenderSettings()
    hits = torch.zeros(len(cloud) + 1, dtype=torch.int64)
    with torch.no_grad():
        for cam in cameras:
            _, binning, table = prepare_view(cloud, cam, settings)
            hits += _hits(table, binning, settings, cam)
    return hits[:-1].numpy()


def frame_hits(frame: Frame, n: int, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) int64: `pixel_hits` of the cloud rows `rows` (of a cloud of `n`) in a view whose
    frame was made already (`rendering.frames.Frame`: the Hessian's), sweeping only the tiles
    that draw one of them."""
    rows = np.asarray(rows, np.int64)
    if len(rows) == 0 or frame.binning.num_pairs == 0:
        return np.zeros(len(rows), np.int64)
    if _compiled(frame.table, frame.settings):
        drawn = frame.rows.numpy()
        drawn = np.where(drawn >= 0, drawn, n)
        wanted = np.zeros(n + 1, bool)
        wanted[rows] = True
        b = frame.binning
        hits = compiled.table_hits(frame.table.numpy(), b.gaussian_ids.numpy(), b.offsets.numpy(), b.tiles_x,
                                   b.tile_size, frame.camera.width, frame.camera.height,
                                   wanted=np.append(wanted[drawn], False))
        by_row = np.zeros(n + 1, np.int64)
        by_row[drawn] = hits[:-1]
        return by_row[rows]
    wanted = torch.zeros(n + 1, dtype=torch.bool)
    wanted[torch.from_numpy(rows)] = True
    drawn = frame.rows.to("cpu").clamp(min=-1)
    of_table = torch.cat([wanted[drawn.where(drawn >= 0, torch.full_like(drawn, n))], torch.zeros(1, dtype=torch.bool)])
    b = frame.binning
    tiles = torch.repeat_interleave(torch.arange(b.tiles_x * b.tiles_y), b.counts.cpu(), output_size=b.num_pairs)
    keep = torch.zeros(b.tiles_x * b.tiles_y, dtype=torch.bool)
    keep[tiles[of_table[b.gaussian_ids.cpu()]]] = True
    with torch.no_grad():
        hits = table_hits(frame.table, replace(b, counts=torch.where(keep, b.counts, 0)), frame.settings, frame.camera)
    by_row = torch.zeros(n + 1, dtype=torch.int64)
    by_row[drawn.where(drawn >= 0, torch.full_like(drawn, n))] = hits[:-1]
    return by_row[torch.from_numpy(rows)].numpy()


def _compiled(table: torch.Tensor, settings: RenderSettings) -> bool:
    """Whether the compiled sweep counts the hits of `table` under `settings` (the renderer's rule:
    its compiled path, float32 on the CPU, Numba there)."""
    return compiled.available() and use_compiled(settings.kernels, table.device, table.dtype)


def _hits(table: torch.Tensor, binning, settings: RenderSettings, cam: Camera) -> torch.Tensor:
    """`table_hits` by the compiled sweep where it runs."""
    if not _compiled(table, settings) or binning.num_pairs == 0:
        return table_hits(table, binning, settings, cam)
    return torch.from_numpy(compiled.table_hits(table.numpy(), binning.gaussian_ids.numpy(), binning.offsets.numpy(),
                                                binning.tiles_x, binning.tile_size, cam.width, cam.height))


def table_hits(table: torch.Tensor, binning, settings: RenderSettings, cam: Camera) -> torch.Tensor:
    """(R+1,) int64 hits of each row of a packed table (the last, the dummy's, 0), over the tiles
    `binning` lists (torch code: the reference of `compiled.table_hits`, and what runs off the
    compiled path)."""
    hits = torch.zeros(table.shape[0], dtype=torch.int64)
    if binning.num_pairs == 0:
        return hits
    pairs = pair_table(table, binning)
    ids_of_pairs = torch.cat([binning.gaussian_ids, binning.gaussian_ids.new_full((1,), table.shape[0] - 1)])
    ts = binning.tile_size
    p = ts * ts
    local = torch.arange(p)
    mono = pixel_monomials(ts, pairs.dtype, pairs.device)
    for tiles, kmax in tile_groups(binning, settings.block, settings.budget):
        b = tiles.shape[0]
        cx, cy = tile_centres(tiles, binning, pairs.dtype)
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
            _, tr, _, _ = alpha_and_transmittance(gd, cx[active], cy[active], mono, t0)
            w, kept = compositing_weights(tr)
            if k0 + settings.block < kmax:
                trans[active] = torch.where(was_done, t_prev, torch.minimum(t0, kept.amin(0)))
                done[active] = was_done | (tr[-1] < T_MIN)
            count_k = ((w > 0) & inside[active]).sum(-1).reshape(-1)
            hits.index_add_(0, ids_of_pairs.index_select(0, ids.reshape(-1)), count_k)
    hits[-1] = 0
    return hits


def pixel_hits_reference(cloud: GaussianCloud, cameras: Sequence[Camera], antialias: str = "auto") -> np.ndarray:
    """Slow definition of `pixel_hits`: every pixel, every Gaussian in depth order, with the
    renderer's alpha, skip and stop rules (the float64 reference projection)."""
    from ..rendering.reference import project_reference  # noqa: PLC0415 - tests only

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


def merge_weights(scores: np.ndarray, score: str) -> np.ndarray:
    """How much the picture depends on each Gaussian, >= 0, 0 for one no view sees: the score
    itself (the Hessian's log det(I + H/lambda), not its exponent, which merged worse); ones for
    "random" (a merge that no score guides)."""
    if score == "random":
        return np.ones_like(scores)
    return np.maximum(scores, 0.0)
