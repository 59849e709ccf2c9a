"""Redraw a view after some of its Gaussians changed, without projecting and binning the rest again.

A `Frame` keeps what rendering a view made: the packed per-Gaussian table, the depth-sorted tile
lists and, once composited, the pixels. `redraw` gives the frame of a changed cloud: only the
Gaussians that changed or are new are projected and binned, their tile pairs are merged into the
kept lists in depth order, and the view is composited again. Its image is the one `render` draws
of the changed cloud (up to the order of Gaussians at exactly the same depth in one tile). What
this is for: the fidelity check of a refine compares the input with a refined cloud that differs
in a few rows in ten, from views whose input frames the Hessian's sweep made already.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..camera import Camera
from ..cloud import GaussianCloud
from . import RenderSettings, prepare_view
from .rasterize import composite, tiles_to_image
from .tiles import Binning, _sort_key

__all__ = ["Frame", "make_frame", "redraw"]

#: Column of the packed table that holds the camera depth (`rasterize.pack`).
_DEPTH = 9


@dataclass
class Frame:
    """One view of a cloud, ready to composite or to redraw.

    table (R+1, 11): packed rows (`rasterize.pack`), the last the transparent dummy; binning: the
    tile lists of table rows; rows (R,) int64: the cloud row each table row draws (-1: none any
    more); pixels (H, W, 5): composited [r, g, b, depth, alpha] (None until `image` is called)."""

    camera: Camera
    settings: RenderSettings
    table: torch.Tensor
    binning: Binning
    rows: torch.Tensor
    pixels: torch.Tensor | None = None

    def image(self, background=(0.0, 0.0, 0.0)) -> torch.Tensor:
        """(H, W, 3) the view over `background`, as `render(...).image`."""
        if self.pixels is None:
            acc = composite(self.table, self.binning, block=self.settings.block, budget=self.settings.budget,
                            kernels=self.settings.kernels)
            self.pixels = tiles_to_image(acc, self.binning, self.camera.height, self.camera.width)
        bg = torch.as_tensor(background, dtype=self.pixels.dtype, device=self.pixels.device).reshape(3)
        return self.pixels[..., :3] + (1.0 - self.pixels[..., 4:5]) * bg


def make_frame(cloud: GaussianCloud, camera: Camera, settings: RenderSettings | None = None, *,
               device=None) -> Frame:
    """The frame of `cloud` seen through `camera` (no gradients; `device` as for `render`)."""
    s = settings or RenderSettings()
    with torch.no_grad():
        _, binning, table = prepare_view(cloud, camera, s, device=device)
    return Frame(camera, s, table, binning, torch.arange(len(cloud), device=table.device))


def _pair_tiles(binning: Binning) -> torch.Tensor:
    """(M,) the tile of each pair."""
    tiles = torch.arange(binning.tiles_x * binning.tiles_y, device=binning.counts.device)
    return torch.repeat_interleave(tiles, binning.counts, output_size=binning.num_pairs)


def redraw(frame: Frame, cloud: GaussianCloud, rows) -> Frame:
    """The frame of `cloud` through the same camera and settings, where `cloud` is the frame's cloud
    with the Gaussians of `rows` (rows of `cloud`) changed or added: every other row of `cloud`
    must be as the frame drew it, at the same index."""
    s, cam, dev = frame.settings, frame.camera, frame.table.device
    rows = torch.unique(torch.as_tensor(rows).reshape(-1).to("cpu", torch.int64))
    if len(rows) and (int(rows[0]) < 0 or int(rows[-1]) >= len(cloud)):
        raise ValueError(f"redraw: rows must be rows of the cloud (0..{len(cloud) - 1})")
    if len(rows) == len(cloud):  # every row changed: nothing of the frame to keep
        return make_frame(cloud, cam, s, device=dev)
    with torch.no_grad():
        # table rows that drew the changed Gaussians are dropped from the tile lists
        where = torch.full((max(len(cloud), int(frame.rows.max()) + 1 if len(frame.rows) else 0),), -1,
                           dtype=torch.int64, device=dev)
        drawn = frame.rows >= 0
        where[frame.rows[drawn]] = drawn.nonzero().squeeze(1)
        gone = where[rows.to(dev)]
        gone = gone[gone >= 0]
        drop = torch.zeros(len(frame.table), dtype=torch.bool, device=dev)
        drop[gone] = True
        _, new, fresh = prepare_view(cloud.select(rows.numpy()), cam, s, device=dev)
        first = len(frame.table) - 1  # the new rows go between the kept ones and the dummy
        table = torch.cat([frame.table[:-1], fresh[:-1].to(frame.table.dtype), frame.table[-1:]])
        table_rows = torch.cat([frame.rows, rows.to(dev)])
        table_rows[gone] = -1
        old = frame.binning
        keep = ~drop.index_select(0, old.gaussian_ids)
        ids = torch.cat([old.gaussian_ids[keep], new.gaussian_ids + first])
        tiles = torch.cat([_pair_tiles(old)[keep], _pair_tiles(new)])
        # by tile, then depth; the kept pair first where depths are equal
        order = torch.sort(_sort_key(table[:, _DEPTH].index_select(0, ids)), stable=True).indices
        order = order.index_select(0, torch.sort(tiles.index_select(0, order), stable=True).indices)
        counts = torch.bincount(tiles, minlength=old.tiles_x * old.tiles_y)
        offsets = torch.zeros(len(counts) + 1, dtype=torch.int64, device=dev)
        offsets[1:] = torch.cumsum(counts, 0)
        binning = Binning(old.tile_size, old.tiles_x, old.tiles_y, ids.index_select(0, order), offsets, counts)
    return Frame(cam, s, table, binning, table_rows)
