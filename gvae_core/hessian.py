"""Hessian-guided sampling (DESIGN.md step 4): a per-Gaussian second-order importance score.

The score is built from the Gauss-Newton (Fisher) block H_i = J_i^T J_i of the rendered images
with respect to Gaussian i's position (in the scene-normalised frame) and log-scale (6x6),
summed over views and over every pixel and colour channel. It needs no ground truth.

The block is computed exactly, not estimated: one extra sweep over the renderer's tile lists
per view (`_gauss_newton_sweep`) gives, for every pixel p, channel c and Gaussian k it reaches,
the derivative of I_pc with respect to k's exponent (alpha_k = o_k exp(E_k)) and colour, which
the renderer's backward pass would compute for a one-hot output gradient. The squares of these
derivatives are summed over pixels as moments of the pixel offsets (one GEMM per block, then
moved to each Gaussian's centre), so no per-pixel Jacobian is ever stored; the derivatives of the
projection, written out for each anti-aliasing mode (`_gaussian_blocks`), carry them to position
and log-scale. `hessian_blocks_reference` (one backward pass per pixel and channel through
`render`) is the slow definition the tests hold it to: if the projection of `gvae_core.rendering`
changes, `_gaussian_blocks` must follow, and those tests say so. Gaussians are processed in
Morton order (neighbours in space are neighbours in memory) and the result is put back.

Score: log det(I + H_i / lambda) with a ridge lambda relative to the mean block trace (finite,
>= 0, 0 for Gaussians no view sees), or the trace of H_i.

Views: the capture's cameras when given (`scoring_views` picks a few, spread out, at a modest
resolution), else `default_views`: around the cloud for an object, from inside it for a scene
that surrounds its centre (`surround_radius`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from . import quaternions
from .antialias import DILATION_KEY, FILTER_KEY, resolve_antialias
from .camera import Camera
from .capture import DEFAULT_RESOLUTION, DEFAULT_VIEWS, default_views, scoring_views
from .cloud import GaussianCloud
from .conventions import LOG_SCALE_RANGE, SH_C1 as SH_C1_, SH_C2 as SH_C2_, SH_C3 as SH_C3_
from .parallel import in_threads
from .rendering import RenderSettings, compiled, render
from .rendering import projection as pj
from .rendering.projection import Projected, project
from .rendering.rasterize import (ALPHA_MAX, T_MIN, alpha_and_transmittance, composite, compositing_weights,
                                  live_blocks, pack, pair_table, tile_centres, tiles_to_image)
from .rendering.frames import Frame
from .rendering.tiles import bin_gaussians

BLOCK = 6  # position (3) + log-scale (3)
#: Tile edge of the Hessian sweeps: small tiles waste fewer evaluations on sub-pixel Gaussians.
TILE_SIZE = 4
#: Upper-triangle index pairs of a 6x6 block, in the order of the packed (21, N) form.
_TRIU = torch.triu_indices(BLOCK, BLOCK)
#: Exponents (i, j) of the pixel-offset monomials u^i v^j up to degree 4; the first 6 are degree <= 2.
_POWERS = [(d - j, j) for d in range(5) for j in range(d + 1)]
_P2 = 6
_INDEX = {p: k for k, p in enumerate(_POWERS)}
#: Columns of the per-pair moments: 15 of s = sum_c e_c^2, 6 per channel of t_c = e_c w, 1 of w^2.
_NMOM = len(_POWERS) + 3 * _P2 + 1


# ------------------------------------------------------------------------- exact blocks

def _fields(cloud: GaussianCloud, dtype) -> dict[str, torch.Tensor]:
    """The cloud's parameters as torch tensors in the working dtype (positions as stored: the
    projection takes them relative to the camera in float64 before rounding)."""
    c = cloud.detach() if cloud.is_torch else cloud.to_torch()
    return {name: getattr(c, name).to(dtype) if name != "means" or dtype == torch.float64 else getattr(c, name)
            for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")}


def _monomials(ts: int, dtype) -> torch.Tensor:
    """(P, 15): u^i v^j of each pixel centre of a tile relative to the tile centre, by `_POWERS`."""
    r = torch.arange(ts, dtype=torch.float64) - (ts - 1) / 2.0
    u, v = r.repeat(ts), r.repeat_interleave(ts)
    return torch.stack([u ** i * v ** j for i, j in _POWERS], 1).to(dtype)


def _tile_groups(binning, block: int, budget: int) -> list[tuple[torch.Tensor, int]]:
    """Non-empty tiles in Z-order of their position, in groups of about `budget` pixel-pair
    evaluations a block (like `rendering.rasterize.tile_groups`, whose longest-first order scatters
    neighbouring tiles): consecutive pairs then belong to nearby Gaussians."""
    ty, tx = np.divmod(np.arange(binning.tiles_x * binning.tiles_y), binning.tiles_x)
    code = np.zeros(len(tx), np.int64)
    for bit in range(16):
        code |= ((tx >> bit) & 1) << (2 * bit) | ((ty >> bit) & 1) << (2 * bit + 1)
    counts = binning.counts.numpy()
    order = np.argsort(code, kind="stable")
    order = order[counts[order] > 0]
    p = binning.tile_size ** 2
    groups, i = [], 0
    while i < len(order):
        b = max(1, budget // (p * block))
        chunk = order[i:i + b]
        groups.append((torch.from_numpy(chunk), int(counts[chunk].max())))
        i += b
    return groups


def _gauss_newton_sweep(pairs: torch.Tensor, binning, acc: torch.Tensor, block: int, budget: int,
                        mom: torch.Tensor, width: int, height: int) -> None:
    """Add, per Gaussian, the moments of its pixel derivatives about its centre into `mom` (N, 34)
    (float64).

    Recomputes every block of the compositing as the renderer does (same alpha, cap, skip and stop
    rules) and, per pixel, the derivative e_c of channel c with respect to the Gaussian's exponent
    E (alpha = o exp(E)) and its weight w = alpha T (the derivative with respect to its colour c):
    e_c = alpha (colour_c T - behind_c / (1 - alpha)), behind_c the colour drawn after it. Moments
    (one GEMM a block, about the tile centre, then moved to the Gaussian's centre): s = sum_c e_c^2
    by the monomials u^i v^j up to degree 4, t_c = e_c w up to degree 2, and w^2."""
    dt = pairs.dtype
    ts = binning.tile_size
    p = ts * ts
    mono_t = _monomials(ts, dt).T.contiguous()  # (15, P)
    mono2t = mono_t[:_P2].contiguous()
    dummy = pairs.shape[0] - 1
    gids = torch.cat([binning.gaussian_ids, binning.gaussian_ids.new_full((1,), -1)])
    # pixels of the border tiles past the image's edge are composited but not part of the image
    local = torch.arange(p)
    for tiles, kmax in _tile_groups(binning, block, budget):
        b = tiles.shape[0]
        cx, cy = tile_centres(tiles, binning, dt)
        inside = (((tiles % binning.tiles_x)[:, None] * ts + local % ts < width)
                  & ((tiles // binning.tiles_x)[:, None] * ts + local // ts < height)).to(dt)  # (B, P)
        start, count = binning.offsets[tiles], binning.counts[tiles]
        trans = torch.ones((b, p), dtype=dt)
        done = torch.zeros((b, p), dtype=torch.bool)
        rest = acc[tiles][:, :3].permute(1, 0, 2).contiguous()  # (3, B, P): colour still to come
        for active, k0, kb, ids in live_blocks(start, count, done, kmax, block, dummy):
            ids = ids.reshape(-1)
            gd = pairs.index_select(0, ids).reshape(kb, -1, pairs.shape[1])
            # alpha and transmittance exactly as the renderer computes them
            was_done = done[active]
            t_prev = trans[active]
            t0 = torch.where(was_done, torch.zeros_like(t_prev), t_prev)
            alpha, tr, mu, mv = alpha_and_transmittance(gd, cx[active], cy[active], mono2t, t0)
            w, kept = compositing_weights(tr)  # (kb, B, P)
            if k0 + block < kmax:
                trans[active] = torch.where(was_done, t_prev, torch.minimum(tr[0], kept.amin(0)))
                done[active] = was_done | (tr[-1] < T_MIN)
            col = gd[..., 6:9].permute(2, 0, 1)[..., None]  # (3, kb, B, 1)
            behind = col * w  # (3, kb, B, P): becomes the colour drawn after each, in place
            behind[:, 0].neg_().add_(rest[:, active])
            for k in range(1, kb):  # (a loop of slabs is ten times faster than torch.cumsum here)
                torch.sub(behind[:, k - 1], behind[:, k], out=behind[:, k])
            rest[:, active] = behind[:, -1]
            w = w.mul_(inside[active])  # from here on: derivatives of the image's pixels only
            w2 = (w * w).sum(-1).reshape(-1)
            keep = (w2 > 0).nonzero().squeeze(1)
            if keep.numel() == 0:
                continue
            # d I_c / d E = alpha (colour T - behind / (1 - alpha)); zero where alpha is capped,
            # skipped (alpha = 0), past the stop (w = 0) or outside the image
            gate = torch.where((alpha < ALPHA_MAX) & (w > 0), alpha, torch.zeros_like(alpha))
            inv = torch.rsub(alpha, 1.0).reciprocal_()
            e = behind.mul_(inv).neg_().addcmul_(col, tr[:-1]).mul_(gate)
            s = (e * e).sum(0).reshape(-1, p)
            t = e.mul_(w).reshape(3, -1, p)
            moments = torch.empty((_NMOM, s.shape[0]), dtype=dt)
            torch.mm(mono_t, s.T, out=moments[:len(_POWERS)])
            moments[len(_POWERS):-1] = torch.matmul(mono2t, t.transpose(1, 2)).reshape(3 * _P2, -1)
            moments[-1] = w2
            off = torch.stack([mu.reshape(-1), mv.reshape(-1)])
            if keep.numel() < w2.numel():
                moments, off, ids = moments[:, keep], off[:, keep], ids.index_select(0, keep)
            mom.index_add_(0, gids.index_select(0, ids), _central(moments, off).T.contiguous())


def _central(raw: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
    """(34, K) float64 moments about each Gaussian's centre from the (34, K) moments about the
    tile centre, the centre's offset from it being `off` (2, K): sum w (u - mu)^i (v - mv)^j =
    sum_kl C(i,k) C(j,l) (-mu)^(i-k) (-mv)^(j-l) sum w u^k v^l, by Taylor shifts in u, then in v
    (in place, 48 multiply-adds a pair)."""
    m = raw.double()
    nu, nv = -off[0].double(), -off[1].double()
    s = [m[k] for k in range(len(_POWERS))]
    t = [m[len(_POWERS) + ch * _P2:len(_POWERS) + (ch + 1) * _P2] for ch in range(3)]

    def shift(rows, a):  # rows[0..n]: moments of orders 0..n in one variable; shift by a
        n = len(rows) - 1
        for step in range(1, n + 1):
            for i in range(n, step - 1, -1):
                rows[i].addcmul_(rows[i - 1], a)

    for degree, group in ((4, s), (2, None)):
        for j in range(degree + 1):  # shift in u: for each power of v, the powers of u
            if group is not None:
                shift([group[_INDEX[(i, j)]] for i in range(degree - j + 1)], nu)
            else:
                for tc in t:
                    shift([tc[_INDEX[(i, j)]] for i in range(degree - j + 1)], nu)
        for i in range(degree + 1):  # then in v
            if group is not None:
                shift([group[_INDEX[(i, j)]] for j in range(degree - i + 1)], nv)
            else:
                for tc in t:
                    shift([tc[_INDEX[(i, j)]] for j in range(degree - i + 1)], nv)
    return m


def _sh_basis_gradient(d: list[torch.Tensor], degree: int) -> list[tuple]:
    """Derivatives (d/dx, d/dy, d/dz; None for 0) of the non-constant real SH basis functions of
    `gvae_core.rendering.sh.sh_basis`, in its order, at directions d = (x, y, z) (M-vectors)."""
    x, y, z = d
    c1 = SH_C1_
    out = [(None, -c1, None), (None, None, c1), (-c1, None, None)]
    if degree >= 2:
        a = SH_C2_
        out += [(a[0] * y, a[0] * x, None), (None, a[1] * z, a[1] * y), (-2 * a[2] * x, -2 * a[2] * y, 4 * a[2] * z),
                (a[3] * z, None, a[3] * x), (2 * a[4] * x, -2 * a[4] * y, None)]
    if degree >= 3:
        b = SH_C3_
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [(6 * b[0] * xy, 3 * b[0] * (xx - yy), None), (b[1] * yz, b[1] * xz, b[1] * xy),
                (-2 * b[2] * xy, b[2] * (4 * zz - xx - 3 * yy), 8 * b[2] * yz),
                (-6 * b[3] * xz, -6 * b[3] * yz, b[3] * (6 * zz - 3 * xx - 3 * yy)),
                (b[4] * (4 * zz - 3 * xx - yy), -2 * b[4] * xy, 8 * b[4] * xz),
                (2 * b[5] * xz, -2 * b[5] * yz, b[5] * (xx - yy)), (3 * b[6] * (xx - yy), -6 * b[6] * xy, None)]
    return out


def _mad(terms):
    """sum of products a * b over (a, b) pairs, skipping None factors; None if nothing is left."""
    acc = None
    for a, b in terms:
        if a is None or b is None:
            continue
        acc = a * b if acc is None else acc.addcmul_(a, b) if torch.is_tensor(a) and torch.is_tensor(b) else acc + a * b
    return acc


def _dot3(p, q):
    return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]


@dataclass
class _Jacobian:
    """One view's camera space of the rows: offset from the camera (float64), x/z, y/z, 1/z, 1/z²,
    the perspective Jacobian's entries (its centre clamped, `fov_limits`) and their derivatives by
    camera x, y, z (those that are not zero)."""

    rel64: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    iz: torch.Tensor
    iz2: torch.Tensor
    j00: torch.Tensor
    j11: torch.Tensor
    j02: torch.Tensor
    j12: torch.Tensor
    dj00_z: torch.Tensor
    dj11_z: torch.Tensor
    dj02_x: torch.Tensor
    dj02_z: torch.Tensor
    dj12_y: torch.Tensor
    dj12_z: torch.Tensor


def _jacobian(f: dict, rows: torch.Tensor, camera: Camera, dt) -> _Jacobian:
    f64 = torch.float64
    rel64 = f["means"].index_select(0, rows).to(f64) - torch.as_tensor(camera.center, dtype=f64)
    x, y, z = (rel64 @ torch.as_tensor(camera.rotation.T, dtype=f64)).to(dt).T.contiguous()
    iz = 1.0 / z
    u, v = x * iz, y * iz
    fx, fy = camera.fx, camera.fy
    lo_x, hi_x, lo_y, hi_y = pj.fov_limits(camera)
    uc, vc = u.clamp(lo_x, hi_x), v.clamp(lo_y, hi_y)
    free_u, free_v = ((u > lo_x) & (u < hi_x)).to(dt), ((v > lo_y) & (v < hi_y)).to(dt)
    iz2 = iz * iz
    return _Jacobian(rel64, u, v, iz, iz2, j00=fx * iz, j11=fy * iz, j02=-fx * uc * iz, j12=-fy * vc * iz,
                     dj00_z=-fx * iz2, dj11_z=-fy * iz2, dj02_x=-fx * iz2 * free_u, dj02_z=fx * iz2 * (uc + free_u * u),
                     dj12_y=-fy * iz2 * free_v, dj12_z=fy * iz2 * (vc + free_v * v))


def _camera_axes(f: dict, rows: torch.Tensor, camera: Camera, dt, alias: _Antialias):
    """(m0, m1, m2, gain, size, dlog_o): rows 0, 1, 2 (camera x, y, z) of the Gaussian's axes in
    camera space (column k of R diag(s_eff)), d log s_eff / d log s (3, M), the 3D size (None
    without one) and d log(opacity) / d theta so far (the 3D filter's compensation; None: zero)."""
    q_camera = torch.as_tensor(quaternions.from_rotmat(camera.rotation), dtype=dt)
    qn = quaternions.multiply(q_camera, quaternions.normalize(f["quats"].index_select(0, rows).to(dt)))
    w, qx, qy, qz = qn.T.contiguous()
    ls_raw = f["scales"].index_select(0, rows).to(dt)
    ls = ls_raw.clamp(*LOG_SCALE_RANGE)
    inside = ((ls_raw >= LOG_SCALE_RANGE[0]) & (ls_raw <= LOG_SCALE_RANGE[1])).to(dt)
    dlog_o = [None] * BLOCK  # d log(opacity) / d theta
    size = None if alias.size is None else alias.size.index_select(0, rows).to(dt)
    if size is None:
        s_eff, gain = ls.exp(), inside  # gain: d log s_eff / d log s
    else:  # the 3D filter or dilation: effective scales sqrt(s² + f²)
        size = torch.where(torch.isfinite(size), size, torch.zeros_like(size)).clamp(*pj.FILTER_3D_RANGE)
        log_eff = 0.5 * torch.logaddexp(2.0 * ls, 2.0 * torch.log(size)[:, None])
        s_eff = log_eff.exp()
        gain = (2.0 * (ls - log_eff)).exp() * inside  # s² / (s² + f²)
        if alias.mode == "mip":  # opacity times prod s / s_eff
            dlog_o[3:] = list(((1.0 - gain) * inside).T)
    s_eff, gain = s_eff.T.contiguous(), gain.T.contiguous()
    r0 = (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy))
    r1 = (2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx))
    r2 = (2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy))
    m0 = [r0[k] * s_eff[k] for k in range(3)]
    m1 = [r1[k] * s_eff[k] for k in range(3)]
    m2 = [r2[k] * s_eff[k] for k in range(3)]
    return m0, m1, m2, gain, size, dlog_o


