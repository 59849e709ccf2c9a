"""Compiled kernels of the detail model (Numba): its inputs (`detail_rows`:
`features.detail_inputs_reference`, the numpy float64 code it is tested against, row by row in one
pass with no temporaries) and its `features` network (`model_rows`: `model.DetailModel.forward`,
the torch code it is tested against, one Gaussian at a time in cache, the axis head's shared part
computed once for the three axes).

Imported only when used (`features.detail_inputs`), so that importing `gvae_core.detail` does not
load Numba; compiled once and cached on disk by the renderer's `kernel` decorator (nogil: the
caller runs ranges of rows in threads). The inputs' arithmetic is float64 as in the reference,
rounded to float32 once at the end; the network's is float32 as torch's.
"""

from __future__ import annotations

import math

import numpy as np

from ..conventions import SH_C0
from ..rendering.kernels import EXP_LO, exp_f32, inline, kernel

__all__ = ["detail_rows", "model_rows", "LOG_SCALE", "OPACITY", "CHANGE"]

#: The reference's clamps on use (`features._LOG_SCALE`, `_OPACITY`, `_CHANGE`; a test holds them equal).
LOG_SCALE = (-20.0, 10.0)
OPACITY = (-12.0, 12.0)
CHANGE = 4.0
_BIG = 1.7976931348623157e308  # what np.nan_to_num makes of an infinity (float64)


@inline
def _finite(x):
    """np.nan_to_num of one float64."""
    if math.isnan(x):
        return 0.0
    if math.isinf(x):
        return _BIG if x > 0 else -_BIG
    return x


@inline
def _clip(x, lo, hi):
    return min(max(x, lo), hi)


@inline
def _own(i, s0, s1, s2, o0, o1, o2, nu, sh_dc, oct0, oct1, out):
    """Gaussian i's own values into out (16,): px (3), ds1 (3), ds0 (3), do1, do0, rgb (3), op, and the
    largest of its (clamped) log-scales."""
    lnu = math.log(nu[i])
    out[15] = -np.inf
    for a in range(3):
        c2 = _clip(_finite(s2[i, a]), LOG_SCALE[0], LOG_SCALE[1])
        c1 = _clip(_finite(s1[i, a]), LOG_SCALE[0], LOG_SCALE[1])
        c0 = _clip(_finite(s0[i, a]), LOG_SCALE[0], LOG_SCALE[1])
        out[a] = c2 + lnu
        out[3 + a] = _clip((c2 - c1) / oct1, -CHANGE, CHANGE)
        out[6 + a] = _clip((c1 - c0) / oct0, -CHANGE, CHANGE)
        out[15] = max(out[15], c2)
        # dc_to_rgb, nan_to_num, clip to [0, 1] (the clamp at 0 of dc_to_rgb is the clip's)
        out[11 + a] = _clip(_finite(np.float64(sh_dc[i, a]) * SH_C0 + 0.5), 0.0, 1.0)
    p2 = _clip(_finite(o2[i]), OPACITY[0], OPACITY[1])
    p1 = _clip(_finite(o1[i]), OPACITY[0], OPACITY[1])
    p0 = _clip(_finite(o0[i]), OPACITY[0], OPACITY[1])
    out[9] = _clip((p2 - p1) / oct1, -3 * CHANGE, 3 * CHANGE)
    out[10] = _clip((p1 - p0) / oct0, -3 * CHANGE, 3 * CHANGE)
    out[14] = p2


@inline
def _f32(x):
    return np.float32(_finite(x))


