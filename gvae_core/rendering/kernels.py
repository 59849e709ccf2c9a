"""Compiled CPU kernels of the renderer and the Hessian sweep (Numba), used by `compiled`.

Each kernel is a plain loop over Gaussians, tiles or pixels, compiled once to machine code for
this CPU (`nogil`: the glue in `compiled` runs chunks of the work in threads) and cached on disk
in a user cache directory (`kernel_cache_dir`), never beside the source. Everything is float32
but what the torch path does in float64 (positions relative to the camera, the footprint and
tile tests); the rules are those of `projection`, `tiles` and `rasterize`, which the tests hold
these kernels to.

The innermost loops run over the pixels of one tile with no branches (selects only) so that the
compiler vectorises them; `_exp` is a polynomial exp that vectorises too (the C library's does not),
and the pixels still drawing are counted in float32 (an integer count in the same loop kept the
compiler at 4-wide vectors: twice the time).
Each kernel is only ever called with one set of argument types, so each compiles once.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
from pathlib import Path

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.core.caching import CompileResultCacheImpl, FunctionCache, _CacheLocator, _SourceFileBackedLocatorMixin
from numba.extending import intrinsic

from ..conventions import (LOG_SCALE_RANGE, NEAR_PLANE, OPACITY_LOGIT_RANGE, SH_C0, SH_C1, SH_C2, SH_C3)
from .projection import DILATION, FILTER_3D_RANGE, FOOTPRINT_MARGIN, MAX_AXIS_PX, MIP_2D_RATIO_FLOOR, MIP_2D_VARIANCE

f32 = np.float32


# ----------------------------------------------------------------------------- on-disk cache

def kernel_cache_dir() -> Path:
    """Where compiled kernels are kept: $GVAE_CACHE_DIR/kernels, else the user's cache directory
    (XDG_CACHE_HOME or ~/.cache on Linux, ~/Library/Caches on macOS, %LOCALAPPDATA% on Windows)
    /gvae/kernels; one folder per version of this file, of Numba and of numpy, so that checkouts and
    installs of the same kernels share it and different ones never overwrite each other's."""
    base = os.environ.get("GVAE_CACHE_DIR")
    if base:
        root = Path(base)
    elif sys.platform == "win32":
        root = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local") / "gvae"
    elif sys.platform == "darwin":
        root = Path.home() / "Library" / "Caches" / "gvae"
    else:
        root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "gvae"
    digest = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]
    numpy_version = ".".join(np.__version__.split(".")[:2])
    return root / "kernels" / f"numba-{numba.__version__}-numpy-{numpy_version}-{digest}"


class _Locator(_SourceFileBackedLocatorMixin, _CacheLocator):
    """Numba's cache locator for this file's kernels: `kernel_cache_dir()` (numba's own choice
    would be a __pycache__ beside the source, inside the install folder)."""

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(kernel_cache_dir())

    def get_cache_path(self):
        return self._cache_path


class _CacheImpl(CompileResultCacheImpl):
    _locator_classes = [_Locator]


class _Cache(FunctionCache):
    _impl_class = _CacheImpl


#: Compiler flags: fused multiply-adds and reassociation (vectorised sums), never the flags that
#: assume no NaN or infinity (the guards against them must stay).
FASTMATH = {"contract", "reassoc", "nsz", "arcp"}


def kernel(fn):
    """`numba.njit` without the GIL, cached in `kernel_cache_dir()` (set on this dispatcher only,
    so other code's use of numba is untouched); without a writable cache it still compiles."""
    disp = numba.njit(nogil=True, fastmath=FASTMATH, error_model="numpy")(fn)
    try:
        disp._cache = _Cache(disp.py_func)
    except (OSError, RuntimeError):  # no writable cache directory: compile in every process
        pass
    return disp