@dataclass
class _Conic:
    """The projected axes a, b (rows of J M), a x b, det(t tᵀ) = |a x b|², the 2D dilation d,
    1 / det Σ2D, the conic (qa, qb, qc) and the derivatives of |a|² + d, |b|² + d and a.b by theta
    (position in camera space, then log-scale; None: zero)."""

    ak: list
    bk: list
    cross: list
    cc: torch.Tensor
    d: object
    inv: torch.Tensor
    qa: torch.Tensor
    qb: torch.Tensor
    qc: torch.Tensor
    daa: list
    dbb: list
    dab: list


def _conic(jac: _Jacobian, m0: list, m1: list, m2: list, gain, size, alias: _Antialias, camera: Camera,
           dt) -> _Conic:
    ak = [jac.j00 * m0[k] + jac.j02 * m2[k] for k in range(3)]  # rows a, b of J M (the projected axes)
    bk = [jac.j11 * m1[k] + jac.j12 * m2[k] for k in range(3)]
    am0, am1, am2 = _dot3(ak, m0), _dot3(ak, m1), _dot3(ak, m2)
    bm0, bm1, bm2 = _dot3(bk, m0), _dot3(bk, m1), _dot3(bk, m2)
    aa, bb, ab = _dot3(ak, ak), _dot3(bk, bk), _dot3(ak, bk)
    d = pj.MIP_2D_VARIANCE if alias.mode == "mip" else pj.DILATION
    dd_z = None  # d (2D dilation) / d camera z
    if alias.mode == "matched" and size is not None:  # what the 3D dilation leaves of the classic one
        rest_2d = pj.DILATION - size * size * (camera.fx * camera.fy) * jac.iz2
        d = rest_2d.clamp(min=0.0)
        dd_z = 2.0 * size * size * (camera.fx * camera.fy) * jac.iz2 * jac.iz * (rest_2d > 0).to(dt)
    cross = [ak[1] * bk[2] - ak[2] * bk[1], ak[2] * bk[0] - ak[0] * bk[2], ak[0] * bk[1] - ak[1] * bk[0]]
    cc = _dot3(cross, cross)
    det = cc + d * (aa + bb) + d * d
    daa = [2 * jac.dj02_x * am2, None, 2 * (jac.dj00_z * am0 + jac.dj02_z * am2)] + \
        [2 * ak[k] * ak[k] * gain[k] for k in range(3)]
    dbb = [None, 2 * jac.dj12_y * bm2, 2 * (jac.dj11_z * bm1 + jac.dj12_z * bm2)] + \
        [2 * bk[k] * bk[k] * gain[k] for k in range(3)]
    if dd_z is not None:  # the diagonal of Sigma_2D = t t^T + d I moves with d
        daa[2], dbb[2] = daa[2] + dd_z, dbb[2] + dd_z
    dab = [jac.dj02_x * bm2, jac.dj12_y * am2,
           jac.dj00_z * bm0 + jac.dj02_z * bm2 + jac.dj11_z * am1 + jac.dj12_z * am2] + \
        [2 * ak[k] * bk[k] * gain[k] for k in range(3)]
    inv = 1.0 / det
    return _Conic(ak, bk, cross, cc, d, inv, (bb + d) * inv, -ab * inv, (aa + d) * inv, daa, dbb, dab)


