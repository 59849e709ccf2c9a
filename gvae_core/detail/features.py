"""What the detail model sees of each Gaussian: its own state, its lineage and its neighbourhood,
in units that depend neither on the scene's size nor on the training resolution. numpy (and
scipy's k-d tree for the neighbours, imported only when they are asked for); no torch
arithmetic.

Per Gaussian, `SHARED` values and, per axis of its ellipsoid, `AXIS` values (the model predicts a
change per axis with one network shared by the three axes, so it cannot tell them apart but by
what they are). Sizes are in pixels of the training sampling rate (log size + log nu, nu from
the cloud's anti-aliasing size, `gvae_core.octaves.training_rate`); lineage changes are per
octave of training resolution between the stages (log2 of their height ratio); neighbours are the
`neighbours` nearest centres.

`detail_inputs` runs a compiled kernel (`detail.kernels`, Numba; rows in threads) where Numba
loads; `detail_inputs_reference`, the numpy float64 code, is what the tests hold it to and what
runs without Numba.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass

import numpy as np

from ..cloud import GaussianCloud
from ..conventions import dc_to_rgb
from ..lineage import APP_OPACITY, GEO_EXIST, GEO_LOG_SCALE, Lineage
from ..octaves import training_rate
from ..rendering.compiled import numba_missing
from .. import parallel
from ..parallel import in_threads

__all__ = ["SHARED", "AXIS", "NODE", "LINEAGE_COLUMNS", "CONTEXT_COLUMNS", "DetailInputs", "detail_inputs",
           "detail_inputs_reference", "lineage_nodes"]

SHARED = ("opacity", "opacity_change", "opacity_change_before", "existed_before", "existed_two_before",
          "size_mean", "size_max", "size_min", "has_history", "luminance",
          "neighbour_distance", "neighbour_contrast", "neighbour_scale_change", "neighbour_opacity_change",
          "neighbour_size", "neighbour_opacity")
AXIS = ("size", "scale_change", "scale_change_before", "size_vs_mean")
#: Per lineage node (the last three, oldest first), for the paper's lineage encoder (`DetailConfig.encoder`):
#: its log-scales relative to the last node's, its opacity, whether the Gaussian existed there, and the
#: octaves from it to the last node.
NODE = ("log_scale_0", "log_scale_1", "log_scale_2", "opacity", "exist", "octaves_to_last")
#: Columns that come from the lineage, and from the neighbours (zeroed to leave them out).
LINEAGE_COLUMNS = {"shared": ("opacity_change", "opacity_change_before", "existed_before", "existed_two_before",
                              "has_history", "neighbour_scale_change", "neighbour_opacity_change"),
                   "axis": ("scale_change", "scale_change_before")}
CONTEXT_COLUMNS = {"shared": tuple(c for c in SHARED if c.startswith("neighbour_")), "axis": ()}

# Clamps on use: a few wild Gaussians must not dominate.
_LOG_SCALE = (-20.0, 10.0)
_OPACITY = (-12.0, 12.0)
_CHANGE = 4.0


@dataclass
class DetailInputs:
    """shared (N, len(SHARED)), axis (N, 3, len(AXIS)) and nodes (N, 3, len(NODE)) float32, finite."""

    shared: np.ndarray
    axis: np.ndarray
    nodes: np.ndarray

    def __len__(self) -> int:
        return len(self.shared)

    def select(self, rows) -> DetailInputs:
        return DetailInputs(self.shared[rows], self.axis[rows], self.nodes[rows])


def lineage_nodes(cloud: GaussianCloud, lineage: Lineage | None):
    """Each Gaussian's last three lineage nodes, oldest first: log-scales (N,3,3), opacity logits
    (N,3), whether the Gaussian itself existed there (N,3), and the octaves between consecutive
    nodes (2,). Missing history (a one- or two-node lineage, or none) repeats the oldest node known
    (no change) with exist 0. The lineage's last stage must be the cloud's (refine's
    `_lineage_for` cuts it there); rows are matched by `gvae_id`, else by position in the stage."""
    c = cloud.numpy()
    n = len(c)
    scales = np.repeat(np.asarray(c.scales, np.float64)[:, None], 3, 1)
    opac = np.repeat(np.asarray(c.opacities, np.float64)[:, None], 3, 1)
    exist = np.zeros((n, 3))
    exist[:, 2] = 1.0
    octaves = np.ones(2)
    if lineage is None or lineage.n_stages < 2:
        return scales, opac, exist, octaves
    last = lineage.n_stages - 1
    seq = lineage.sequences(last)
    ids = c.extra.get("gvae_id")
    if ids is not None and len(ids) == n:
        rows = lineage.rows_of(last, ids)
        if (rows < 0).any():
            raise ValueError(f"detail: {int((rows < 0).sum())} Gaussian id(s) are not alive at the lineage's last "
                             f"stage {last}")
    elif len(seq) == n:
        rows = np.arange(n)
    else:
        raise ValueError(f"detail: the lineage's last stage has {len(seq)} Gaussians, the cloud {n} (and no gvae_id)")
    t = min(3, lineage.n_stages)
    g = seq.geometry[rows, -t:]
    a = seq.appearance[rows, -t:]
    scales[:, 3 - t:] = g[..., GEO_LOG_SCALE] + math.log(lineage.scale)  # back to world log-scales
    scales[:, 2] = c.scales  # the cloud's own values (the last node is the cloud)
    opac[:, 3 - t:] = a[..., APP_OPACITY]
    opac[:, 2] = c.opacities
    exist[:, 3 - t:] = g[..., GEO_EXIST]
    if t < 3:
        scales[:, 0], opac[:, 0] = scales[:, 1], opac[:, 1]
    res = np.asarray(lineage.resolutions[-t:], np.float64)
    for i in range(t - 1):
        ratio = res[i + 1] / res[i] if res[i] > 0 else 0.0
        octaves[3 - t + i] = math.log2(ratio) if ratio > 1.0 else 1.0
    return scales, opac, exist, octaves


def _rates(c: GaussianCloud) -> np.ndarray:
    """(N,) float64 each Gaussian's training rate; where it is not finite and positive, the median of
    those that are (1 when none is)."""
    nu = training_rate(c)
    if nu is None:
        raise ValueError("detail: the cloud needs its anti-aliasing size (the sampling rate it was trained at)")
    nu = np.where(np.isfinite(nu) & (nu > 0) & (nu < 1e29), nu, np.nan)
    return np.where(np.isnan(nu), np.nanmedian(nu) if np.isfinite(nu).any() else 1.0, nu)


def _neighbours(c: GaussianCloud, r: np.ndarray, k: int, workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(M, k) distances and indices of the k nearest other centres of rows `r` (scipy's k-d tree)."""
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import; only the context needs it

    pos = np.nan_to_num(np.asarray(c.means, np.float64))
    dist, idx = cKDTree(pos).query(pos[r], k + 1, workers=workers)
    return dist[:, 1:], idx[:, 1:]