@kernel
def detail_rows(s0, s1, s2, o0, o1, o2, e0, e1, e2, nu, sh_dc, octaves, has_history, rows, idx, dist, start, stop,
                shared, axis, nodes):
    """Rows start..stop of `rows`: shared (M, 16), axis (M, 3, 4) and nodes (M, 3, 6) float32, as
    `detail_inputs_reference` makes them. s0, s1, s2 (N, 3) float64: the log-scales of the lineage's
    last three nodes (oldest first, the last the cloud's own); o0, o1, o2 (N,) their opacity logits;
    e0, e1, e2 (N,) whether the Gaussian existed at each; nu (N,) float64 the training rates
    (finite, > 0); sh_dc (N, 3) float32; octaves (2,) between the nodes; idx, dist (M, K) int64 /
    float64 the K nearest neighbours of each row (K 0: none, their columns are 0)."""
    to_last = (octaves[0] + octaves[1], octaves[1], 0.0)
    k = idx.shape[1]
    me = np.empty(16)
    nb = np.empty(16)
    for j in range(start, stop):
        i = rows[j]
        _own(i, s0, s1, s2, o0, o1, o2, nu, sh_dc, octaves[0], octaves[1], me)
        px_mean = (me[0] + me[1] + me[2]) / 3.0
        nb_distance = nb_contrast = nb_scale = nb_opacity_change = nb_size = nb_opacity = 0.0
        if k >= 1:
            d = 0.0
            for q in range(k):
                _own(idx[j, q], s0, s1, s2, o0, o1, o2, nu, sh_dc, octaves[0], octaves[1], nb)
                d += dist[j, q]
                for a in range(3):
                    nb_contrast += abs(nb[11 + a] - me[11 + a])
                    nb_scale += nb[3 + a]
                    nb_size += nb[a]
                nb_opacity_change += nb[9]
                nb_opacity += nb[14]
            size = math.exp(me[15])
            nb_distance = math.log(d / k / size + 1e-6)
            nb_contrast /= 3 * k
            nb_scale /= 3 * k
            nb_opacity_change /= k
            nb_size = nb_size / (3 * k) - px_mean
            nb_opacity = nb_opacity / k - me[14]
        sh = shared[j]
        sh[0], sh[1], sh[2] = _f32(me[14] / 4), _f32(me[9] / 4), _f32(me[10] / 4)
        sh[3], sh[4] = _f32(e1[i]), _f32(e0[i])
        sh[5] = _f32(px_mean / 3)
        sh[6] = _f32(max(me[0], me[1], me[2]) / 3)
        sh[7] = _f32(min(me[0], me[1], me[2]) / 3)
        sh[8] = _f32(has_history)
        sh[9] = _f32((me[11] + me[12] + me[13]) / 3.0)
        sh[10], sh[11], sh[12] = _f32(nb_distance / 3), _f32(nb_contrast * 4), _f32(nb_scale)
        sh[13], sh[14], sh[15] = _f32(nb_opacity_change / 4), _f32(nb_size / 3), _f32(nb_opacity / 4)
        for a in range(3):
            ax = axis[j, a]
            ax[0], ax[1], ax[2], ax[3] = _f32(me[a] / 3), _f32(me[3 + a]), _f32(me[6 + a]), _f32(me[a] - px_mean)
        for t in range(3):
            sn = s0 if t == 0 else s1 if t == 1 else s2
            nd = nodes[j, t]
            for a in range(3):
                own = _clip(_finite(sn[i, a]), LOG_SCALE[0], LOG_SCALE[1])
                last = _clip(_finite(s2[i, a]), LOG_SCALE[0], LOG_SCALE[1])
                nd[a] = _f32(_clip(own - last, -CHANGE, CHANGE))
            on = o0 if t == 0 else o1 if t == 1 else o2
            nd[3] = _f32(_clip(_finite(on[i]), OPACITY[0], OPACITY[1]) / 4)
            nd[4] = _f32(e0[i] if t == 0 else e1[i] if t == 1 else e2[i])
            nd[5] = _f32(to_last[t])


# ----------------------------------------------------------------------------- the model

f32 = np.float32


_ONE, _HALF = f32(1.0), f32(0.5)
# erf as torch's vectorised CPU GELU computes it (Abramowitz & Stegun 7.1.26, |error| < 1.5e-7)
_P = f32(0.3275911)
_A1, _A2, _A3, _A4, _A5 = f32(0.254829592), f32(-0.284496736), f32(1.421413741), f32(-1.453152027), f32(1.061405429)
_SQRT1_2 = f32(0.7071067811865476)