def _conic_derivatives(c: _Conic) -> tuple[list, list, list]:
    """d qa, d qb, d qc by theta (None: zero)."""
    ca = (c.qa * c.qa, 2 * c.qa * c.qb, c.qb * c.qb)
    cb = (c.qa * c.qb, c.qb * c.qb + c.qa * c.qc, c.qb * c.qc)
    cq = (c.qb * c.qb, 2 * c.qb * c.qc, c.qc * c.qc)

    def derivative(coef):
        return [_mad([(-coef[0], c.daa[t]), (-coef[1], c.dab[t]), (-coef[2], c.dbb[t])]) for t in range(BLOCK)]

    return derivative(ca), derivative(cb), derivative(cq)


def _mip_opacity_derivative(jac: _Jacobian, m0: list, m1: list, m2: list, gain, c: _Conic, dt) -> list:
    """d log(opacity) / d theta of the 2D Mip filter's compensation sqrt(det(t tᵀ) / det Σ2D)
    (zero where the ratio is held at its floor)."""
    ak, bk, cross = c.ak, c.bk, c.cross
    pv = [bk[1] * cross[2] - bk[2] * cross[1], bk[2] * cross[0] - bk[0] * cross[2],
          bk[0] * cross[1] - bk[1] * cross[0]]  # B x C
    qv = [cross[1] * ak[2] - cross[2] * ak[1], cross[2] * ak[0] - cross[0] * ak[2],
          cross[0] * ak[1] - cross[1] * ak[0]]  # C x A
    dcc = [2 * jac.dj02_x * _dot3(m2, pv), 2 * jac.dj12_y * _dot3(m2, qv),
           2 * (jac.dj00_z * _dot3(m0, pv) + jac.dj02_z * _dot3(m2, pv) + jac.dj11_z * _dot3(m1, qv)
                + jac.dj12_z * _dot3(m2, qv))]
    dcc += [2 * gain[k] * (ak[k] * pv[k] + bk[k] * qv[k]) for k in range(3)]
    ok = (c.cc * c.inv > pj.MIP_2D_RATIO_FLOOR).to(dt)
    inv_cc = ok / torch.where(c.cc > 0, c.cc, torch.ones_like(c.cc))
    out = []
    for t in range(BLOCK):
        ddet = dcc[t] + c.d * ((c.daa[t] if c.daa[t] is not None else 0.0) + (c.dbb[t] if c.dbb[t] is not None
                                                                                else 0.0))
        out.append(0.5 * (dcc[t] * inv_cc - ok * ddet * c.inv))
    return out


