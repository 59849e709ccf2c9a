"""SuperSplat's (PlayCanvas) compressed PLY: a standard binary PLY with packed elements.

    element chunk  ceil(N / 256)   float min_x min_y min_z max_x max_y max_z,
                                   min_scale_x .. min_scale_z, max_scale_x .. max_scale_z
                                   [, min_r min_g min_b max_r max_g max_b]   (newer files)
    element vertex N               uint packed_position, packed_rotation, packed_scale, packed_color
    element sh N (optional)        uchar f_rest_0 .. f_rest_{3K-1}   (channel-major, as the PLY layout)

Gaussian i belongs to chunk i // 256 and is stored relative to that chunk's bounds:
- packed_position / packed_scale: 11, 10, 11 bits (x in bits 21-31, y in 11-20, z in 0-10) of
  t = (v - min) / (max - min), decoded as min + t (max - min); scales are log-scales (the writer
  clamps their bounds to +-20);
- packed_rotation: bits 30-31 the index (in rot_0..3 = w, x, y, z order) of the largest component of
  the unit quaternion, made positive; the other three in index order, 10 bits each from bit 20 down,
  as unorm of q_i / sqrt 2 + 0.5; the largest is sqrt(1 - sum of the others' squares);
- packed_color: r, g, b, a in bits 24-31, 16-23, 8-15, 0-7: unorm of the colour SH_C0 * f_dc + 0.5
  (relative to the chunk's colour bounds when the chunk has them, else as is) and of sigmoid(opacity);
- sh: uchar c with f_rest = 8 * (n - 0.5), n = (c + 0.5) / 256 except 0 -> 0 and 255 -> 1.
Quantisation (decoding is what SuperSplat and splat-transform do, the opacity end codes a quarter
step inside as in `_codec`): position and log-scale within half a step of the chunk's extent
(1/2047 or 1/1023 of it); colour within half of 1/255 of the chunk's colour extent; opacity sigmoid
within 0.5/255; rotation within 0.5/1023 * sqrt 2 ~ 0.0007 per smaller component; SH within 1/32
for |f_rest| <= 4 (clamped outside). Precision depends on how compact each chunk of 256 is, which is
why SuperSplat sorts Gaussians spatially (Morton order) before writing; `write_compressed_ply` keeps
the cloud's row order.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..cloud import GaussianCloud
from ..conventions import SH_C0, SH_DEGREE_OF_REST, activate_opacities, rgb_to_dc
from ..ply import PlyError, drop_nonfinite, read_header
from ._codec import OPACITY_OF_CODE, writable

__all__ = ["read_compressed_ply", "write_compressed_ply", "is_compressed_ply_header", "CHUNK_SIZE"]

CHUNK_SIZE = 256
CHUNK_BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
                "min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
CHUNK_COLORS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
#: The writer clamps the log-scale bounds of a chunk to +-this (SuperSplat's rule).
SCALE_BOUND = 20.0

_SH_OF_CODE = (8.0 * (np.concatenate([[0.0], (np.arange(1, 255) + 0.5) / 256, [1.0]]) - 0.5)).astype(np.float32)
_SMALL_OF_CODE = ((np.arange(1024) / 1023.0 - 0.5) * math.sqrt(2.0)).astype(np.float32)


def is_compressed_ply_header(header) -> bool:
    """Whether a parsed PLY header (`ply.read_header`) has the compressed layout."""
    names = {e.name for e in header.elements}
    vertex = next((e for e in header.elements if e.name == "vertex"), None)
    return "chunk" in names and vertex is not None and any(p == "packed_position" for p, _ in vertex.props)


# ------------------------------------------------------------------------------------ read

def read_compressed_ply(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read a compressed PLY into a numpy GaussianCloud (SH degree from the `sh` element).
    Chunk bounds that are not finite make their Gaussians non-finite rows: PlyError naming them,
    or with `sanitize` they are dropped with a warning."""
    path = Path(path)
    where = str(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        header = read_header(f, where)
        dtypes = _element_dtypes(header, where)
        need = header.data_offset + sum(dt.itemsize * e.count for e, dt in zip(header.elements, dtypes))
        if need > size:
            raise PlyError(f"{where}: truncated: the header declares {need - header.data_offset} bytes of data "
                           f"but only {size - header.data_offset} follow it")
        f.seek(header.data_offset)
        data = {}
        for el, dt in zip(header.elements, dtypes):
            arr = np.fromfile(f, dt, el.count)
            if len(arr) != el.count:
                raise PlyError(f"{where}: truncated while reading (did the file change?)")
            data[el.name] = arr
    cloud, finite = _decode(data, where)
    return drop_nonfinite(cloud, finite, where, sanitize, stacklevel=3)


def _element_dtypes(header, where: str) -> list[np.dtype]:
    if header.byte_order is None:
        raise PlyError(f"{where}: a compressed PLY must be binary, not ascii")
    counts = {}
    for e in header.elements:
        counts[e.name] = counts.get(e.name, 0) + 1
        if e.has_list:
            raise PlyError(f"{where}: compressed PLY element {e.name!r} has list properties")
    for name in ("chunk", "vertex"):
        if counts.get(name) != 1:
            raise PlyError(f"{where}: bad compressed PLY: expected one {name!r} element, found {counts.get(name, 0)}")
    if counts.get("sh", 0) > 1:
        raise PlyError(f"{where}: bad compressed PLY: {counts['sh']} 'sh' elements")
    els = {e.name: e for e in header.elements}
    chunk, vertex, sh = els["chunk"], els["vertex"], els.get("sh")
    types = {e.name: dict(e.props) for e in header.elements}
    want_chunk = CHUNK_BOUNDS + (CHUNK_COLORS if "min_r" in types["chunk"] else ())
    bad = [p for p in want_chunk if types["chunk"].get(p) not in ("f4", "f8")]
    if bad:
        raise PlyError(f"{where}: bad compressed PLY: chunk properties missing or not float: {', '.join(bad)}")
    bad = [p for p in PACKED if types["vertex"].get(p) != "u4"]
    if bad:
        raise PlyError(f"{where}: bad compressed PLY: vertex properties missing or not uint: {', '.join(bad)}")
    if chunk.count != -(-vertex.count // CHUNK_SIZE):
        raise PlyError(f"{where}: bad compressed PLY: {chunk.count} chunks for {vertex.count} Gaussians "
                       f"(expected {-(-vertex.count // CHUNK_SIZE)}, one per {CHUNK_SIZE})")
    if sh is not None:
        names = [p for p, _ in sh.props]
        if len(names) not in (9, 24, 45) or names != [f"f_rest_{i}" for i in range(len(names))] \
                or any(t != "u1" for _, t in sh.props):
            raise PlyError(f"{where}: bad compressed PLY: the sh element must hold uchar f_rest_0..f_rest_(3K-1) "
                           "with 3K in 9, 24, 45")
        if sh.count != vertex.count:
            raise PlyError(f"{where}: bad compressed PLY: {sh.count} sh rows for {vertex.count} Gaussians")
    others = [e.name for e in header.elements if e.name not in ("chunk", "vertex", "sh") and e.count]
    if others:
        warnings.warn(f"{where}: ignoring element(s) {', '.join(others)} of a compressed PLY", stacklevel=4)
    order = header.byte_order
    return [np.dtype([(p, order + t) for p, t in e.props]) for e in header.elements]


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return ((packed >> np.uint32(shift)) & np.uint32(top)).astype(np.float64) / top


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    """lo (1 - t) + hi t, exactly lo at t = 0 and hi at t = 1 (also when the other bound is infinite)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return np.where(t == 1.0, hi, np.where(t == 0.0, lo, lo * (1.0 - t) + hi * t))


def _decode(data: dict[str, np.ndarray], where: str):
    chunk, vertex = data["chunk"], data["vertex"]
    n = len(vertex)

    def per_row(name: str) -> np.ndarray:
        return np.repeat(chunk[name].astype(np.float64), CHUNK_SIZE)[:n]

    def field3(packed: np.ndarray, lo: tuple, hi: tuple) -> np.ndarray:
        out = np.empty((n, 3), np.float32)
        for i, (shift, bits) in enumerate(((21, 11), (11, 10), (0, 11))):
            out[:, i] = _lerp(per_row(lo[i]), per_row(hi[i]), _unorm(packed, shift, bits))
        return out

    means = field3(vertex["packed_position"], CHUNK_BOUNDS[0:3], CHUNK_BOUNDS[3:6])
    scales = field3(vertex["packed_scale"], CHUNK_BOUNDS[6:9], CHUNK_BOUNDS[9:12])
    color = vertex["packed_color"]
    rgb = np.empty((n, 3), np.float64)
    colored = "min_r" in chunk.dtype.names
    for i, shift in enumerate((24, 16, 8)):
        t = _unorm(color, shift, 8)
        rgb[:, i] = _lerp(per_row(CHUNK_COLORS[i]), per_row(CHUNK_COLORS[3 + i]), t) if colored else t
    with np.errstate(invalid="ignore", over="ignore"):
        sh_dc = rgb_to_dc(rgb).astype(np.float32)
    opacities = OPACITY_OF_CODE[(color & np.uint32(0xFF)).astype(np.intp)]

    rot = vertex["packed_rotation"]
    big = rot >> np.uint32(30)
    f = [_SMALL_OF_CODE[((rot >> np.uint32(shift)) & np.uint32(0x3FF)).astype(np.intp)] for shift in (20, 10, 0)]
    m = np.sqrt(np.maximum(0.0, 1.0 - (f[0] * f[0] + f[1] * f[1] + f[2] * f[2])))
    quats = np.empty((n, 4), np.float32)
    for j in range(4):
        below = f[j] if j < 3 else m
        above = f[j - 1] if j > 0 else m
        quats[:, j] = np.where(big == j, m, np.where(big > j, below, above))

    sh = data.get("sh")
    if sh is None:
        sh_rest = np.zeros((n, 0, 3), np.float32)
    else:
        k = len(sh.dtype.names) // 3
        codes = sh.view(np.uint8).reshape(n, 3, k)
        sh_rest = np.empty((n, k, 3), np.float32)
        step = 1 << 14  # rows per block: the transpose stays in cache
        for start in range(0, n, step):
            sh_rest[start:start + step] = _SH_OF_CODE[codes[start:start + step]].transpose(0, 2, 1)
    assert sh_rest.shape[1] in SH_DEGREE_OF_REST
    cloud = GaussianCloud(means=means, scales=scales, quats=quats, opacities=opacities, sh_dc=sh_dc,
                          sh_rest=sh_rest)
    finite = np.ones(n, bool)
    for a in (means, scales, sh_dc):
        if not np.isfinite(a.sum()):
            finite &= np.isfinite(a).all(1)
    return cloud, finite


# ----------------------------------------------------------------------------------- write

def _pack_unorm(v: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(v * top + 0.5), 0, top).astype(np.uint32)


def _normalize(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """SuperSplat's normalize: 0 at or below lo, 1 at or above hi, 0 for a chunk narrower than 1e-5."""
    span = hi - lo
    t = (x - lo) / np.where(span < 1e-5, 1.0, span)
    t = np.where(span < 1e-5, 0.0, t)
    return np.where(x <= lo, 0.0, np.where(x >= hi, 1.0, t))


def write_compressed_ply(cloud: GaussianCloud, path) -> Path:
    """Write `cloud` as a compressed PLY (atomic), in its row order, with per-chunk colour bounds.
    Refuses non-finite rows (PlyError); extra properties are not stored (a warning says so)."""
    path = Path(path)
    where = str(path)
    c = writable(cloud, "a compressed PLY", where)
    n, k = len(c), c.sh_rest.shape[1]
    starts = np.arange(0, n, CHUNK_SIZE)
    ci = np.arange(n) // CHUNK_SIZE

    def bounds(v: np.ndarray):
        if n == 0:
            return np.zeros((0,) + v.shape[1:]), np.zeros((0,) + v.shape[1:])
        return np.minimum.reduceat(v, starts, axis=0), np.maximum.reduceat(v, starts, axis=0)

    def pack3(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        t = _normalize(v, lo[ci], hi[ci])
        return (_pack_unorm(t[:, 0], 11) << np.uint32(21)) | (_pack_unorm(t[:, 1], 10) << np.uint32(11)) \
            | _pack_unorm(t[:, 2], 11)

    means = c.means.astype(np.float64)
    scales = c.scales.astype(np.float64)
    rgb = c.sh_dc.astype(np.float64) * SH_C0 + 0.5
    p_lo, p_hi = bounds(means)
    s_lo, s_hi = (np.clip(b, -SCALE_BOUND, SCALE_BOUND) for b in bounds(scales))
    c_lo, c_hi = bounds(rgb)
    packed = np.empty((n, 4), "<u4")
    packed[:, 0] = pack3(means, p_lo, p_hi)
    packed[:, 2] = pack3(scales, s_lo, s_hi)
    tc = _normalize(rgb, c_lo[ci], c_hi[ci])
    alpha = activate_opacities(c.opacities.astype(np.float64))
    packed[:, 3] = ((_pack_unorm(tc[:, 0], 8) << np.uint32(24)) | (_pack_unorm(tc[:, 1], 8) << np.uint32(16))
                    | (_pack_unorm(tc[:, 2], 8) << np.uint32(8)) | _pack_unorm(alpha, 8))
    q = c.unit_quats().astype(np.float64)
    rows = np.arange(n)
    big = np.argmax(np.abs(q), axis=1)
    q = np.where((q[rows, big] < 0)[:, None], -q, q)
    rot = big.astype(np.uint32)
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])
    for kk in range(3):
        rot = (rot << np.uint32(10)) | _pack_unorm(q[rows, others[big, kk]] * (math.sqrt(2.0) * 0.5) + 0.5, 10)
    packed[:, 1] = rot
    chunk = np.empty((len(starts), 18), "<f4")
    chunk[:, 0:3], chunk[:, 3:6], chunk[:, 6:9], chunk[:, 9:12] = p_lo, p_hi, s_lo, s_hi
    chunk[:, 12:15], chunk[:, 15:18] = c_lo, c_hi
    sh = np.clip(np.trunc((c.sh_rest.astype(np.float64).transpose(0, 2, 1).reshape(n, 3 * k) / 8 + 0.5) * 256),
                 0, 255).astype(np.uint8)

    lines = ["ply", "format binary_little_endian 1.0", "comment compressed PLY written by gvae_core",
             f"element chunk {len(starts)}"]
    lines += [f"property float {p}" for p in CHUNK_BOUNDS + CHUNK_COLORS]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    if k:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * k)]
    head = ("\n".join(lines) + "\nend_header\n").encode("ascii")

    def write_body(f) -> None:
        f.write(head)
        f.write(chunk.tobytes())
        f.write(packed.tobytes())
        if k:
            f.write(sh.tobytes())

    return atomic_write(path, write_body)