def is_cached(disp) -> bool:
    """Whether the on-disk cache holds something for this kernel and this version of the source."""
    cache = getattr(disp, "_cache", None)
    if not isinstance(cache, _Cache):
        return False
    try:
        return bool(cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 - an unreadable index is a missing one
        return False


def module_kernels(module) -> list:
    """The dispatchers `kernel` made in `module` (those `is_cached` can answer for)."""
    return [v for v in vars(module).values() if isinstance(getattr(v, "_cache", None), _Cache)]


def inline(fn):
    """A helper compiled into the kernels that call it."""
    return numba.njit(inline="always", fastmath=FASTMATH, error_model="numpy")(fn)


# ----------------------------------------------------------------------------- float helpers

@intrinsic
def _bits_to_f32(typingctx, x):
    """The float32 whose bit pattern is the int32 `x`."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


_LOG2E = f32(1.4426950408889634)
_LN2_HI = f32(0.693359375)
_LN2_LO = f32(-2.12194440e-4)
_E5, _E4, _E3 = f32(1.9875691500e-4), f32(1.3981999507e-3), f32(8.3334519073e-3)
_E2, _E1, _E0 = f32(4.1665795894e-2), f32(1.6666665459e-1), f32(5.0000001201e-1)
EXP_LO = f32(-87.0)
_ONE, _ZERO, _HALF = f32(1.0), f32(0.0), f32(0.5)


@inline
def exp_f32(x):
    """exp of a float32 in [-87, 0] (callers clamp at EXP_LO) to about 1 ulp (Cephes' expf: 2^n times
    a degree-6 polynomial on [-ln2/2, ln2/2]); branch-free, so loops over it vectorise. The detail
    model's network uses it too."""
    n = np.floor(x * _LOG2E + _HALF)
    r = x - n * _LN2_HI - n * _LN2_LO
    z = r * r
    p = (((((_E5 * r + _E4) * r + _E3) * r + _E2) * r + _E1) * r + _E0) * z + r + _ONE
    return p * _bits_to_f32((np.int32(n) + np.int32(127)) << np.int32(23))



ALPHA_MAX = f32(0.99)
ALPHA_MIN = f32(1.0 / 255.0)
T_MIN = f32(1e-4)
#: Columns of the packed table (`rasterize.pack`).
MX, MY, CA, CB, CC, OP, CR, CG, CBL, DEPTH = range(10)


@inline
def _tile_origin(t, tiles_x, ts):
    return f32((t % tiles_x) * ts), f32((t // tiles_x) * ts)


# ----------------------------------------------------------------------------- projection

_TWO, _FOUR, _THREE = f32(2.0), f32(4.0), f32(3.0)
_NEAR = f32(NEAR_PLANE)
_LS_LO, _LS_HI = f32(LOG_SCALE_RANGE[0]), f32(LOG_SCALE_RANGE[1])
_OL_LO, _OL_HI = f32(OPACITY_LOGIT_RANGE[0]), f32(OPACITY_LOGIT_RANGE[1])
_F3_LO, _F3_HI = f32(FILTER_3D_RANGE[0]), f32(FILTER_3D_RANGE[1])
_DIL, _MIP = f32(DILATION), f32(MIP_2D_VARIANCE)
_RATIO_FLOOR = f32(MIP_2D_RATIO_FLOOR)
_AXIS = f32(MAX_AXIS_PX)
_C0, _C1 = f32(SH_C0), f32(SH_C1)
_C20, _C21, _C22, _C23, _C24 = (f32(c) for c in SH_C2)
_C30, _C31, _C32, _C33, _C34, _C35, _C36 = (f32(c) for c in SH_C3)
#: `flags` bits of the projection kernels: the 3D filter (Mip-Splatting; opacity compensated), the
#: 3D dilation (`matched`), the 2D Mip filter in place of the classic dilation.
FILTER_3D, DILATION_3D, MIP_2D = 1, 2, 4
#: Layout of the float64 camera vector (`compiled.camera_vector`).
CAM_SIZE = 24


@inline
def _clampf(x, lo, hi):
    return min(max(x, lo), hi)


@inline
def _sh_basis(x, y, z, degree, b):
    """The non-constant real SH basis functions (`sh.sh_basis` order) at unit (x, y, z) into b."""
    b[0], b[1], b[2] = -_C1 * y, _C1 * z, -_C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b[3], b[4], b[5] = _C20 * x * y, _C21 * y * z, _C22 * (_TWO * zz - xx - yy)
        b[6], b[7] = _C23 * x * z, _C24 * (xx - yy)
        if degree >= 3:
            b[8] = _C30 * y * (_THREE * xx - yy)
            b[9] = _C31 * x * y * z
            b[10] = _C32 * y * (_FOUR * zz - xx - yy)
            b[11] = _C33 * z * (_TWO * zz - _THREE * xx - _THREE * yy)
            b[12] = _C34 * x * (_FOUR * zz - xx - yy)
            b[13] = _C35 * z * (xx - yy)
            b[14] = _C36 * x * (xx - _THREE * yy)


@inline
def _sh_basis_grad(x, y, z, degree, gb, gx, gy, gz):
    """Adds sum_k gb[k] d b_k / d(x, y, z) for the basis of `_sh_basis`; returns the three sums."""
    gx += -_C1 * gb[2]
    gy += -_C1 * gb[0]
    gz += _C1 * gb[1]
    if degree >= 2:
        gx += _C20 * y * gb[3] - _TWO * _C22 * x * gb[5] + _C23 * z * gb[6] + _TWO * _C24 * x * gb[7]
        gy += _C20 * x * gb[3] + _C21 * z * gb[4] - _TWO * _C22 * y * gb[5] - _TWO * _C24 * y * gb[7]
        gz += _C21 * y * gb[4] + _FOUR * _C22 * z * gb[5] + _C23 * x * gb[6]
        if degree >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (f32(6.0) * _C30 * x * y * gb[8] + _C31 * y * z * gb[9] - _TWO * _C32 * x * y * gb[10]
                   - f32(6.0) * _C33 * x * z * gb[11] + _C34 * (_FOUR * zz - _THREE * xx - yy) * gb[12]
                   + _TWO * _C35 * x * z * gb[13] + _THREE * _C36 * (xx - yy) * gb[14])
            gy += (_THREE * _C30 * (xx - yy) * gb[8] + _C31 * x * z * gb[9]
                   + _C32 * (_FOUR * zz - xx - _THREE * yy) * gb[10] - f32(6.0) * _C33 * y * z * gb[11]
                   - _TWO * _C34 * x * y * gb[12] - _TWO * _C35 * y * z * gb[13] - f32(6.0) * _C36 * x * y * gb[14])
            gz += (_C31 * x * y * gb[9] + f32(8.0) * _C32 * y * z * gb[10]
                   + _C33 * (f32(6.0) * zz - _THREE * xx - _THREE * yy) * gb[11] + f32(8.0) * _C34 * x * z * gb[12]
                   + _C35 * (xx - yy) * gb[13])
    return gx, gy, gz


@inline
def _camera_point(means, i, cam):
    """Camera-space position (float32 x, y, z) of Gaussian i, from its offset to the camera centre
    taken in float64, and that offset (float64)."""
    rx, ry, rz = means[i, 0] - cam[9], means[i, 1] - cam[10], means[i, 2] - cam[11]
    x = f32(cam[0] * rx + cam[1] * ry + cam[2] * rz)
    y = f32(cam[3] * rx + cam[4] * ry + cam[5] * rz)
    z = f32(cam[6] * rx + cam[7] * ry + cam[8] * rz)
    return x, y, z, rx, ry, rz


@inline
def _unit_quat(quats, i):
    """Quaternion i normalised (zero or non-finite norm: the identity), its norm and whether it was used."""
    q0, q1, q2, q3 = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
    norm = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    if np.isfinite(norm) and norm > f32(1e-12):
        return q0 / norm, q1 / norm, q2 / norm, q3 / norm, norm, True
    return _ONE, _ZERO, _ZERO, _ZERO, _ONE, False


@inline
def _rotation(w, x, y, z):
    """The rotation matrix of a unit quaternion, row by row (`quaternions.to_rotmat`)."""
    return (_ONE - _TWO * (y * y + z * z), _TWO * (x * y - w * z), _TWO * (x * z + w * y),
            _TWO * (x * y + w * z), _ONE - _TWO * (x * x + z * z), _TWO * (y * z - w * x),
            _TWO * (x * z - w * y), _TWO * (y * z + w * x), _ONE - _TWO * (x * x + y * y))


@inline
def _logaddexp(a, b):
    m = max(a, b)
    return m + np.log1p(np.exp(-abs(a - b)))


@kernel
def project_forward(means, log_scales, quats, logits, sh_dc, sh_rest, sizes, cam, degree, flags, width, height,
                    lo, hi, table, foot, radii, visible):
    """`projection.project` of Gaussians lo..hi-1 into rows of the packed table (N+1, 11) (zeros but
    the last column for Gaussians not drawn), the footprint (N, 4) float64 (k, Sxx, Sxy, Syy),
    radii (N,) int32 and visible (N,) bool. means (N,3) float64; the other fields float32; sizes
    (N,) float32, the 3D filter or dilation of `flags` (empty without one); cam: `CAM_SIZE` float64."""
    fx, fy, cx, cy = f32(cam[12]), f32(cam[13]), f32(cam[14]), f32(cam[15])
    lo_x, hi_x, lo_y, hi_y = f32(cam[16]), f32(cam[17]), f32(cam[18]), f32(cam[19])
    aw, ax, ay, az = f32(cam[20]), f32(cam[21]), f32(cam[22]), f32(cam[23])
    fxfy = f32(cam[12] * cam[13])
    k_rest = sh_rest.shape[1]
    kb = min((degree + 1) * (degree + 1) - 1, k_rest)
    basis = np.zeros(15, np.float32)
    big = float(4 * max(width, height))
    for i in range(lo, hi):
        for c in range(10):
            table[i, c] = _ZERO
        table[i, 10] = _ONE
        foot[i, 0] = foot[i, 1] = foot[i, 2] = foot[i, 3] = 0.0
        radii[i] = 0
        visible[i] = False
        x, y, z, rx, ry, rz = _camera_point(means, i, cam)
        if not (np.isfinite(z) and z > _NEAR):
            continue
        iz = _ONE / z
        u, v = x * iz, y * iz
        j00, j11 = fx * iz, fy * iz
        j02 = -fx * _clampf(u, lo_x, hi_x) * iz
        j12 = -fy * _clampf(v, lo_y, hi_y) * iz
        bw, bx, by, bz, _, _ = _unit_quat(quats, i)
        w = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        opac = _ONE / (_ONE + np.exp(-_clampf(logits[i], _OL_LO, _OL_HI)))
        l0 = _clampf(log_scales[i, 0], _LS_LO, _LS_HI)
        l1 = _clampf(log_scales[i, 1], _LS_LO, _LS_HI)
        l2 = _clampf(log_scales[i, 2], _LS_LO, _LS_HI)
        f = _ZERO
        if flags & (FILTER_3D | DILATION_3D):
            f = sizes[i]
            f = _clampf(f if np.isfinite(f) else _ZERO, _F3_LO, _F3_HI)
            lf = _TWO * np.log(f)
            e0, e1, e2 = (_HALF * _logaddexp(_TWO * l0, lf), _HALF * _logaddexp(_TWO * l1, lf),
                          _HALF * _logaddexp(_TWO * l2, lf))
            if flags & FILTER_3D:
                opac = opac * np.exp((l0 - e0) + (l1 - e1) + (l2 - e2))
            s0, s1, s2 = np.exp(e0), np.exp(e1), np.exp(e2)
        else:
            s0, s1, s2 = np.exp(l0), np.exp(l1), np.exp(l2)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(w, qx, qy, qz)
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        a0 = _clampf(j00 * m00 + j02 * m20, -_AXIS, _AXIS)
        a1 = _clampf(j00 * m01 + j02 * m21, -_AXIS, _AXIS)
        a2 = _clampf(j00 * m02 + j02 * m22, -_AXIS, _AXIS)
        b0 = _clampf(j11 * m10 + j12 * m20, -_AXIS, _AXIS)
        b1 = _clampf(j11 * m11 + j12 * m21, -_AXIS, _AXIS)
        b2 = _clampf(j11 * m12 + j12 * m22, -_AXIS, _AXIS)
        if flags & MIP_2D:
            d = _MIP
        elif flags & DILATION_3D:
            d = max(_DIL - f * f * fxfy * (iz * iz), _ZERO)
        else:
            d = _DIL
        aa = a0 * a0 + a1 * a1 + a2 * a2
        bb = b0 * b0 + b1 * b1 + b2 * b2
        sxy = a0 * b0 + a1 * b1 + a2 * b2
        c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        cc = c0 * c0 + c1 * c1 + c2 * c2
        det = cc + d * (aa + bb) + d * d
        sxx, syy = aa + d, bb + d
        inv = _ONE / det
        if flags & MIP_2D:
            opac = opac * np.sqrt(max(cc * inv, _RATIO_FLOOR))
        mx, my = fx * u + cx, fy * v + cy
        if not opac >= ALPHA_MIN:
            continue
        kk = math.sqrt(max(2.0 * math.log(float(opac) * 255.0), 0.0)) * (1.0 + FOOTPRINT_MARGIN) + 1e-4
        ex, ey = kk * math.sqrt(float(sxx)), kk * math.sqrt(float(syy))
        mxd, myd = float(mx), float(my)
        if not (mxd + ex >= 0.5 and mxd - ex <= width - 0.5 and myd + ey >= 0.5 and myd - ey <= height - 0.5):
            continue
        # colour: SH along the direction from the camera centre (float64, then float32)
        r0, r1, r2 = sh_dc[i, 0] * _C0 + _HALF, sh_dc[i, 1] * _C0 + _HALF, sh_dc[i, 2] * _C0 + _HALF
        if kb > 0 and degree > 0:
            n2 = rx * rx + ry * ry + rz * rz
            dx = dy = dz = _ZERO
            if n2 > 1e-300:
                nr = math.sqrt(n2)
                dx, dy, dz = f32(rx / nr), f32(ry / nr), f32(rz / nr)
            _sh_basis(dx, dy, dz, degree, basis)
            for k in range(kb):
                r0 += basis[k] * sh_rest[i, k, 0]
                r1 += basis[k] * sh_rest[i, k, 1]
                r2 += basis[k] * sh_rest[i, k, 2]
        table[i, MX], table[i, MY] = mx, my
        table[i, CA], table[i, CB], table[i, CC] = syy * inv, -sxy * inv, sxx * inv
        table[i, OP] = opac
        table[i, CR], table[i, CG], table[i, CBL] = max(r0, _ZERO), max(r1, _ZERO), max(r2, _ZERO)
        table[i, DEPTH] = z
        foot[i, 0], foot[i, 1], foot[i, 2], foot[i, 3] = kk, float(sxx), float(sxy), float(syy)
        radii[i] = np.int32(math.ceil(min(max(ex, ey), big)))
        visible[i] = True


@kernel
def project_backward(means, log_scales, quats, logits, sh_dc, sh_rest, sizes, cam, degree, flags, lo, hi,
                     table, grad_table, g_means, g_scales, g_quats, g_logits, g_dc, g_rest):
    """Gradients of the loss with respect to the raw parameters of Gaussians lo..hi-1, from its
    gradient `grad_table` (N+1, 11) with respect to the rows `project_forward` wrote into `table`
    (the same arguments): the reverse of every step of the projection, with torch's rules at clamps
    (no gradient past an active clamp) and none for Gaussians not drawn. g_means (N, 3) float64,
    the others float32, all written (zeros where nothing flows)."""
    fx, fy = f32(cam[12]), f32(cam[13])
    lo_x, hi_x, lo_y, hi_y = f32(cam[16]), f32(cam[17]), f32(cam[18]), f32(cam[19])
    aw, ax, ay, az = f32(cam[20]), f32(cam[21]), f32(cam[22]), f32(cam[23])
    fxfy = f32(cam[12] * cam[13])
    k_rest = sh_rest.shape[1]
    kb = min((degree + 1) * (degree + 1) - 1, k_rest)
    basis = np.zeros(15, np.float32)
    gbasis = np.zeros(15, np.float32)
    for i in range(lo, hi):
        g_means[i, 0] = g_means[i, 1] = g_means[i, 2] = 0.0
        g_scales[i, 0] = g_scales[i, 1] = g_scales[i, 2] = _ZERO
        g_quats[i, 0] = g_quats[i, 1] = g_quats[i, 2] = g_quats[i, 3] = _ZERO
        g_logits[i] = _ZERO
        g_dc[i, 0] = g_dc[i, 1] = g_dc[i, 2] = _ZERO
        for k in range(k_rest):
            g_rest[i, k, 0] = g_rest[i, k, 1] = g_rest[i, k, 2] = _ZERO
        if table[i, OP] == _ZERO:  # not drawn: the outputs are constants
            continue
        gmx, gmy = grad_table[i, MX], grad_table[i, MY]
        g_a, g_b, g_c = grad_table[i, CA], grad_table[i, CB], grad_table[i, CC]
        g_op = grad_table[i, OP]
        g_r, g_g, g_bl = grad_table[i, CR], grad_table[i, CG], grad_table[i, CBL]
        g_z = grad_table[i, DEPTH]
        # ---- forward again (as project_forward; the Gaussian is drawn, so it is in front)
        x, y, z, rx, ry, rz = _camera_point(means, i, cam)
        iz = _ONE / z
        u, v = x * iz, y * iz
        uc, vc = _clampf(u, lo_x, hi_x), _clampf(v, lo_y, hi_y)
        j00, j11 = fx * iz, fy * iz
        j02, j12 = -fx * uc * iz, -fy * vc * iz
        bw, bx, by, bz, qnorm, q_used = _unit_quat(quats, i)
        w = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        logit = logits[i]
        opac0 = _ONE / (_ONE + np.exp(-_clampf(logit, _OL_LO, _OL_HI)))
        ls0, ls1, ls2 = log_scales[i, 0], log_scales[i, 1], log_scales[i, 2]
        l0, l1, l2 = _clampf(ls0, _LS_LO, _LS_HI), _clampf(ls1, _LS_LO, _LS_HI), _clampf(ls2, _LS_LO, _LS_HI)
        in0 = _ONE if (ls0 >= _LS_LO and ls0 <= _LS_HI) else _ZERO
        in1 = _ONE if (ls1 >= _LS_LO and ls1 <= _LS_HI) else _ZERO
        in2 = _ONE if (ls2 >= _LS_LO and ls2 <= _LS_HI) else _ZERO
        f = _ZERO
        comp = _ONE
        if flags & (FILTER_3D | DILATION_3D):
            f = sizes[i]
            f = _clampf(f if np.isfinite(f) else _ZERO, _F3_LO, _F3_HI)
            lf = _TWO * np.log(f)
            e0, e1, e2 = (_HALF * _logaddexp(_TWO * l0, lf), _HALF * _logaddexp(_TWO * l1, lf),
                          _HALF * _logaddexp(_TWO * l2, lf))
            s0, s1, s2 = np.exp(e0), np.exp(e1), np.exp(e2)
            # d log s_eff / d log s = s² / (s² + f²)
            gain0, gain1, gain2 = np.exp(_TWO * (l0 - e0)), np.exp(_TWO * (l1 - e1)), np.exp(_TWO * (l2 - e2))
            if flags & FILTER_3D:
                comp = np.exp((l0 - e0) + (l1 - e1) + (l2 - e2))
        else:
            s0, s1, s2 = np.exp(l0), np.exp(l1), np.exp(l2)
            gain0 = gain1 = gain2 = _ONE
        opac1 = opac0 * comp
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(w, qx, qy, qz)
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        pa0, pa1, pa2 = j00 * m00 + j02 * m20, j00 * m01 + j02 * m21, j00 * m02 + j02 * m22
        pb0, pb1, pb2 = j11 * m10 + j12 * m20, j11 * m11 + j12 * m21, j11 * m12 + j12 * m22
        a0, a1, a2 = _clampf(pa0, -_AXIS, _AXIS), _clampf(pa1, -_AXIS, _AXIS), _clampf(pa2, -_AXIS, _AXIS)
        b0, b1, b2 = _clampf(pb0, -_AXIS, _AXIS), _clampf(pb1, -_AXIS, _AXIS), _clampf(pb2, -_AXIS, _AXIS)
        d_free = _ZERO  # d (2D dilation) / d z where the 3D dilation leaves some of it
        if flags & MIP_2D:
            d = _MIP
        elif flags & DILATION_3D:
            rest_2d = _DIL - f * f * fxfy * (iz * iz)
            d = max(rest_2d, _ZERO)
            if rest_2d > _ZERO:
                d_free = _TWO * f * f * fxfy * iz * iz * iz
        else:
            d = _DIL
        aa = a0 * a0 + a1 * a1 + a2 * a2
        bb = b0 * b0 + b1 * b1 + b2 * b2
        sxy = a0 * b0 + a1 * b1 + a2 * b2
        c0, c1, c2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        cc = c0 * c0 + c1 * c1 + c2 * c2
        det = cc + d * (aa + bb) + d * d
        sxx, syy = aa + d, bb + d
        inv = _ONE / det
        # ---- backward
        g_cc = g_det = _ZERO
        g_opac1 = g_op
        if flags & MIP_2D:
            ratio = cc * inv
            root = np.sqrt(max(ratio, _RATIO_FLOOR))
            g_opac1 = g_op * root
            if ratio > _RATIO_FLOOR:
                g_ratio = g_op * opac1 * _HALF / root
                g_cc += g_ratio * inv
                g_det -= g_ratio * ratio * inv
        g_ls0 = g_ls1 = g_ls2 = _ZERO
        if flags & FILTER_3D:  # opacity x prod s / s_eff
            t = g_opac1 * opac1
            g_ls0 += t * (_ONE - gain0) * in0
            g_ls1 += t * (_ONE - gain1) * in1
            g_ls2 += t * (_ONE - gain2) * in2
        g_opac0 = g_opac1 * comp
        if logit >= _OL_LO and logit <= _OL_HI:
            g_logits[i] = g_opac0 * opac0 * (_ONE - opac0)
        # conic (syy, -sxy, sxx) / det
        g_syy, g_sxy, g_sxx = g_a * inv, -g_b * inv, g_c * inv
        g_inv = g_a * syy - g_b * sxy + g_c * sxx
        g_det -= g_inv * inv * inv
        g_aa = g_sxx + g_det * d
        g_bb = g_syy + g_det * d
        g_cc += g_det
        g_d = g_sxx + g_syy + g_det * (aa + bb + _TWO * d)
        gc0, gc1, gc2 = _TWO * c0 * g_cc, _TWO * c1 * g_cc, _TWO * c2 * g_cc
        # c = a x b: d/da = b x g_c, d/db = g_c x a
        ga0 = _TWO * a0 * g_aa + b0 * g_sxy + (b1 * gc2 - b2 * gc1)
        ga1 = _TWO * a1 * g_aa + b1 * g_sxy + (b2 * gc0 - b0 * gc2)
        ga2 = _TWO * a2 * g_aa + b2 * g_sxy + (b0 * gc1 - b1 * gc0)
        gb0 = _TWO * b0 * g_bb + a0 * g_sxy + (gc1 * a2 - gc2 * a1)
        gb1 = _TWO * b1 * g_bb + a1 * g_sxy + (gc2 * a0 - gc0 * a2)
        gb2 = _TWO * b2 * g_bb + a2 * g_sxy + (gc0 * a1 - gc1 * a0)
        ga0 = ga0 if abs(pa0) <= _AXIS else _ZERO
        ga1 = ga1 if abs(pa1) <= _AXIS else _ZERO
        ga2 = ga2 if abs(pa2) <= _AXIS else _ZERO
        gb0 = gb0 if abs(pb0) <= _AXIS else _ZERO
        gb1 = gb1 if abs(pb1) <= _AXIS else _ZERO
        gb2 = gb2 if abs(pb2) <= _AXIS else _ZERO
        g_j00 = ga0 * m00 + ga1 * m01 + ga2 * m02
        g_j02 = ga0 * m20 + ga1 * m21 + ga2 * m22
        g_j11 = gb0 * m10 + gb1 * m11 + gb2 * m12
        g_j12 = gb0 * m20 + gb1 * m21 + gb2 * m22
        gm00, gm01, gm02 = ga0 * j00, ga1 * j00, ga2 * j00
        gm10, gm11, gm12 = gb0 * j11, gb1 * j11, gb2 * j11
        gm20, gm21, gm22 = ga0 * j02 + gb0 * j12, ga1 * j02 + gb1 * j12, ga2 * j02 + gb2 * j12
        # M = R(q) diag(s)
        gs0 = gm00 * r00 + gm10 * r10 + gm20 * r20
        gs1 = gm01 * r01 + gm11 * r11 + gm21 * r21
        gs2 = gm02 * r02 + gm12 * r12 + gm22 * r22
        g_ls0 += gs0 * s0 * gain0 * in0
        g_ls1 += gs1 * s1 * gain1 * in1
        g_ls2 += gs2 * s2 * gain2 * in2
        g_scales[i, 0], g_scales[i, 1], g_scales[i, 2] = g_ls0, g_ls1, g_ls2
        gr00, gr01, gr02 = gm00 * s0, gm01 * s1, gm02 * s2
        gr10, gr11, gr12 = gm10 * s0, gm11 * s1, gm12 * s2
        gr20, gr21, gr22 = gm20 * s0, gm21 * s1, gm22 * s2
        gw = _TWO * (-qz * gr01 + qy * gr02 + qz * gr10 - qx * gr12 - qy * gr20 + qx * gr21)
        gx = _TWO * (qy * gr01 + qz * gr02 + qy * gr10 - _TWO * qx * gr11 - w * gr12 + qz * gr20 + w * gr21
                     - _TWO * qx * gr22)
        gy = _TWO * (-_TWO * qy * gr00 + qx * gr01 + w * gr02 + qx * gr10 + qz * gr12 - w * gr20 + qz * gr21
                     - _TWO * qy * gr22)
        gz = _TWO * (-_TWO * qz * gr00 - w * gr01 + qx * gr02 + w * gr10 - _TWO * qz * gr11 + qy * gr12 + qx * gr20
                     + qy * gr21)
        if q_used:  # q_camera (x) q / |q|
            gbw = aw * gw + ax * gx + ay * gy + az * gz
            gbx = -ax * gw + aw * gx + az * gy - ay * gz
            gby = -ay * gw - az * gx + aw * gy + ax * gz
            gbz = -az * gw + ay * gx - ax * gy + aw * gz
            dot = bw * gbw + bx * gbx + by * gby + bz * gbz
            g_quats[i, 0] = (gbw - bw * dot) / qnorm
            g_quats[i, 1] = (gbx - bx * dot) / qnorm
            g_quats[i, 2] = (gby - by * dot) / qnorm
            g_quats[i, 3] = (gbz - bz * dot) / qnorm
        # Jacobian and centre -> camera-space position
        g_uc = -fx * iz * g_j02
        g_vc = -fy * iz * g_j12
        g_iz = fx * g_j00 + fy * g_j11 - fx * uc * g_j02 - fy * vc * g_j12
        g_u = fx * gmx + (g_uc if (u >= lo_x and u <= hi_x) else _ZERO)
        g_v = fy * gmy + (g_vc if (v >= lo_y and v <= hi_y) else _ZERO)
        g_iz += g_u * x + g_v * y
        g_z += -g_iz * iz * iz + g_d * d_free
        g_x, g_y = g_u * iz, g_v * iz
        # colour: the DC term and SH along the direction from the camera centre; no gradient where clamped
        r0, r1, r2 = sh_dc[i, 0] * _C0 + _HALF, sh_dc[i, 1] * _C0 + _HALF, sh_dc[i, 2] * _C0 + _HALF
        use_sh = kb > 0 and degree > 0
        nr = 0.0
        if use_sh:
            dx = dy = dz = _ZERO
            n2 = rx * rx + ry * ry + rz * rz
            if n2 > 1e-300:
                nr = math.sqrt(n2)
                dx, dy, dz = f32(rx / nr), f32(ry / nr), f32(rz / nr)
            _sh_basis(dx, dy, dz, degree, basis)
            for k in range(kb):
                r0 += basis[k] * sh_rest[i, k, 0]
                r1 += basis[k] * sh_rest[i, k, 1]
                r2 += basis[k] * sh_rest[i, k, 2]
        g_r = g_r if r0 >= _ZERO else _ZERO
        g_g = g_g if r1 >= _ZERO else _ZERO
        g_bl = g_bl if r2 >= _ZERO else _ZERO
        g_dc[i, 0], g_dc[i, 1], g_dc[i, 2] = _C0 * g_r, _C0 * g_g, _C0 * g_bl
        grx = float(cam[0] * g_x + cam[3] * g_y + cam[6] * g_z)
        gry = float(cam[1] * g_x + cam[4] * g_y + cam[7] * g_z)
        grz = float(cam[2] * g_x + cam[5] * g_y + cam[8] * g_z)
        if use_sh:
            for k in range(kb):
                g_rest[i, k, 0], g_rest[i, k, 1], g_rest[i, k, 2] = basis[k] * g_r, basis[k] * g_g, basis[k] * g_bl
                gbasis[k] = sh_rest[i, k, 0] * g_r + sh_rest[i, k, 1] * g_g + sh_rest[i, k, 2] * g_bl
            if nr > 0.0:  # direction = offset / |offset|
                gdx, gdy, gdz = _sh_basis_grad(dx, dy, dz, degree, gbasis, _ZERO, _ZERO, _ZERO)
                ux, uy, uz = rx / nr, ry / nr, rz / nr
                radial = float(gdx) * ux + float(gdy) * uy + float(gdz) * uz
                grx += (float(gdx) - ux * radial) / nr
                gry += (float(gdy) - uy * radial) / nr
                grz += (float(gdz) - uz * radial) / nr
        g_means[i, 0], g_means[i, 1], g_means[i, 2] = grx, gry, grz


# ----------------------------------------------------------------------------- tile binning

#: Columns of the per-footprint constants of `gather_footprints`.
GEO = 9


@kernel
def gather_footprints(table, foot, order, lo, hi, geo):
    """geo[j] (`_GEO` float64) = what the tile tests need of the footprint of Gaussian order[j], j in
    lo..hi-1: centre x, y, half-height ey, and of the ellipse d^T S^-1 d <= k² (S = (Sxx, Sxy, Syy)):
    the slope Sxy / Syy of its centre line, det S / Syy, the height of its rightmost point
    k Sxy / sqrt(Sxx), k², 1 / Syy, and the half-width k sqrt(Sxx). One tight gather: the passes
    that follow read memory in order."""
    for j in range(lo, hi):
        i = order[j]
        k, sxx, sxy, syy = foot[i, 0], foot[i, 1], foot[i, 2], foot[i, 3]
        slope = sxy / syy
        geo[j, 0], geo[j, 1], geo[j, 2] = float(table[i, MX]), float(table[i, MY]), k * math.sqrt(syy)
        geo[j, 3], geo[j, 4] = slope, max(sxx - sxy * slope, 0.0)
        geo[j, 5], geo[j, 6], geo[j, 7] = k * sxy / math.sqrt(sxx), k * k, 1.0 / syy
        geo[j, 8] = k * math.sqrt(sxx)


@inline
def _tile_of(x, ts):
    """x // ts for a whole number x >= 0 (a float division: integer division is many times slower)."""
    return int((x + 0.5) / ts)


@inline
def _tile_rows(my, ey, ts, height):
    """First and last tile row whose band of pixel centres the footprint's box reaches (last < first: none)."""
    y0 = min(max(math.ceil(my - ey - 0.5), 0.0), height - 1.0)
    y1 = min(max(math.floor(my + ey - 0.5), -1.0), height - 1.0)
    if not y1 >= y0:
        return 0, -1
    return _tile_of(y0, ts), _tile_of(y1, ts)


@inline
def _row_span(geo, j, ty, ts, width, height, exact):
    """First and last tile column of tile row ty the footprint ellipse of geo[j] reaches (last <
    first: none), as `tiles._pairs` finds them (float64): for fixed dy the ellipse spans dx =
    slope dy +- sqrt(det S / Syy (k² - dy² / Syy)); its right end peaks at the rightmost point's dy."""
    mx, my, ey = geo[j, 0], geo[j, 1], geo[j, 2]
    band_lo = max(ty * ts + (0.5 - my), -ey)
    band_hi = min(min(float(ty * ts + ts - 1), height - 1.0) + (0.5 - my), ey)
    if exact:
        slope, det_ratio, peak, kk, inv_syy = geo[j, 3], geo[j, 4], geo[j, 5], geo[j, 6], geo[j, 7]
        dyr = min(max(peak, band_lo), band_hi)
        dyl = min(max(-peak, band_lo), band_hi)
        x_hi = mx + slope * dyr + math.sqrt(det_ratio * max(kk - dyr * dyr * inv_syy, 0.0)) + 1e-3
        x_lo = mx + slope * dyl - math.sqrt(det_ratio * max(kk - dyl * dyl * inv_syy, 0.0)) - 1e-3
    else:
        x_hi, x_lo = mx + geo[j, 8], mx - geo[j, 8]
    x0 = min(max(math.ceil(x_lo - 0.5), 0.0), width - 1.0)
    x1 = min(max(math.floor(x_hi - 0.5), -1.0), width - 1.0)
    if not (x1 >= x0 and band_hi >= band_lo):
        return 0, -1
    return _tile_of(x0, ts), _tile_of(x1, ts)


@kernel
def bin_count(geo, lo, hi, ts, tiles_x, width, height, exact, hist):
    """hist[tile] += the pairs of footprints geo[lo:hi] (`gather_footprints`) with the tiles they reach."""
    for j in range(lo, hi):
        ty0, ty1 = _tile_rows(geo[j, 1], geo[j, 2], ts, height)
        for ty in range(ty0, ty1 + 1):
            tx0, tx1 = _row_span(geo, j, ty, ts, width, height, exact)
            for tx in range(tx0, tx1 + 1):
                hist[ty * tiles_x + tx] += 1


@kernel
def bin_fill(geo, order, lo, hi, ts, tiles_x, width, height, exact, cursor, ids):
    """The pairs of `bin_count`, order[j] written at cursor[tile] (advanced): footprints taken in
    the order of `order` (front to back), each tile's list keeps it."""
    for j in range(lo, hi):
        i = order[j]
        ty0, ty1 = _tile_rows(geo[j, 1], geo[j, 2], ts, height)
        for ty in range(ty0, ty1 + 1):
            tx0, tx1 = _row_span(geo, j, ty, ts, width, height, exact)
            for tx in range(tx0, tx1 + 1):
                t = ty * tiles_x + tx
                ids[cursor[t]] = i
                cursor[t] += 1


@kernel
def radix_order(keys, order):
    """`order` (int64) stably sorted by `keys` (uint32, parallel to order; both overwritten): LSD
    radix sort in three passes of 11 bits. The bits of positive float32 depths sort as the depths."""
    n = keys.shape[0]
    k2 = np.empty_like(keys)
    o2 = np.empty_like(order)
    count = np.empty(2049, np.int64)
    for shift in (0, 11, 22):
        count[:] = 0
        for i in range(n):
            count[((keys[i] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            dst = count[(keys[i] >> shift) & 2047]
            count[(keys[i] >> shift) & 2047] = dst + 1
            k2[dst] = keys[i]
            o2[dst] = order[i]
        keys[:] = k2
        order[:] = o2


# ----------------------------------------------------------------------------- compositing
#: Values per pair of `composite_backward`: d loss / d (mx, my, conic a, b, c, log opacity, r, g, b, depth).
NGRAD = 10


@inline
def _pixel_grid(ts):
    """Pixel centres of a tile relative to its corner, row by row: x (P,), y (P,) float32."""
    p_count = ts * ts
    px = np.empty(p_count, np.float32)
    py = np.empty(p_count, np.float32)
    for p in range(p_count):
        px[p] = f32(p % ts) + _HALF
        py[p] = f32(p // ts) + _HALF
    return px, py


@inline
def _alpha(px, py, mx, my, ha, nb, hc, lo):
    """alpha at a pixel: min(0.99, exp(log o - q/2)), 0 below 1/255 (and for non-finite exponents)."""
    dx = px - mx
    dy = py - my
    e = lo + dx * (ha * dx + nb * dy) + hc * dy * dy
    e = e if e > EXP_LO else EXP_LO
    e = e if e < _ZERO else _ZERO
    alpha = min(exp_f32(e), ALPHA_MAX)
    return (alpha if alpha >= ALPHA_MIN else _ZERO), dx, dy


@inline
def _gaussian(table, g, x0, y0):
    """A table row's centre relative to the tile corner, the conic's quadratic-form coefficients
    (-a/2, -b, -c/2) and log opacity."""
    mx, my = table[g, MX] - x0, table[g, MY] - y0
    ha, nb, hc = -_HALF * table[g, CA], -table[g, CB], -_HALF * table[g, CC]
    lo = np.log(max(table[g, OP], f32(1e-30)))
    return mx, my, ha, nb, hc, lo


@kernel
def composite_forward(table, ids, offsets, t_lo, t_hi, tiles_x, ts, acc):
    """Front-to-back compositing of tiles t_lo..t_hi-1: acc[t] (5, P) = sum of w [r, g, b, depth, 1]
    over each pixel's depth-sorted list (`ids[offsets[t]:offsets[t + 1]]`, rows of `table` (N+1, 11)),
    w = alpha T; a pixel stops before the Gaussian that would take T below 1e-4, a tile when all of
    its pixels have. Returns the pixel-Gaussian pairs evaluated."""
    p_count = ts * ts
    px, py = _pixel_grid(ts)
    trans = np.empty(p_count, np.float32)
    live = np.empty(p_count, np.float32)
    # five 1-D rows: the compiler vectorises loops over 1-D arrays, not over rows of a 2-D one
    o_r, o_g, o_b = np.empty(p_count, np.float32), np.empty(p_count, np.float32), np.empty(p_count, np.float32)
    o_d, o_a = np.empty(p_count, np.float32), np.empty(p_count, np.float32)
    evals = 0
    for t in range(t_lo, t_hi):
        x0, y0 = _tile_origin(t, tiles_x, ts)
        trans[:] = _ONE
        live[:] = _ONE
        o_r[:] = _ZERO
        o_g[:] = _ZERO
        o_b[:] = _ZERO
        o_d[:] = _ZERO
        o_a[:] = _ZERO
        start, end = offsets[t], offsets[t + 1]
        last = end
        for k in range(start, end):
            g = ids[k]
            mx, my, ha, nb, hc, lo = _gaussian(table, g, x0, y0)
            cr, cg, cb, cd = table[g, CR], table[g, CG], table[g, CBL], table[g, DEPTH]
            alive = _ZERO
            for p in range(p_count):
                alpha, _, _ = _alpha(px[p], py[p], mx, my, ha, nb, hc, lo)
                tr = trans[p]
                after = tr - tr * alpha
                keep = live[p] if after >= T_MIN else _ZERO
                w = keep * alpha * tr
                o_r[p] += w * cr
                o_g[p] += w * cg
                o_b[p] += w * cb
                o_d[p] += w * cd
                o_a[p] += w
                alive += keep
                trans[p] = after if keep > _ZERO else tr
                live[p] = keep
            if alive == _ZERO:
                last = k + 1
                break
        evals += (last - start) * p_count
        acc[t, 0] = o_r
        acc[t, 1] = o_g
        acc[t, 2] = o_b
        acc[t, 3] = o_d
        acc[t, 4] = o_a
    return evals


@kernel
def composite_backward(table, ids, offsets, t_lo, t_hi, tiles_x, ts, acc, g_acc, pair_grads):
    """The gradient of `composite_forward` for tiles t_lo..t_hi-1: from g_acc (tiles, 5, P), the
    gradient with respect to its output acc, pair_grads[k] (NGRAD) of each pair k = d loss / d (mx,
    my, conic a, b, c, log opacity, r, g, b, depth) of that pair's Gaussian (rows past a tile's stop
    are left as they are: zeros). Recomputes the compositing: with v = feat . g_acc per pixel and
    behind = what the pixel draws after the pair (sum of v w over later pairs, the forward total
    less the running sum), d loss / d alpha = v T - behind / (1 - alpha); times alpha it is the
    derivative by the exponent (0 where alpha is capped, skipped or past the stop)."""
    p_count = ts * ts
    px, py = _pixel_grid(ts)
    trans = np.empty(p_count, np.float32)
    live = np.empty(p_count, np.float32)
    rest = np.empty(p_count, np.float32)
    v_r, v_g, v_b = np.empty(p_count, np.float32), np.empty(p_count, np.float32), np.empty(p_count, np.float32)
    v_d, v_a = np.empty(p_count, np.float32), np.empty(p_count, np.float32)
    for t in range(t_lo, t_hi):
        x0, y0 = _tile_origin(t, tiles_x, ts)
        start, end = offsets[t], offsets[t + 1]
        if end == start:
            continue
        for p in range(p_count):
            v_r[p], v_g[p], v_b[p], v_d[p], v_a[p] = g_acc[t, 0, p], g_acc[t, 1, p], g_acc[t, 2, p], g_acc[t, 3, p], \
                g_acc[t, 4, p]
            rest[p] = (v_r[p] * acc[t, 0, p] + v_g[p] * acc[t, 1, p] + v_b[p] * acc[t, 2, p] + v_d[p] * acc[t, 3, p]
                       + v_a[p] * acc[t, 4, p])
        trans[:] = _ONE
        live[:] = _ONE
        for k in range(start, end):
            g = ids[k]
            mx, my, ha, nb, hc, lo = _gaussian(table, g, x0, y0)
            cr, cg, cb, cd = table[g, CR], table[g, CG], table[g, CBL], table[g, DEPTH]
            s0 = s_x = s_y = s_xx = s_xy = s_yy = _ZERO
            gr = gg = gb = gd = _ZERO
            alive = _ZERO
            for p in range(p_count):
                alpha, dx, dy = _alpha(px[p], py[p], mx, my, ha, nb, hc, lo)
                tr = trans[p]
                after = tr - tr * alpha
                keep = live[p] if after >= T_MIN else _ZERO
                w = keep * alpha * tr
                v = cr * v_r[p] + cg * v_g[p] + cb * v_b[p] + cd * v_d[p] + v_a[p]
                behind = rest[p] - v * w
                rest[p] = behind
                ge = (v * tr - behind / (_ONE - alpha)) * alpha
                ge = ge if (alpha < ALPHA_MAX and w > _ZERO) else _ZERO
                s0 += ge
                s_x += ge * dx
                s_y += ge * dy
                s_xx += ge * dx * dx
                s_xy += ge * dx * dy
                s_yy += ge * dy * dy
                gr += w * v_r[p]
                gg += w * v_g[p]
                gb += w * v_b[p]
                gd += w * v_d[p]
                alive += keep
                trans[p] = after if keep > _ZERO else tr
                live[p] = keep
            a, b, c = table[g, CA], table[g, CB], table[g, CC]
            pair_grads[k, 0] = a * s_x + b * s_y
            pair_grads[k, 1] = b * s_x + c * s_y
            pair_grads[k, 2] = -_HALF * s_xx
            pair_grads[k, 3] = -s_xy
            pair_grads[k, 4] = -_HALF * s_yy
            pair_grads[k, 5] = s0
            pair_grads[k, 6], pair_grads[k, 7], pair_grads[k, 8], pair_grads[k, 9] = gr, gg, gb, gd
            if alive == _ZERO:
                break


@kernel
def pair_grads_to_table(pair_grads, ids, table, c_lo, c_hi, grad_table):
    """grad_table[i, c] = sum of pair_grads[:, c] over the pairs of Gaussian i for the columns c in
    c_lo..c_hi-1 (threads take columns apart: each sum in pair order, as one thread would), the
    log-opacity column turned into d / d opacity (0 for rows of opacity 0); the rest left as they are."""
    for k in range(ids.shape[0]):
        g = ids[k]
        for c in range(c_lo, c_hi):
            grad_table[g, c] += pair_grads[k, c]
    if c_lo <= OP < c_hi:
        for g in range(grad_table.shape[0]):
            o = table[g, OP]
            grad_table[g, OP] = grad_table[g, OP] / o if o > _ZERO else _ZERO


#: Accumulated alpha above which a pixel has a depth (`render`'s rule).
DRAWN = f32(1e-6)


@kernel
def assemble_forward(acc, tiles_x, ts, bg, t_lo, t_hi, image, alpha, depth):
    """Tiles t_lo..t_hi-1 of the compositing's acc (tiles, 5, P) as pixels: image (H, W, 3) = colour +
    (1 - alpha) bg, alpha (H, W), depth (H, W) = the weighted depth / alpha where alpha > 1e-6, else
    0; the padded border tiles' pixels outside the image are dropped."""
    height, width = alpha.shape
    for t in range(t_lo, t_hi):
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        for p in range(ts * ts):
            y, x = y0 + p // ts, x0 + p % ts
            if y >= height or x >= width:
                continue
            a = acc[t, 4, p]
            for c in range(3):
                image[y, x, c] = acc[t, c, p] + (_ONE - a) * bg[c]
            alpha[y, x] = a
            depth[y, x] = acc[t, 3, p] / a if a > DRAWN else _ZERO


@kernel
def assemble_backward(acc, tiles_x, ts, bg, t_lo, t_hi, height, width, g_image, g_alpha, g_depth, g_acc):
    """The gradient of `assemble_forward` with respect to acc, for tiles t_lo..t_hi-1 of g_acc
    (tiles, 5, P), from the gradients of its outputs (g_alpha, g_depth empty: no gradient there;
    0 for the padded pixels)."""
    with_alpha, with_depth = g_alpha.size > 0, g_depth.size > 0
    for t in range(t_lo, t_hi):
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        for p in range(ts * ts):
            y, x = y0 + p // ts, x0 + p % ts
            if y >= height or x >= width:
                for c in range(5):
                    g_acc[t, c, p] = _ZERO
                continue
            ga = g_alpha[y, x] if with_alpha else _ZERO
            for c in range(3):
                g_acc[t, c, p] = g_image[y, x, c]
                ga -= g_image[y, x, c] * bg[c]
            a = acc[t, 4, p]
            g_acc[t, 3, p] = _ZERO
            if with_depth and a > DRAWN:  # depth = acc_3 / a
                gd = g_depth[y, x] / a
                g_acc[t, 3, p] = gd
                ga -= gd * acc[t, 3, p] / a
            g_acc[t, 4, p] = ga


# ----------------------------------------------------------------------------- the Hessian's sweep

#: Values per pair of `gauss_newton_moments`: 15 moments of s = sum_c e_c² by the pixel-offset
#: monomials u^i v^j up to degree 4 (`hessian._POWERS` order), 6 per channel of t_c = e_c w up
#: to degree 2, and w².
NMOM = 34


@kernel
def gauss_newton_moments(table, ids, offsets, t_lo, t_hi, tiles_x, ts, width, height, acc, moments, base):
    """For each pair k of tiles t_lo..t_hi-1, moments[k - base] (NMOM) about its Gaussian's centre
    (u, v = pixel centre - Gaussian centre) over the tile's pixels inside the image: the derivative
    e_c of channel c by the Gaussian's exponent, e_c = alpha (colour_c T - behind_c / (1 - alpha))
    (0 where capped, skipped or past the stop), and its weight w = alpha T (`hessian`'s sweep);
    `acc` the forward compositing of the tiles (`composite_forward`). Rows past a tile's stop are
    left as they are (zeros)."""
    p_count = ts * ts
    px, py = _pixel_grid(ts)
    trans = np.empty(p_count, np.float32)
    live = np.empty(p_count, np.float32)
    inside = np.empty(p_count, np.float32)
    rest_r, rest_g, rest_b = np.empty(p_count, np.float32), np.empty(p_count, np.float32), np.empty(p_count, np.float32)
    for t in range(t_lo, t_hi):
        x0, y0 = _tile_origin(t, tiles_x, ts)
        start, end = offsets[t], offsets[t + 1]
        if end == start:
            continue
        for p in range(p_count):
            rest_r[p], rest_g[p], rest_b[p] = acc[t, 0, p], acc[t, 1, p], acc[t, 2, p]
            inside[p] = _ONE if (x0 + px[p] < width and y0 + py[p] < height) else _ZERO
        trans[:] = _ONE
        live[:] = _ONE
        for k in range(start, end):
            g = ids[k]
            mx, my, ha, nb, hc, lo = _gaussian(table, g, x0, y0)
            cr, cg, cb = table[g, CR], table[g, CG], table[g, CBL]
            m00 = m10 = m01 = m20 = m11 = m02 = m30 = m21 = m12 = m03 = _ZERO
            m40 = m31 = m22 = m13 = m04 = _ZERO
            r00 = r10 = r01 = r20 = r11 = r02 = _ZERO
            g00 = g10 = g01 = g20 = g11 = g02 = _ZERO
            b00 = b10 = b01 = b20 = b11 = b02 = _ZERO
            ww = _ZERO
            alive = _ZERO
            for p in range(p_count):
                alpha, dx, dy = _alpha(px[p], py[p], mx, my, ha, nb, hc, lo)
                tr = trans[p]
                after = tr - tr * alpha
                keep = live[p] if after >= T_MIN else _ZERO
                w = keep * alpha * tr
                br, bg, bb = rest_r[p] - cr * w, rest_g[p] - cg * w, rest_b[p] - cb * w
                rest_r[p], rest_g[p], rest_b[p] = br, bg, bb
                wi = w * inside[p]
                gate = alpha if (alpha < ALPHA_MAX and wi > _ZERO) else _ZERO
                inv = _ONE / (_ONE - alpha)
                er = (cr * tr - br * inv) * gate
                eg = (cg * tr - bg * inv) * gate
                eb = (cb * tr - bb * inv) * gate
                s = er * er + eg * eg + eb * eb
                xx, xy, yy = dx * dx, dx * dy, dy * dy
                m00 += s
                m10 += s * dx
                m01 += s * dy
                m20 += s * xx
                m11 += s * xy
                m02 += s * yy
                m30 += s * xx * dx
                m21 += s * xx * dy
                m12 += s * xy * dy
                m03 += s * yy * dy
                m40 += s * xx * xx
                m31 += s * xx * xy
                m22 += s * xx * yy
                m13 += s * xy * yy
                m04 += s * yy * yy
                tr_, tg_, tb_ = er * wi, eg * wi, eb * wi
                r00 += tr_
                r10 += tr_ * dx
                r01 += tr_ * dy
                r20 += tr_ * xx
                r11 += tr_ * xy
                r02 += tr_ * yy
                g00 += tg_
                g10 += tg_ * dx
                g01 += tg_ * dy
                g20 += tg_ * xx
                g11 += tg_ * xy
                g02 += tg_ * yy
                b00 += tb_
                b10 += tb_ * dx
                b01 += tb_ * dy
                b20 += tb_ * xx
                b11 += tb_ * xy
                b02 += tb_ * yy
                ww += wi * wi
                alive += keep
                trans[p] = after if keep > _ZERO else tr
                live[p] = keep
            row = k - base
            moments[row, 0], moments[row, 1], moments[row, 2] = m00, m10, m01
            moments[row, 3], moments[row, 4], moments[row, 5] = m20, m11, m02
            moments[row, 6], moments[row, 7], moments[row, 8], moments[row, 9] = m30, m21, m12, m03
            moments[row, 10], moments[row, 11], moments[row, 12], moments[row, 13], moments[row, 14] = \
                m40, m31, m22, m13, m04
            moments[row, 15], moments[row, 16], moments[row, 17] = r00, r10, r01
            moments[row, 18], moments[row, 19], moments[row, 20] = r20, r11, r02
            moments[row, 21], moments[row, 22], moments[row, 23] = g00, g10, g01
            moments[row, 24], moments[row, 25], moments[row, 26] = g20, g11, g02
            moments[row, 27], moments[row, 28], moments[row, 29] = b00, b10, b01
            moments[row, 30], moments[row, 31], moments[row, 32] = b20, b11, b02
            moments[row, 33] = ww
            if alive == _ZERO:
                break


@kernel
def add_moments(moments, ids, base, g_lo, g_hi, out):
    """out[ids[base + r]] += moments[r] for the rows r with some weight (w² > 0) whose Gaussian is in
    g_lo..g_hi-1 (threads add into rows apart)."""
    for r in range(moments.shape[0]):
        if moments[r, NMOM - 1] > _ZERO:
            g = ids[base + r]
            if g_lo <= g < g_hi:
                for c in range(NMOM):
                    out[g, c] += moments[r, c]


# ----------------------------------------------------------------------------- the Hessian's blocks

@inline
def _world(g, to_world):
    """(d/dx, d/dy, d/dz) in camera space -> d / d normalised world position (in place on g[0:3])."""
    a, b, c = g[0], g[1], g[2]
    for j in range(3):
        g[j] = to_world[0, j] * a + to_world[1, j] * b + to_world[2, j] * c


@kernel
def gaussian_blocks(means, log_scales, quats, sh_rest, sizes, cam, degree, flags, scale, table, mom, lo, hi, out):
    """out[i] (21, float64) += the packed upper triangle of this view's Gauss-Newton block J^T J of
    Gaussian i (position in the normalised frame, log-scale) for i in lo..hi-1 with some weight
    (mom[i, NMOM-1] > 0), from its moments mom[i] (`gauss_newton_moments`, summed over its pairs;
    cleared once read, so that mom is all zeros again for the next view) and its drawn colour
    (table[i, 6:9]): `hessian._gaussian_blocks`, one Gaussian at a time in float64 (the derivatives
    of the projection by camera-space position and log-scale, in the anti-aliasing mode of `flags`,
    composed with the moments)."""
    fx, fy = cam[12], cam[13]
    lo_x, hi_x, lo_y, hi_y = cam[16], cam[17], cam[18], cam[19]
    aw, ax, ay, az = cam[20], cam[21], cam[22], cam[23]
    to_world = np.empty((3, 3), np.float64)
    for a in range(3):
        for b in range(3):
            to_world[a, b] = scale * cam[3 * a + b]
    k_rest = sh_rest.shape[1]
    kb = min((degree + 1) * (degree + 1) - 1, k_rest)
    basis_grad = np.zeros(15, np.float32)
    lam = np.zeros((6, 6), np.float64)  # lam[monomial][theta]
    s_mat = np.empty((6, 6), np.float64)
    a_mat = np.empty((6, 6), np.float64)
    h = np.empty((6, 6), np.float64)
    dlog_o = np.empty(6, np.float64)
    dmx, dmy = np.empty(6, np.float64), np.empty(6, np.float64)
    dqa, dqb, dqc = np.empty(6, np.float64), np.empty(6, np.float64), np.empty(6, np.float64)
    daa, dbb, dab = np.empty(6, np.float64), np.empty(6, np.float64), np.empty(6, np.float64)
    jc = np.empty((3, 3), np.float64)
    s_eff = np.empty(3, np.float64)
    gain = np.empty(3, np.float64)
    pw = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))
    index = np.empty((5, 5), np.int64)  # moment column of u^i v^j
    col = 0
    for d_ in range(5):
        for j_ in range(d_ + 1):
            index[d_ - j_, j_] = col
            col += 1
    for i in range(lo, hi):
        m = mom[i]
        if not m[NMOM - 1] > 0.0:  # (a row with no weight got nothing from `add_moments`: zeros)
            continue
        rx, ry, rz = means[i, 0] - cam[9], means[i, 1] - cam[10], means[i, 2] - cam[11]
        x = cam[0] * rx + cam[1] * ry + cam[2] * rz
        y = cam[3] * rx + cam[4] * ry + cam[5] * rz
        z = cam[6] * rx + cam[7] * ry + cam[8] * rz
        iz = 1.0 / z
        u, v = x * iz, y * iz
        uc, vc = min(max(u, lo_x), hi_x), min(max(v, lo_y), hi_y)
        free_u = 1.0 if (u > lo_x and u < hi_x) else 0.0
        free_v = 1.0 if (v > lo_y and v < hi_y) else 0.0
        iz2 = iz * iz
        j00, j11, j02, j12 = fx * iz, fy * iz, -fx * uc * iz, -fy * vc * iz
        dj00_z, dj11_z = -fx * iz2, -fy * iz2
        dj02_x, dj02_z = -fx * iz2 * free_u, fx * iz2 * (uc + free_u * u)
        dj12_y, dj12_z = -fy * iz2 * free_v, fy * iz2 * (vc + free_v * v)
        bw, bx, by, bz, _, _ = _unit_quat(quats, i)
        bw, bx, by, bz = float(bw), float(bx), float(by), float(bz)
        w = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)
        r10, r11, r12 = 2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)
        r20, r21, r22 = 2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)
        for t in range(6):
            dlog_o[t] = 0.0
        f = 0.0
        for c in range(3):
            raw = float(log_scales[i, c])
            ls = min(max(raw, LOG_SCALE_RANGE[0]), LOG_SCALE_RANGE[1])
            ins = 1.0 if (raw >= LOG_SCALE_RANGE[0] and raw <= LOG_SCALE_RANGE[1]) else 0.0
            if flags & (FILTER_3D | DILATION_3D):
                f = float(sizes[i])
                f = min(max(f if np.isfinite(f) else 0.0, FILTER_3D_RANGE[0]), FILTER_3D_RANGE[1])
                a_, b_ = 2.0 * ls, 2.0 * math.log(f)
                log_eff = 0.5 * (max(a_, b_) + math.log1p(math.exp(-abs(a_ - b_))))
                s_eff[c] = math.exp(log_eff)
                gain[c] = math.exp(2.0 * (ls - log_eff)) * ins
                if flags & FILTER_3D:
                    dlog_o[3 + c] = (1.0 - gain[c]) * ins
            else:
                s_eff[c], gain[c] = math.exp(ls), ins
        m0 = (r00 * s_eff[0], r01 * s_eff[1], r02 * s_eff[2])
        m1 = (r10 * s_eff[0], r11 * s_eff[1], r12 * s_eff[2])
        m2 = (r20 * s_eff[0], r21 * s_eff[1], r22 * s_eff[2])
        ak = (j00 * m0[0] + j02 * m2[0], j00 * m0[1] + j02 * m2[1], j00 * m0[2] + j02 * m2[2])
        bk = (j11 * m1[0] + j12 * m2[0], j11 * m1[1] + j12 * m2[1], j11 * m1[2] + j12 * m2[2])
        am0 = ak[0] * m0[0] + ak[1] * m0[1] + ak[2] * m0[2]
        am2 = ak[0] * m2[0] + ak[1] * m2[1] + ak[2] * m2[2]
        am1 = ak[0] * m1[0] + ak[1] * m1[1] + ak[2] * m1[2]
        bm0 = bk[0] * m0[0] + bk[1] * m0[1] + bk[2] * m0[2]
        bm1 = bk[0] * m1[0] + bk[1] * m1[1] + bk[2] * m1[2]
        bm2 = bk[0] * m2[0] + bk[1] * m2[1] + bk[2] * m2[2]
        aa = ak[0] * ak[0] + ak[1] * ak[1] + ak[2] * ak[2]
        bb = bk[0] * bk[0] + bk[1] * bk[1] + bk[2] * bk[2]
        ab = ak[0] * bk[0] + ak[1] * bk[1] + ak[2] * bk[2]
        dd_z = 0.0
        if flags & MIP_2D:
            d = MIP_2D_VARIANCE
        elif flags & DILATION_3D:
            rest_2d = DILATION - f * f * (fx * fy) * iz2
            d = max(rest_2d, 0.0)
            dd_z = 2.0 * f * f * (fx * fy) * iz2 * iz if rest_2d > 0.0 else 0.0
        else:
            d = DILATION
        cr0, cr1, cr2 = ak[1] * bk[2] - ak[2] * bk[1], ak[2] * bk[0] - ak[0] * bk[2], ak[0] * bk[1] - ak[1] * bk[0]
        cc = cr0 * cr0 + cr1 * cr1 + cr2 * cr2
        det = cc + d * (aa + bb) + d * d
        daa[0], daa[1], daa[2] = 2 * dj02_x * am2, 0.0, 2 * (dj00_z * am0 + dj02_z * am2) + dd_z
        dbb[0], dbb[1], dbb[2] = 0.0, 2 * dj12_y * bm2, 2 * (dj11_z * bm1 + dj12_z * bm2) + dd_z
        dab[0], dab[1] = dj02_x * bm2, dj12_y * am2
        dab[2] = dj00_z * bm0 + dj02_z * bm2 + dj11_z * am1 + dj12_z * am2
        for c in range(3):
            daa[3 + c] = 2 * ak[c] * ak[c] * gain[c]
            dbb[3 + c] = 2 * bk[c] * bk[c] * gain[c]
            dab[3 + c] = 2 * ak[c] * bk[c] * gain[c]
        inv = 1.0 / det
        qa, qb, qc = (bb + d) * inv, -ab * inv, (aa + d) * inv
        for t in range(6):
            dqa[t] = -(qa * qa * daa[t] + 2 * qa * qb * dab[t] + qb * qb * dbb[t])
            dqb[t] = -(qa * qb * daa[t] + (qb * qb + qa * qc) * dab[t] + qb * qc * dbb[t])
            dqc[t] = -(qb * qb * daa[t] + 2 * qb * qc * dab[t] + qc * qc * dbb[t])
        if flags & MIP_2D:  # the 2D Mip filter's opacity sqrt(cc / det)
            pv = (bk[1] * cr2 - bk[2] * cr1, bk[2] * cr0 - bk[0] * cr2, bk[0] * cr1 - bk[1] * cr0)
            qv = (cr1 * ak[2] - cr2 * ak[1], cr2 * ak[0] - cr0 * ak[2], cr0 * ak[1] - cr1 * ak[0])
            m2p = m2[0] * pv[0] + m2[1] * pv[1] + m2[2] * pv[2]
            m2q = m2[0] * qv[0] + m2[1] * qv[1] + m2[2] * qv[2]
            m0p = m0[0] * pv[0] + m0[1] * pv[1] + m0[2] * pv[2]
            m1q = m1[0] * qv[0] + m1[1] * qv[1] + m1[2] * qv[2]
            ok = 1.0 if cc * inv > MIP_2D_RATIO_FLOOR else 0.0
            inv_cc = ok / cc if cc > 0.0 else 0.0
            for t in range(6):
                if t == 0:
                    dcc = 2 * dj02_x * m2p
                elif t == 1:
                    dcc = 2 * dj12_y * m2q
                elif t == 2:
                    dcc = 2 * (dj00_z * m0p + dj02_z * m2p + dj11_z * m1q + dj12_z * m2q)
                else:
                    dcc = 2 * gain[t - 3] * (ak[t - 3] * pv[t - 3] + bk[t - 3] * qv[t - 3])
                ddet = dcc + d * (daa[t] + dbb[t])
                dlog_o[t] += 0.5 * (dcc * inv_cc - ok * ddet * inv)
        for t in range(6):
            dmx[t] = dmy[t] = 0.0
        dmx[0], dmx[2] = fx * iz, -fx * u * iz
        dmy[1], dmy[2] = fy * iz, -fy * v * iz
        for g in (dmx, dmy, dqa, dqb, dqc, dlog_o):
            _world(g, to_world)
        for t in range(6):
            lam[0, t] = dlog_o[t]
            lam[1, t] = qa * dmx[t] + qb * dmy[t]
            lam[2, t] = qb * dmx[t] + qc * dmy[t]
            lam[3, t] = -0.5 * dqa[t]
            lam[4, t] = -dqb[t]
            lam[5, t] = -0.5 * dqc[t]
        for a in range(6):
            for b in range(6):
                s_mat[a, b] = m[index[pw[a][0] + pw[b][0], pw[a][1] + pw[b][1]]]
        for t in range(6):
            for b in range(6):
                acc_ = 0.0
                for a in range(6):
                    acc_ += lam[a, t] * s_mat[a, b]
                a_mat[t, b] = acc_
        for t1 in range(6):
            for t2 in range(t1, 6):
                acc_ = 0.0
                for b in range(6):
                    acc_ += a_mat[t1, b] * lam[b, t2]
                h[t1, t2] = acc_
        if degree > 0 and kb > 0:  # the colour's own derivative (SH along the direction)
            dist = math.sqrt(rx * rx + ry * ry + rz * rz)
            ux, uy, uz = rx / dist, ry / dist, rz / dist
            inv_dist = scale / dist
            for c in range(3):
                for b in range(kb):
                    basis_grad[b] = sh_rest[i, b, c]
                gx, gy, gz = _sh_basis_grad(f32(ux), f32(uy), f32(uz), degree, basis_grad, _ZERO, _ZERO, _ZERO)
                gx, gy, gz = float(gx), float(gy), float(gz)
                radial = gx * ux + gy * uy + gz * uz
                live = 1.0 if table[i, CR + c] > _ZERO else 0.0
                jc[c, 0] = (gx - radial * ux) * inv_dist * live
                jc[c, 1] = (gy - radial * uy) * inv_dist * live
                jc[c, 2] = (gz - radial * uz) * inv_dist * live
            wsum = m[NMOM - 1]
            for t1 in range(6):
                lt0 = lt1 = lt2 = 0.0
                for a in range(6):
                    lt0 += lam[a, t1] * m[15 + a]
                    lt1 += lam[a, t1] * m[21 + a]
                    lt2 += lam[a, t1] * m[27 + a]
                for t2 in range(3):
                    extra = lt0 * jc[0, t2] + lt1 * jc[1, t2] + lt2 * jc[2, t2]
                    if t1 <= t2:
                        h[t1, t2] += extra
                    if t2 <= t1:
                        h[t2, t1] += extra
                    if t1 < 3 and t1 <= t2:
                        h[t1, t2] += (jc[0, t1] * jc[0, t2] + jc[1, t1] * jc[1, t2] + jc[2, t1] * jc[2, t2]) * wsum
        col = 0
        for t1 in range(6):
            for t2 in range(t1, 6):
                val = h[t1, t2]
                out[i, col] += val if np.isfinite(val) else 0.0
                col += 1
        m[:] = 0.0  # read: cleared for the next view's sweep


@kernel
def logdet_scores(rows, lam, lo, hi, out):
    """out[i] = log det(I + H_i / lam) (float32, >= 0) for i in lo..hi-1, H_i the symmetric 6x6
    block whose upper triangle is rows[i] (21, row by row; non-finite entries read as 0), by an
    LDL^T factorisation whose pivots are clamped at 1 (`hessian._logdet_eye_plus`, one block at a time)."""
    a = np.empty((6, 6), np.float64)
    low = np.zeros((6, 6), np.float64)
    d = np.empty(6, np.float64)
    for i in range(lo, hi):
        col = 0
        for r in range(6):
            for c in range(r, 6):
                v = rows[i, col]
                v = v / lam if np.isfinite(v) else 0.0
                a[r, c] = v
                a[c, r] = v
                col += 1
        total, product = 0.0, 1.0  # the log of a product of pivots (one log a block, not six)
        for j in range(6):
            dj = 1.0 + a[j, j]
            for k in range(j):
                dj -= low[j, k] * low[j, k] * d[k]
            dj = max(dj, 1.0)
            d[j] = dj
            product *= dj
            if product > 1e150:
                total += math.log(product)
                product = 1.0
            for r in range(j + 1, 6):
                v = a[j, r]
                for k in range(j):
                    v -= low[r, k] * low[j, k] * d[k]
                low[r, j] = v / dj
        out[i] = max(total + math.log(product), 0.0)


#: Every kernel of this module (what `compiled.compile_kernels` makes ready).
KERNELS = ("project_forward", "project_backward", "radix_order", "gather_footprints", "bin_count", "bin_fill",
           "composite_forward", "composite_backward", "pair_grads_to_table", "assemble_forward",
           "assemble_backward", "gauss_newton_moments", "add_moments",
           "gaussian_blocks", "logdet_scores")