def _monomial_coefficients(jac: _Jacobian, c: _Conic, conic_derivatives: tuple, dlog_o: list, camera: Camera,
                           scale: float) -> list[list]:
    """lam[monomial][theta]: the derivative of the exponent E by theta as a polynomial in the pixel
    offset (monomials 1, du, dv, du², du dv, dv²), the position part carried from camera x, y, z to
    the normalised world position (d/dp_j = scale * sum_i d/dcam_i R[i, j])."""
    fx, fy, rot = camera.fx, camera.fy, camera.rotation
    dmx = [fx * jac.iz, None, -fx * jac.u * jac.iz, None, None, None]
    dmy = [None, fy * jac.iz, -fy * jac.v * jac.iz, None, None, None]
    to_world = [[float(scale * rot[i, j]) for j in range(3)] for i in range(3)]

    def world(g):
        if all(x is None for x in g[:3]):
            return g
        pos = [_mad([(to_world[i][j], g[i]) for i in range(3)]) for j in range(3)]
        return pos + g[3:]

    dqa, dqb, dqc = (world(g) for g in conic_derivatives)
    dmx, dmy, dlog_o = world(dmx), world(dmy), world(dlog_o)
    qa, qb, qc = c.qa, c.qb, c.qc
    return [dlog_o, [_mad([(qa, dmx[t]), (qb, dmy[t])]) for t in range(BLOCK)],
            [_mad([(qb, dmx[t]), (qc, dmy[t])]) for t in range(BLOCK)],
            [None if g is None else -0.5 * g for g in dqa], [None if g is None else -g for g in dqb],
            [None if g is None else -0.5 * g for g in dqc]]