def detail_inputs(cloud: GaussianCloud, lineage: Lineage | None = None, *, neighbours: int = 8,
                  rows=None) -> DetailInputs:
    """The model's inputs for the Gaussians `rows` (default: all) of `cloud` (numpy; needs its
    anti-aliasing size) with its `lineage` (None: Gaussians without history); the neighbours are
    found among all of them (`neighbours` 0: none, their columns are 0). By the compiled kernel
    where Numba loads, else `detail_inputs_reference` (the same values to float32 rounding)."""
    if numba_missing() is not None:
        return detail_inputs_reference(cloud, lineage, neighbours=neighbours, rows=rows)
    c = cloud.numpy()
    n = len(c)
    nu = _rates(c)
    if lineage is None or lineage.n_stages < 2:  # the cloud's own values at every node, as lineage_nodes
        s = np.ascontiguousarray(c.scales, np.float64)
        o = np.ascontiguousarray(c.opacities, np.float64).reshape(n)
        zero, one = np.zeros(n), np.ones(n)
        nodes_s, nodes_o, nodes_e, octaves = (s, s, s), (o, o, o), (zero, zero, one), np.ones(2)
    else:
        scales, opac, exist, octaves = lineage_nodes(c, lineage)
        nodes_s = tuple(np.ascontiguousarray(scales[:, t]) for t in range(3))
        nodes_o = tuple(np.ascontiguousarray(opac[:, t]) for t in range(3))
        nodes_e = tuple(np.ascontiguousarray(exist[:, t]) for t in range(3))
    r = np.arange(n, dtype=np.int64) if rows is None else np.asarray(rows, np.int64).reshape(-1)
    m = len(r)
    k = int(min(neighbours, n - 1))
    if k >= 1 and m:
        dist, idx = _neighbours(c, r, k, workers=parallel.count())
        dist, idx = np.ascontiguousarray(dist, np.float64), np.ascontiguousarray(idx, np.int64)
    else:
        dist, idx = np.zeros((m, 0)), np.zeros((m, 0), np.int64)
    has_history = float(lineage is not None and lineage.n_stages > 1)
    shared = np.empty((m, len(SHARED)), np.float32)
    axis = np.empty((m, 3, len(AXIS)), np.float32)
    nodes = np.empty((m, 3, len(NODE)), np.float32)
    sh_dc = np.ascontiguousarray(c.sh_dc, np.float32)
    kern = importlib.import_module(".kernels", __package__).detail_rows

    def part(a: int, b: int) -> None:
        kern(*nodes_s, *nodes_o, *nodes_e, nu, sh_dc, np.asarray(octaves, np.float64), has_history, r, idx, dist,
             a, b, shared, axis, nodes)

    in_threads(m, part)
    return DetailInputs(shared, axis, nodes)