@inline
def _exp_neg(x):
    """exp of a float32 <= 0 (below -87: exp(-87)) to about 1 ulp (`rendering.kernels.exp_f32`)."""
    return exp_f32(max(x, EXP_LO))


@inline
def _gelu(x):
    """x Φ(x) = x (1 + erf(x / sqrt 2)) / 2, with the erf torch's CPU GELU uses; branch-free."""
    u = x * _SQRT1_2
    a = abs(u)
    t = _ONE / (_P * a + _ONE)
    r = (((_A5 * t + _A4) * t + _A3) * t + _A2) * t + _A1
    e = _ONE - r * t * _exp_neg(-(u * u))
    return _HALF * x * (_ONE + (e if u >= 0 else -e))


@inline
def _dense(x, wt, b, out):
    """out = b + x @ wt: wt (len(x), len(out)) the layer's weight transposed (the loop over the
    outputs is contiguous, so it vectorises)."""
    h = out.shape[0]
    for o in range(h):
        out[o] = b[o]
    for i in range(x.shape[0]):
        xi = x[i]
        for o in range(h):
            out[o] += wt[i, o] * xi


@inline
def _gelu_all(x):
    for o in range(x.shape[0]):
        x[o] = _gelu(x[o])


@kernel
def model_rows(shared, axis, shared_mask, axis_mask, s1, s1b, s2, s2b, a1h, a1x, a1b, a2, a2b, r1, r1b, r2,
               r2b, max_scale, max_opacity, max_dc, start, stop, scales, rest):
    """Rows start..stop of the detail model's `features` network (`model.DetailModel.forward`, float32),
    one Gaussian at a time: shared (M, S) and axis (M, 3, A) inputs, the masks, each layer's weight
    transposed (in, out) and bias: the shared network s1, s2; the axis head's first layer split into
    the rows that read the shared part (a1h) and the axis's values (a1x), its last a2 (h,), a2b (1,);
    the other head r1 (reading h, then the axes' mean and largest), r2. Writes the bounded changes:
    scales (M, 3) and rest (M, R): the opacity's [, the DC colour's]."""
    h = s1b.shape[0]
    s, a_n, n_rest = shared.shape[1], axis.shape[2], r2b.shape[0]
    x = np.empty(s, np.float32)
    h1 = np.empty(h, np.float32)
    hid = np.empty(h, np.float32)
    hh = np.empty(h, np.float32)
    pre = np.empty(h, np.float32)
    ax = np.empty((3, a_n), np.float32)
    cat = np.empty(h + 2 * a_n, np.float32)
    out = np.empty(n_rest, np.float32)
    for j in range(start, stop):
        for i in range(s):
            x[i] = shared[j, i] * shared_mask[i]
        _dense(x, s1, s1b, h1)
        _gelu_all(h1)
        _dense(h1, s2, s2b, hid)
        _gelu_all(hid)
        _dense(hid, a1h, a1b, hh)  # the shared part of the axis head's first layer, once for the three axes
        for a in range(3):
            for i in range(a_n):
                ax[a, i] = axis[j, a, i] * axis_mask[i]
            for o in range(h):
                pre[o] = hh[o]
            for i in range(a_n):
                xi = ax[a, i]
                for o in range(h):
                    pre[o] += a1x[i, o] * xi
            _gelu_all(pre)
            ds = a2b[0]
            for o in range(h):
                ds += pre[o] * a2[o]
            scales[j, a] = max_scale * np.tanh(ds / max_scale)
        for o in range(h):
            cat[o] = hid[o]
        for i in range(a_n):
            cat[h + i] = (ax[0, i] + ax[1, i] + ax[2, i]) / np.float32(3.0)
            cat[h + a_n + i] = max(ax[0, i], ax[1, i], ax[2, i])
        _dense(cat, r1, r1b, pre)
        _gelu_all(pre)
        _dense(pre, r2, r2b, out)
        rest[j, 0] = max_opacity * np.tanh(out[0] / max_opacity)
        for c in range(1, n_rest):
            rest[j, c] = max_dc * np.tanh(out[c] / max_dc)