def _moment_blocks(lam: list[list], mom: torch.Tensor) -> list[list]:
    """h[t1][t2] (t1 <= t2; None: zero) = lam S lamᵀ, S the moments of s by monomial pairs."""
    srow = {p: mom[k] for k, p in enumerate(_POWERS)}
    smat = [[srow[(_POWERS[i][0] + _POWERS[j][0], _POWERS[i][1] + _POWERS[j][1])] for j in range(_P2)]
            for i in range(_P2)]
    # A = lam^T-side product: a[theta][j] = sum_i lam[i][theta] S[i][j]
    a_mat = [[_mad([(lam[i][t], smat[i][j]) for i in range(_P2)]) for j in range(_P2)] for t in range(BLOCK)]
    h = [[None] * BLOCK for _ in range(BLOCK)]
    for t1 in range(BLOCK):
        for t2 in range(t1, BLOCK):
            h[t1][t2] = _mad([(a_mat[t1][j], lam[j][t2]) for j in range(_P2)])
    return h


def _colour_jacobian(rest: torch.Tensor, rel64: torch.Tensor, colors: torch.Tensor, degree: int, dt,
                     scale: float) -> list[list]:
    """jc[c][axis]: d colour_c / d normalised world position of the SH bands `rest` (k, 3, M) along
    the view direction (0 where the colour is clamped)."""
    k = len(rest)
    dist = torch.sqrt((rel64 * rel64).sum(-1))
    dirs = (rel64 / dist[:, None]).to(dt).T.contiguous()
    inv_dist = (scale / dist).to(dt)
    grads = _sh_basis_gradient(list(dirs), degree)
    live = (colors > 0).to(dt).T.contiguous()
    jc = []  # d colour_c / d world position (normalised), c = r, g, b
    for c in range(3):
        g = [_mad([(grads[b][axis], rest[b, c]) for b in range(k)]) for axis in range(3)]
        g = [torch.zeros_like(inv_dist) if gi is None else gi for gi in g]
        radial = _dot3(g, dirs)
        jc.append([(g[axis] - radial * dirs[axis]) * inv_dist * live[c] for axis in range(3)])
    return jc


def _add_colour_terms(h: list[list], lam: list[list], jc: list[list], mom: torch.Tensor, m: int) -> None:
    """Add to h the cross terms sum_p e_c w (lam mono)_t1 (d colour_c)_t2, both orders, and the
    colour's own part w² (d colour)(d colour)."""
    trow = mom[len(_POWERS):-1].reshape(3, _P2, m)
    wsum = mom[-1]
    for t1 in range(BLOCK):
        lt = [_mad([(lam[i][t1], trow[c, i]) for i in range(_P2)]) for c in range(3)]
        for t2 in range(BLOCK):
            if t2 < 3:
                extra = _mad([(lt[c], jc[c][t2]) for c in range(3)])
                if extra is not None:
                    if t1 <= t2:
                        h[t1][t2] = extra if h[t1][t2] is None else h[t1][t2] + extra
                    if t2 <= t1:
                        h[t2][t1] = extra if h[t2][t1] is None else h[t2][t1] + extra
            if t1 < 3 and t1 <= t2 < 3:
                own = _mad([(jc[c][t1], jc[c][t2]) for c in range(3)]) * wsum
                h[t1][t2] = own if h[t1][t2] is None else h[t1][t2] + own


def _gaussian_blocks(f: dict, rows: torch.Tensor, mom: torch.Tensor, colors: torch.Tensor, camera: Camera,
                     degree: int, dt, scale: float, alias: _Antialias) -> torch.Tensor:
    """(21, M) packed blocks of one view for the Gaussians `rows`, from their central moments
    `mom` (34, M) and drawn colours (M, 3) (0 where clamped).

    The derivatives of what the rasteriser draws (centre, conic, opacity, colour) with respect to
    camera-space position and log-scale are written out from the projection of
    `gvae_core.rendering` in the cloud's anti-aliasing mode (`classic`: the 2D dilation; `matched`:
    the 3D dilation and what it leaves of the 2D one at the Gaussian's depth; `mip`: the 3D filter
    and the 2D Mip filter with their opacity compensation), on M-vectors, one component at a time.
    The derivative of the exponent E = log o - (a du² + 2 b du dv + c dv²) / 2 is a polynomial in
    the pixel offset (du, dv) from the centre, lam[monomial][theta], so J^T J = lam S lam^T + cross
    terms with the colour + the colour's own part, S the moments of s by monomial pairs."""
    m = len(rows)
    jac = _jacobian(f, rows, camera, dt)
    m0, m1, m2, gain, size, dlog_o = _camera_axes(f, rows, camera, dt, alias)
    conic = _conic(jac, m0, m1, m2, gain, size, alias, camera, dt)
    conic_derivatives = _conic_derivatives(conic)
    if alias.mode == "mip":
        for t, term in enumerate(_mip_opacity_derivative(jac, m0, m1, m2, gain, conic, dt)):
            dlog_o[t] = term if dlog_o[t] is None else dlog_o[t] + term
    lam = _monomial_coefficients(jac, conic, conic_derivatives, dlog_o, camera, scale)
    mom = mom.to(dt)
    h = _moment_blocks(lam, mom)
    rest = f["sh_rest"].index_select(0, rows)
    if degree > 0 and rest.shape[1]:
        rest = rest[:, :(degree + 1) ** 2 - 1].to(dt).permute(1, 2, 0).contiguous()  # (k, 3, M)
        _add_colour_terms(h, lam, _colour_jacobian(rest, jac.rel64, colors, degree, dt, scale), mom, m)
    out = torch.zeros((len(_TRIU[0]), m), dtype=torch.float64)
    for k, (t1, t2) in enumerate(zip(*_TRIU.tolist())):
        if h[t1][t2] is not None:
            out[k] = torch.nan_to_num(h[t1][t2], nan=0.0, posinf=0.0, neginf=0.0)
    return out


class _Clock:
    """Seconds per part, added into `timings` (a dict, or None for no bookkeeping)."""

    def __init__(self, timings: dict | None):
        self.timings = timings
        self.t = time.perf_counter()

    def __call__(self, part: str) -> None:
        now = time.perf_counter()
        if self.timings is not None:
            self.timings[part] = self.timings.get(part, 0.0) + now - self.t
        self.t = now