def detail_inputs_reference(cloud: GaussianCloud, lineage: Lineage | None = None, *, neighbours: int = 8,
                            rows=None) -> DetailInputs:
    """`detail_inputs` in numpy, float64 until the end: the definition the compiled kernel is held to."""
    c = cloud.numpy()
    n = len(c)
    nu = _rates(c)
    scales, opac, exist, octaves = lineage_nodes(c, lineage)
    scales = np.clip(np.nan_to_num(scales), *_LOG_SCALE)
    opac = np.clip(np.nan_to_num(opac), *_OPACITY)
    px = scales[:, 2] + np.log(nu)[:, None]  # log size in training pixels, per axis
    ds1 = np.clip((scales[:, 2] - scales[:, 1]) / octaves[1], -_CHANGE, _CHANGE)
    ds0 = np.clip((scales[:, 1] - scales[:, 0]) / octaves[0], -_CHANGE, _CHANGE)
    do1 = np.clip((opac[:, 2] - opac[:, 1]) / octaves[1], -3 * _CHANGE, 3 * _CHANGE)
    do0 = np.clip((opac[:, 1] - opac[:, 0]) / octaves[0], -3 * _CHANGE, 3 * _CHANGE)
    rgb = np.clip(np.nan_to_num(dc_to_rgb(np.asarray(c.sh_dc, np.float64))), 0.0, 1.0)
    op = opac[:, 2]
    has_history = float(lineage is not None and lineage.n_stages > 1)

    r = np.arange(n) if rows is None else np.asarray(rows, np.int64).reshape(-1)
    m = len(r)
    k = int(min(neighbours, n - 1))
    if k >= 1 and m:
        dist, idx = _neighbours(c, r, k)
        size = np.exp(scales[r, 2].max(1))
        nb_distance = np.log(dist.mean(1) / size + 1e-6)
        nb_contrast = np.abs(rgb[idx] - rgb[r, None]).mean((1, 2))
        nb_scale_change = ds1[idx].mean((1, 2))
        nb_opacity_change = do1[idx].mean(1)
        nb_size = px[idx].mean((1, 2)) - px[r].mean(1)
        nb_opacity = op[idx].mean(1) - op[r]
    else:
        nb_distance = nb_contrast = nb_scale_change = nb_opacity_change = nb_size = nb_opacity = np.zeros(m)
    px, ds1, ds0, do1, do0, exist, rgb, op = px[r], ds1[r], ds0[r], do1[r], do0[r], exist[r], rgb[r], op[r]
    shared = np.stack([op / 4, do1 / 4, do0 / 4, exist[:, 1], exist[:, 0], px.mean(1) / 3, px.max(1) / 3,
                       px.min(1) / 3, np.full(m, has_history), rgb.mean(1),
                       nb_distance / 3, nb_contrast * 4, nb_scale_change, nb_opacity_change / 4, nb_size / 3,
                       nb_opacity / 4], 1)
    axis = np.stack([px / 3, ds1, ds0, px - px.mean(1, keepdims=True)], 2).reshape(m, 3, len(AXIS))
    to_last = np.array([octaves.sum(), octaves[1], 0.0])
    nodes = np.concatenate([np.clip(scales[r] - scales[r, 2:3], -_CHANGE, _CHANGE), (opac[r] / 4)[..., None],
                            exist[:, :, None], np.broadcast_to(to_last[None, :, None], (m, 3, 1))], 2)
    return DetailInputs(*(np.nan_to_num(a).astype(np.float32) for a in (shared, axis, nodes)))
