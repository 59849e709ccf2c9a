"""Tile binning with pure tensor ops: every visible Gaussian is paired with every tile that its
opacity-aware footprint ellipse reaches, and the pairs are ordered by (tile, depth).

Pairs are generated row by row: for each Gaussian and each tile row its footprint box spans,
the x-range of the ellipse inside that row's band of pixel centres is exact (the ellipse's
leftmost and rightmost points over a horizontal band are found in closed form), so no pair is
made for a tile the ellipse misses, and no per-pair test is needed afterwards. Gaussians are
taken in depth order, so one stable sort by tile id orders the pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Binning:
    """Depth-sorted per-tile Gaussian lists in CSR form.

    tile_size; tiles_x, tiles_y; gaussian_ids (M,) int64, the pairs sorted by tile then depth;
    offsets (T+1,) int64 into gaussian_ids per tile (tile id = ty * tiles_x + tx); counts (T,).
    """

    tile_size: int
    tiles_x: int
    tiles_y: int
    gaussian_ids: torch.Tensor
    offsets: torch.Tensor
    counts: torch.Tensor
    #: Pixel-Gaussian alpha evaluations of the last forward pass over this binning.
    evaluations: int = 0

    @property
    def num_pairs(self) -> int:
        return int(self.gaussian_ids.shape[0])


def _expand(counts: torch.Tensor):
    """For counts (R,): owner (M,) row index of each of the M = Σ counts items, and its rank."""
    total = int(counts.sum())
    owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts,
                                    output_size=total)
    start = torch.cumsum(counts, 0) - counts
    return owner, torch.arange(total, device=counts.device) - start.index_select(0, owner)


def _sort_key(x: torch.Tensor) -> torch.Tensor:
    """Integers in the order of the floats `x` (for non-NaN values; -0.0 just before 0.0): their
    bit patterns, with the magnitude bits of negative numbers flipped. torch sorts integers by
    radix, ten times faster than floats at a million values."""
    if x.dtype not in (torch.float32, torch.float64):
        return x
    bits = x.contiguous().view(torch.int32 if x.dtype == torch.float32 else torch.int64)
    magnitude = (1 << (8 * x.element_size() - 1)) - 1
    return bits ^ ((bits >> (8 * x.element_size() - 1)) & magnitude)


def bin_gaussians(means2d: torch.Tensor, footprint: torch.Tensor, depths: torch.Tensor,
                  visible: torch.Tensor, width: int, height: int, tile_size: int,
                  exact: bool = True, chunk: int = 1 << 17) -> Binning:
    """Pair visible Gaussians with the tiles whose pixel centres their footprint reaches.

    footprint (N,4) = (k, Σxx, Σxy, Σyy): the ellipse dᵀ Σ⁻¹ d <= k² around means2d. With
    `exact` False, the ellipse's bounding box is used instead (more pairs, same image). `chunk`:
    Gaussians paired at once (small temporaries stay in the cache; the result is the same)."""
    dev = means2d.device
    ts = tile_size
    tiles_x = (width + ts - 1) // ts
    tiles_y = (height + ts - 1) // ts
    ntiles = tiles_x * tiles_y
    with torch.no_grad():
        idx = visible.nonzero().squeeze(1)
        idx = idx.index_select(0, torch.sort(_sort_key(depths.detach().index_select(0, idx)), stable=True).indices)
        # pairs of each chunk of Gaussians, front to back; a stable sort by tile keeps that order
        parts = [_pairs(means2d, footprint, idx[i:i + chunk], width, height, ts, tiles_x, exact)
                 for i in range(0, max(len(idx), 1), chunk)]
        tile = torch.cat([t for t, _ in parts])
        gids = torch.cat([g for _, g in parts]).index_select(0, torch.sort(tile, stable=True).indices)
        counts = torch.bincount(tile.long(), minlength=ntiles) if tile.numel() else torch.zeros(
            ntiles, dtype=torch.int64, device=dev)
        offsets = torch.zeros(ntiles + 1, dtype=torch.int64, device=dev)
        offsets[1:] = torch.cumsum(counts, 0)
    return Binning(ts, tiles_x, tiles_y, gids, offsets, counts)


def _pairs(means2d, footprint, idx, width: int, height: int, ts: int, tiles_x: int, exact: bool):
    """(tile id (M,) int32, Gaussian id (M,) int64) of the pairs of Gaussians `idx`, in their order."""
    f64 = torch.float64
    m = means2d.detach().index_select(0, idx).to(f64)
    k, sxx, sxy, syy = footprint.index_select(0, idx).to(f64).unbind(-1)
    sqx, sqy = torch.sqrt(sxx), torch.sqrt(syy)
    ey = k * sqy
    # Rows of pixel centres (row i has its centre at i + 0.5) inside the footprint box.
    y0 = torch.ceil(m[:, 1] - ey - 0.5).clamp(0, height - 1)
    y1 = torch.floor(m[:, 1] + ey - 0.5).clamp(-1, height - 1)
    ok = y1 >= y0
    ty0 = torch.where(ok, y0, torch.zeros_like(y0)).long() // ts
    ty1 = torch.where(ok, y1.long() // ts, ty0 - 1)
    # One item per (Gaussian, tile row).
    g, r = _expand((ty1 - ty0 + 1).clamp(min=0))
    ty = ty0.index_select(0, g) + r
    per_row = torch.stack([m[:, 0], m[:, 1], k, sxx, sxy, syy, sqx, ey], 1).index_select(0, g)
    mx, my, kg, sxx_g, sxy_g, syy_g, sqx_g, eyg = per_row.unbind(1)
    band_lo = torch.maximum((ty * ts).to(f64) + (0.5 - my), -eyg)
    band_hi = torch.minimum(torch.clamp((ty * ts + ts - 1).to(f64), max=height - 1.0) + (0.5 - my), eyg)
    if exact:
        # For fixed dy the ellipse spans dx = (Σxy/Σyy) dy ± sqrt(det Σ/Σyy (k² - dy²/Σyy));
        # its right end is concave in dy with its maximum at dy = k Σxy / sqrt(Σxx) (the
        # rightmost point), the left end convex with its minimum at the opposite dy.
        slope = sxy_g / syy_g
        det_ratio = torch.clamp(sxx_g - sxy_g * slope, min=0.0)  # det Σ / Σyy
        dy_peak = kg * sxy_g / sqx_g

        def half_width(dy):
            return torch.sqrt(det_ratio * torch.clamp(kg * kg - dy * dy / syy_g, min=0.0))

        dyr = torch.minimum(torch.maximum(dy_peak, band_lo), band_hi)
        dyl = torch.minimum(torch.maximum(-dy_peak, band_lo), band_hi)
        # Small absolute slack so rounding never loses a pixel centre on the boundary.
        x_hi = mx + slope * dyr + half_width(dyr) + 1e-3
        x_lo = mx + slope * dyl - half_width(dyl) - 1e-3
    else:
        ex = kg * sqx_g
        x_hi, x_lo = mx + ex, mx - ex
    x0 = torch.ceil(x_lo - 0.5).clamp(0, width - 1)
    x1 = torch.floor(x_hi - 0.5).clamp(-1, width - 1)
    nonempty = (x1 >= x0) & (band_hi >= band_lo)
    tx0 = torch.where(nonempty, x0, torch.zeros_like(x0)).long() // ts
    tx1 = torch.where(nonempty, x1.long() // ts, tx0 - 1)
    # One item per (Gaussian, tile), in the order of the Gaussians.
    item, c = _expand(tx1 - tx0 + 1)
    tile = ((ty * tiles_x + tx0).index_select(0, item) + c).to(torch.int32)
    return tile, idx.index_select(0, g.index_select(0, item))