def _project(f: dict, camera: Camera, degree: int, dt, aa: _Antialias, chunk: int = 1 << 17) -> Projected:
    """`rendering.projection.project` of every Gaussian, in chunks (it works Gaussian by Gaussian):
    the same result with small temporaries, which for millions of Gaussians saves most of the time
    spent faulting in fresh memory and missing the cache."""
    n = len(f["means"])
    parts = []
    for i in range(0, max(n, 1), chunk):
        part = slice(i, i + chunk)
        parts.append(project(f["means"][part], f["scales"][part], f["quats"][part], f["opacities"][part],
                             f["sh_dc"][part], f["sh_rest"][part], camera, degree, dtype=dt,
                             **aa.select(part).project_args()))
    if len(parts) == 1:
        return parts[0]
    return Projected(**{fld.name: torch.cat([getattr(p, fld.name) for p in parts]) for fld in fields(Projected)})


def _keep_frame(frames: list | None, camera: Camera, settings: RenderSettings, table, binning, rows, acc) -> None:
    """Append the view's `Frame` (composited) to `frames`, unless None."""
    if frames is not None:
        frames.append(Frame(camera, settings, table, binning, rows,
                            tiles_to_image(acc, binning, camera.height, camera.width)))


def _accumulate_view(f: dict, camera: Camera, degree: int, settings: RenderSettings, scale: float,
                     out: torch.Tensor, aa: _Antialias, timings: dict | None = None,
                     work: torch.Tensor | None = None, chunk: int = 1 << 16,
                     frames: list | None = None, rows: torch.Tensor | None = None) -> torch.Tensor | None:
    """Add this view's packed blocks into `out` (21, N) float64 (torch code). `work`: the (N, 34)
    float64 moment buffer of a previous view, reused (returned for the next). `frames`: a list that
    gets the view's `Frame`, its table row i drawing cloud row `rows[i]`."""
    dt = settings.dtype
    clock = _Clock(timings)
    with torch.no_grad():
        proj = _project(f, camera, degree, dt, aa)
        clock("project")
        binning = bin_gaussians(proj.means2d, proj.footprint, proj.depths, proj.visible, camera.width, camera.height,
                                settings.tile_size, exact=settings.exact_tiles)
        clock("bin")
        table = pack(proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths)
        del proj
        pairs = pair_table(table, binning)  # (for the compositing and the sweep)
        acc = composite(table, binning, block=settings.block, budget=settings.budget, pairs=pairs, kernels="torch")
        _keep_frame(frames, camera, settings, table, binning, rows, acc)
        clock("composite")
        if binning.num_pairs == 0:
            return work
        if work is None or work.shape != (out.shape[1], _NMOM):
            work = torch.zeros((out.shape[1], _NMOM), dtype=torch.float64)
        else:
            work.zero_()
        mom = work
        _gauss_newton_sweep(pairs, binning, acc, settings.block, settings.budget, mom,
                            camera.width, camera.height)
        del acc, binning, pairs
        clock("sweep")
        seen = (mom[:, -1] > 0).nonzero().squeeze(1)
        clock("moments")
        for i in range(0, len(seen), chunk):
            r = seen[i:i + chunk]
            blocks = _gaussian_blocks(f, r, mom.index_select(0, r).T.contiguous(), table.index_select(0, r)[:, 6:9],
                                      camera, degree, dt, scale, aa)
            out.index_add_(1, r, blocks)
        clock("blocks")
    return work


def _accumulate_view_compiled(inp: compiled.Inputs, camera: Camera, degree: int, settings: RenderSettings,
                              scale: float, out: np.ndarray, timings: dict | None = None,
                              work: np.ndarray | None = None, frames: list | None = None,
                              rows: torch.Tensor | None = None) -> np.ndarray | None:
    """`_accumulate_view` by the compiled kernels (`rendering.compiled`): the blocks added into
    `out` (N, 21) float64; `work` the (N, 34) float32 moment buffer."""
    clock = _Clock(timings)
    with torch.no_grad():
        table_np, foot, radii, visible = compiled.project_arrays(inp, camera, degree)
        table = torch.from_numpy(table_np)
        clock("project")
        binning = compiled.bin_gaussians(table, torch.from_numpy(foot), torch.from_numpy(visible), camera.width,
                                         camera.height, settings.tile_size, exact=settings.exact_tiles)
        clock("bin")
        del foot, radii, visible
        acc = compiled.composite_forward(table, binning)
        _keep_frame(frames, camera, settings, table, binning, rows, acc)
        clock("composite")
        if binning.num_pairs == 0:
            return work
        if work is None or work.shape != (len(inp), _NMOM):  # float32: a few pairs a Gaussian are summed
            work = np.zeros((len(inp), _NMOM), np.float32)  # (gaussian_blocks leaves it zeros again)
        compiled.gauss_newton_moments(table, binning, acc, camera.width, camera.height, work)
        del acc, binning
        clock("sweep")
        compiled.gaussian_blocks(inp, camera, degree, scale, table, work, out)
        clock("blocks")
    return work


def scoring_settings(render_settings: RenderSettings | None = None) -> RenderSettings:
    """The settings the Hessian renders its views with: the given ones, else the renderer's with
    TILE_SIZE tiles."""
    return render_settings or RenderSettings(tile_size=TILE_SIZE)


def _packed_to_blocks(packed: torch.Tensor) -> torch.Tensor:
    """(N, 6, 6) symmetric blocks from their packed upper triangles (21, N)."""
    blocks = torch.zeros((packed.shape[1], BLOCK, BLOCK), dtype=packed.dtype)
    blocks[:, _TRIU[0], _TRIU[1]] = packed.T
    blocks[:, _TRIU[1], _TRIU[0]] = packed.T
    return blocks


def _hessian_packed(cloud: GaussianCloud, cameras: Sequence[Camera] | None, views: int, resolution: int,
                    render_settings: RenderSettings | None, normalization,
                    progress: Callable[[float, str], None] | None, timings: dict | None = None,
                    frames: list | None = None, in_order: bool = True) -> tuple[torch.Tensor, np.ndarray | None]:
    """(packed blocks (21, N), None) in the cloud's order; with `in_order` False, where the compiled
    kernels ran, (packed blocks in the Morton order they were summed in, that order): a caller that
    reduces each block to a number puts the numbers back instead of the blocks."""
    n = len(cloud)
    if n == 0:
        return torch.zeros((len(_TRIU[0]), n), dtype=torch.float64), None
    normalization = normalization or cloud.normalization()
    cams = (scoring_views(cameras, views, resolution, cloud) if cameras is not None
            else default_views(cloud, views or DEFAULT_VIEWS, resolution, normalization=normalization))
    settings = scoring_settings(render_settings)
    aa = _Antialias.of(cloud, settings)
    # Work on the Gaussians in Morton order: neighbours in space are neighbours in memory, which
    # makes the per-Gaussian gathers and sums of every view several times faster.
    order = torch.from_numpy(_morton_order(cloud.numpy().means))
    f = {k: v.index_select(0, order) for k, v in _fields(cloud, settings.dtype).items()}
    aa = aa.select(order)
    fast = compiled.use_compiled(settings.kernels, "cpu", settings.dtype)
    if fast:
        if progress is not None:
            compiled.compile_kernels(lambda _, message: progress(0.0, message))
        inp = compiled.Inputs(f["means"], f["scales"], f["quats"], f["opacities"], f["sh_dc"], f["sh_rest"],
                              **aa.project_args())
        rows_out = np.zeros((n, len(_TRIU[0])), np.float64)
    else:
        out = torch.zeros((len(_TRIU[0]), n), dtype=torch.float64)
    work = None
    for k, cam in enumerate(cams):
        if progress is not None:
            progress(k / len(cams), f"Hessian view {k + 1}/{len(cams)}")
        if fast:
            work = _accumulate_view_compiled(inp, cam, cloud.sh_degree, settings, float(normalization[1]), rows_out,
                                             timings, work, frames=frames, rows=order)
        else:
            work = _accumulate_view(f, cam, cloud.sh_degree, settings, float(normalization[1]), out, aa, timings,
                                    work, frames=frames, rows=order)
    del work, f
    if fast and not in_order:
        return torch.from_numpy(rows_out).T, order.numpy()
    if fast:  # rows back in the cloud's order; the packed form is their transpose (no copy)
        result = np.empty_like(rows_out)
        rows = order.numpy()

        def put(a: int, b: int) -> None:  # the rows go to distinct places: ranges in threads
            result[rows[a:b]] = rows_out[a:b]

        in_threads(n, put)
        return torch.from_numpy(result).T, None
    result = torch.empty_like(out)
    result[:, order] = out
    return result, None


def _morton_order(means: np.ndarray, bits: int = 21) -> np.ndarray:
    """Rows sorted along a Z-order curve of their positions (`bits` <= 21 per axis, robust box)."""
    p = np.asarray(means, np.float64)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    if not np.isfinite(p).all():
        p = np.where(np.isfinite(p), p, 0.0)
    lo, hi = np.percentile(p, [0.5, 99.5], axis=0)
    code = np.empty(len(p), np.uint64)

    def codes(a: int, b: int) -> None:  # elementwise per row: ranges in threads
        q = np.clip((p[a:b] - lo) / np.maximum(hi - lo, 1e-30), 0.0, 1.0)
        q = (q * ((1 << bits) - 1)).astype(np.uint64)
        c = np.zeros(b - a, np.uint64)
        for axis in range(3):  # spread the bits two apart (the usual magic numbers), then interleave
            v = q[:, axis]
            for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                                (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
                v = (v | (v << np.uint64(shift))) & np.uint64(mask)
            c |= v << np.uint64(axis)
        code[a:b] = c

    in_threads(len(p), codes)
    return np.argsort(code, kind="stable")


@dataclass
class _Antialias:
    """How `render` draws the cloud (`gvae_core.antialias`): the resolved mode ("classic", "mip"
    or "matched") and the per-Gaussian 3D size it uses (the filter or the dilation), or None."""

    mode: str
    size: torch.Tensor | None = None

    @classmethod
    def of(cls, cloud: GaussianCloud, settings: RenderSettings) -> _Antialias:
        mode = resolve_antialias(getattr(settings, "antialias", "classic"), cloud)
        key = {"mip": FILTER_KEY, "matched": DILATION_KEY}.get(mode)
        size = None
        if key is not None and key in cloud.extra:
            size = torch.as_tensor(np.asarray(cloud.numpy().extra[key], np.float32).reshape(-1))
            if size.numel() != len(cloud):
                raise ValueError(f"hessian: extra[{key!r}] must hold one value per Gaussian, got {size.numel()} for "
                                 f"{len(cloud)} Gaussians")
        return cls(mode, size)

    def select(self, rows) -> _Antialias:
        """These rows (an index tensor or a slice)."""
        if self.size is None:
            return self
        return _Antialias(self.mode, self.size[rows] if isinstance(rows, slice) else self.size.index_select(0, rows))

    def project_args(self) -> dict:
        if self.mode == "mip":
            return {"filter_3d": self.size, "mip_2d": True}
        if self.mode == "matched" and self.size is not None:
            return {"dilation_3d": self.size}
        return {}


def hessian_blocks(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None, *, views: int = DEFAULT_VIEWS,
                   resolution: int = DEFAULT_RESOLUTION, render_settings: RenderSettings | None = None,
                   normalization=None, progress=None) -> torch.Tensor:
    """(N,6,6) float64: sum over views, pixels and colour channels of J_i^T J_i, J_i the derivative
    of the rendered image with respect to Gaussian i's position (in the normalised frame) and
    log-scale, computed exactly (see the module docstring). `cameras`: the capture's cameras, of
    which `views` are used (0: all; `capture.scoring_views`: those that see the cloud, spread out,
    scaled down to `resolution` pixels high), else `views` cameras from `capture.default_views`.
    `render_settings`: a `gvae_core.rendering.RenderSettings`: its anti-aliasing mode (the default
    is the renderer's), tile size, block and budget (speed and memory only; default tile size
    TILE_SIZE), dtype (float64 for checks); `normalization`: the cloud's (centre, scale) when known
    (`GaussianCloud.normalization`); `progress(fraction, message)` before each view."""
    return _packed_to_blocks(_hessian_packed(cloud, cameras, views, resolution, render_settings, normalization,
                                             progress)[0])


def _prepare(cloud: GaussianCloud, dtype=torch.float32):
    """A torch copy whose means and log-scales are leaves that require grad."""
    c = cloud.detach().to_torch(dtype=dtype) if cloud.is_torch else cloud.to_torch(dtype=dtype)
    means = c.means.detach().clone().requires_grad_(True)
    scales = c.scales.detach().clone().requires_grad_(True)
    return c.replace(means=means, scales=scales), means, scales


def hessian_blocks_reference(cloud: GaussianCloud, cameras: Sequence[Camera],
                             render_settings: RenderSettings | None = None) -> torch.Tensor:
    """Slow definition: J^T J accumulated pixel by pixel and channel by channel, one backward pass
    through `render` each (position in the normalised frame, log-scale). Cameras are used as given."""
    n = len(cloud)
    blocks = torch.zeros((n, BLOCK, BLOCK), dtype=torch.float64)
    scale = cloud.normalization()[1]
    dtype = render_settings.dtype if render_settings is not None else torch.float32
    rc, means, scales = _prepare(cloud, dtype)
    for cam in cameras:
        image = render(rc, cam, settings=render_settings).image.reshape(-1)
        for p in range(image.numel()):
            if not image[p].requires_grad:
                continue
            gm, gs = torch.autograd.grad(image[p], [means, scales], retain_graph=True, allow_unused=True)
            gm = torch.zeros_like(means) if gm is None else gm
            gs = torch.zeros_like(scales) if gs is None else gs
            g = torch.cat([gm * scale, gs], 1).double()
            blocks += g[:, :, None] * g[:, None, :]
    return blocks


def scores_from_packed(packed: torch.Tensor, score: str = "logdet", ridge: float = 1e-2,
                       kernels: str = "auto") -> torch.Tensor:
    """`scores_from_blocks` on packed upper triangles (21, N) (`_TRIU` order). `kernels`: "auto"
    takes the log-determinants of blocks on the CPU by the compiled kernels where Numba runs
    (`rendering.compiled.logdet_scores`), "torch" by `_logdet_eye_plus` (the reference)."""
    if score not in ("logdet", "trace"):
        raise ValueError(f"hessian: score must be 'logdet' or 'trace', got {score!r}")
    if kernels not in compiled.KERNEL_CHOICES:
        raise ValueError(f"hessian: kernels must be one of {compiled.KERNEL_CHOICES}, got {kernels!r}")
    index = {(int(i), int(j)): k for k, (i, j) in enumerate(zip(*_TRIU.tolist()))}
    on_diagonal = [index[(k, k)] for k in range(BLOCK)]
    fast = kernels != "torch" and packed.device.type == "cpu" and compiled.numba_missing() is None
    if fast:
        rows = packed.T.double().numpy()  # (N, 21): no copy when packed is the transpose of rows
        diagonal = torch.from_numpy(rows[:, on_diagonal].T)
    else:
        diagonal = packed[on_diagonal].double()
    diagonal = torch.nan_to_num(diagonal, nan=0.0, posinf=0.0, neginf=0.0)
    trace = sum(diagonal[k] for k in range(BLOCK)).clamp(min=0.0)
    if score == "trace" or packed.shape[1] == 0:
        return trace.float()
    lam = ridge * float(trace.mean()) / BLOCK
    if not math.isfinite(lam) or lam <= 0.0:
        return torch.zeros(packed.shape[1], dtype=torch.float32)
    if fast:
        return torch.from_numpy(compiled.logdet_scores(rows, lam))
    h = torch.nan_to_num(packed.double(), nan=0.0, posinf=0.0, neginf=0.0)
    out = torch.zeros(h.shape[1], dtype=torch.float32)
    step = 1 << 16  # cache-sized pieces
    for i in range(0, h.shape[1], step):
        out[i:i + step] = _logdet_eye_plus({key: h[k, i:i + step] / lam for key, k in index.items()})
    return out


def _logdet_eye_plus(a: dict) -> torch.Tensor:
    """log det(I + H) (float32, >= 0) of symmetric positive semi-definite 6x6 blocks given by their
    upper-triangle components a[(i, j)] (vectors), by an unrolled LDL^T factorisation (the pivots
    of I + H are >= 1)."""
    d, lo = [], {}
    out = torch.zeros_like(a[(0, 0)])
    for j in range(BLOCK):
        dj = 1.0 + a[(j, j)]
        for k in range(j):
            dj = dj - lo[(j, k)] * lo[(j, k)] * d[k]
        dj = dj.clamp(min=1.0)
        d.append(dj)
        out += torch.log(dj)
        for i in range(j + 1, BLOCK):
            v = a[(j, i)]
            for k in range(j):
                v = v - lo[(i, k)] * lo[(j, k)] * d[k]
            lo[(i, j)] = v / dj
    return out.clamp(min=0.0).float()


def scores_from_blocks(blocks: torch.Tensor, score: str = "logdet", ridge: float = 1e-2) -> torch.Tensor:
    """(N,) float32 scores from (N,6,6) blocks: 'trace', or 'logdet' = log det(I + H/lambda) with
    lambda = ridge * mean(trace)/6 (so the score does not depend on the image scale)."""
    b = blocks.double()
    b = 0.5 * (b + b.transpose(1, 2))
    return scores_from_packed(b[:, _TRIU[0], _TRIU[1]].T, score, ridge)


def hessian_scores(cloud: GaussianCloud, cameras: Sequence[Camera] | None = None, *, views: int = DEFAULT_VIEWS,
                   resolution: int = DEFAULT_RESOLUTION, score: str = "logdet", ridge: float = 1e-2,
                   render_settings: RenderSettings | None = None, normalization=None, progress=None,
                   timings: dict | None = None, frames: list | None = None) -> torch.Tensor:
    """(N,) finite, non-negative per-Gaussian scores from the exact Gauss-Newton blocks
    (`hessian_blocks`, same arguments); see the module docstring. `timings`: a dict that gets the
    seconds spent per part (project, bin, composite, sweep, moments, blocks, score); `frames`: a
    list that gets each view's `rendering.frames.Frame` of the cloud, composited (the scores need
    the compositing; keeping it costs about 70 bytes a Gaussian a view)."""
    if score not in ("logdet", "trace"):
        raise ValueError(f"hessian: score must be 'logdet' or 'trace', got {score!r}")
    packed, order = _hessian_packed(cloud, cameras, views, resolution, render_settings, normalization, progress,
                                    timings, frames, in_order=False)
    clock = _Clock(timings)
    scores = scores_from_packed(packed, score, ridge)
    if order is not None:  # (a score is its block's, with one ridge for all: the scores, not the blocks, go back)
        scores = torch.empty_like(scores).index_copy_(0, torch.from_numpy(order), scores)
    clock("score")
    return scores
