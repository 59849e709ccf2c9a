"""Niantic's `.spz` (Scaniverse and others): fixed-point positions, 8-bit everything else.

Two containers, told apart by their first bytes:
- versions 1-3 ("legacy", gzip, `1f 8b`): one gzip stream holding a 16-byte header, then the data;
- version 4 (Niantic's library writes it by default since 2026): a plaintext 32-byte header
  (magic "NGSP"), optional extension records up to `toc_offset`, a table of contents of
  (compressed, uncompressed) uint64 sizes, then one zstd frame per non-empty attribute stream.
  Reading it needs the `zstandard` package (Blender bundles it; so does `pip install bpy`).

Header (little endian): magic "NGSP" (0x5053474e), uint32 version, uint32 count, uint8 SH degree
(0..4), uint8 fractional bits, uint8 flags (1: trained with anti-aliasing, 2: extension records
follow), then 1 reserved byte (legacy) or uint8 stream count, uint32 TOC offset, 12 reserved bytes
(version 4). The attributes are stored one after the other (not interleaved), in this order:

    positions   9 bytes  x, y, z: signed 24-bit fixed point, value = int * 2**-fractional_bits
                         (version 1: 6 bytes, three float16)
    alphas      1 byte   round(255 * sigmoid(opacity))
    colors      3 bytes  round(255 * (0.15 * f_dc + 0.5)): a wider range than the displayed
                         colour (0.15 < SH_C0), since higher SH bands may bring it back into range
    scales      3 bytes  round(16 * (log-scale + 10))
    rotations   4 bytes  version >= 3, "smallest three": the unit quaternion (x, y, z, w order), sign
                         chosen so its largest component is positive; bits 30-31 hold that
                         component's index, then for each other component in index order a sign bit
                         and a 9-bit magnitude round(511 * |q_i| * sqrt 2), the first in bits 20-29.
                         Versions 1-2: 3 bytes, round(127.5 * q_xyz + 127.5) with w >= 0.
    sh          dim*3    per Gaussian, coefficient-major with the colour channel innermost (our
                         sh_rest (N, K, 3) order): round(128 * c + 128), with degree-1 coefficients
                         rounded to multiples of 8 (5 bits) and higher ones to multiples of 16 (4 bits).

Quantisation (decoding is what Niantic's loader does, with the end codes of opacity a quarter step
inside as in `_codec`), the error bounds the tests check:
- position: half of 2**-fractional_bits (writer: 12 bits, 1/8192 ~ 0.12 mm per metre, fewer bits only
  where a coordinate beyond +-2048 needs them; beyond 2**23 units it refuses);
- log-scale: 1/32 within [-10, 5.94] (clamped outside); colour f_dc: 1/(2 * 255 * 0.15) ~ 0.013 within
  +-3.33 (clamped outside); opacity: sigmoid within 0.5/255;
- rotation: 0.5/511/sqrt 2 ~ 0.0007 per smaller component (versions 1-2: 1/255);
- SH: 4.5/128 ~ 0.035 (degree 1: a 1/128 step, then the nearest multiple of 8/128) and 8.5/128 ~ 0.066
  (higher degrees, multiples of 16/128) within [-1, 1] (clamped outside).
Values are taken as stored. The specification calls the stored frame RUB (three.js); Niantic's own
`ply_to_spz` / `spz_to_ply` and SuperSplat convert nothing, so neither does this module: a PLY
written to .spz and read back has the PLY's axes. SH degree 4 is read as degree 3 (a warning says
so); extension records (both containers) and the anti-aliasing flag are skipped.
Writing: version 3 by default (gzip; every reader we know of takes it, Niantic's included; Spark
2.1.0 and SuperSplat read no version 4), version 4 with `version=4` (needs `zstandard`), version 2
with `version=2`. The float32 arithmetic is Niantic's, so the uncompressed payload is byte for byte
what Niantic's encoder makes (and with `compresslevel=6` the whole gzip file). Row order is kept;
writing what was read gives the same values back (rotations renormalised, within the step).
"""

from __future__ import annotations

import math
import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..cloud import GaussianCloud
from ..ply import PlyError, drop_nonfinite
from ._codec import OPACITY_OF_CODE, byte_codes, opacity_codes, round_half_away, writable

__all__ = ["read_spz", "decode_spz", "write_spz", "SpzHeader", "WRITE_VERSION"]

MAGIC = b"NGSP"
GZIP_MAGIC = b"\x1f\x8b"
#: f_dc is stored as 0.15 * f_dc + 0.5 (Niantic's colorScale).
COLOR_SCALE = 0.15
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2
#: The version `write_spz` writes unless told otherwise.
WRITE_VERSION = 3
DEFAULT_SH1_BITS, DEFAULT_SH_REST_BITS = 5, 4
#: Compression levels `write_spz` uses (Niantic's library uses gzip 6, zstd 12: slightly smaller files
#: for several times the time; docs/benchmarks/formats.md).
GZIP_LEVEL, ZSTD_LEVEL = 1, 3
#: SH rest coefficients per channel for SH degree 0..4.
SH_DIM = (0, 3, 8, 15, 24)
STREAMS = ("positions", "alphas", "colors", "scales", "rotations", "sh")
MAX_FRACTIONAL_BITS = 31
_FIXED_MAX = 2 ** 23 - 1
# Extension records of a legacy file are read from at most this many bytes past the data.
_MAX_EXTENSION_BYTES = 1 << 24
_LEGACY = struct.Struct("<4sIIBBBB")            # 16 bytes
_NGSP = struct.Struct("<4sIIBBBBI12x")          # 32 bytes
_TOC_ENTRY = 16                                 # uint64 compressed size, uint64 uncompressed size

# Decoding tables, one value per byte code.
_DC_OF_CODE = ((np.arange(256) / 255.0 - 0.5) / COLOR_SCALE).astype(np.float32)
_LOG_SCALE_OF_CODE = (np.arange(256) / 16.0 - 10.0).astype(np.float32)
_XYZ_OF_CODE = (np.arange(256) / 127.5 - 1.0).astype(np.float32)
_SQRT1_2 = np.float32(math.sqrt(0.5))
# 10-bit field of the smallest-three rotation: sign bit 9, magnitude bits 0-8.
_SMALL_OF_CODE = (np.where(np.arange(1024) & 512, -1.0, 1.0) * math.sqrt(0.5) * (np.arange(1024) & 511) / 511
                  ).astype(np.float32)
# Index order of the three smaller components for each index of the largest one.
_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])


@dataclass(frozen=True)
class SpzHeader:
    version: int
    count: int
    sh_degree: int
    fractional_bits: int
    flags: int

    def stream_sizes(self) -> list[tuple[str, int]]:
        """(name, bytes) of each attribute stream, in file order."""
        n = self.count
        return [("positions", n * (6 if self.version == 1 else 9)), ("alphas", n), ("colors", 3 * n),
                ("scales", 3 * n), ("rotations", n * (4 if self.version >= 3 else 3)),
                ("sh", n * 3 * SH_DIM[self.sh_degree])]


# ------------------------------------------------------------------------------------ read

def read_spz(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read an .spz file (versions 1-4) into a numpy GaussianCloud. Only version 1's float16
    positions can be non-finite: such rows raise PlyError naming them, or `sanitize` drops them."""
    path = Path(path)
    return decode_spz(path.read_bytes(), str(path), sanitize=sanitize)


def decode_spz(data: bytes, where: str, *, sanitize: bool = False) -> GaussianCloud:
    """The cloud of an .spz file's bytes (`read_spz`; a glTF file holds them in a buffer view);
    `where` names the file in errors."""
    if data[:2] == GZIP_MAGIC:
        header, streams = _read_legacy(data, where)
    elif data[:4] == MAGIC:
        header, streams = _read_ngsp(data, where)
    else:
        raise PlyError(f"{where}: not an .spz file: it starts neither with gzip's 1f 8b nor with 'NGSP'")
    cloud = _unpack(header, streams, where)
    return drop_nonfinite(cloud, np.isfinite(cloud.means).all(1), where, sanitize, stacklevel=4)


def read_spz_header(path) -> SpzHeader:
    """The header of an .spz file (decompressing only its first bytes)."""
    path = Path(path)
    where = str(path)
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if head[:4] == MAGIC:
        if len(head) < _NGSP.size:
            _short(where)
        return _check(_NGSP.unpack_from(head), where, True)[0]
    if head[:2] != GZIP_MAGIC:
        raise PlyError(f"{where}: not an .spz file: it starts neither with gzip's 1f 8b nor with 'NGSP'")
    d = zlib.decompressobj(wbits=31)
    try:
        raw = d.decompress(head, _LEGACY.size)
    except zlib.error as exc:
        raise PlyError(f"{where}: corrupt gzip data: {exc}") from None
    if len(raw) < _LEGACY.size:
        _short(where)
    return _check(_LEGACY.unpack(raw), where, False)[0]


def _short(where: str):
    raise PlyError(f"{where}: truncated: the file ends inside the .spz header")


def _check(fields: tuple, where: str, ngsp: bool) -> tuple[SpzHeader, tuple]:
    magic, version, count, degree, bits, flags, *rest = fields
    if magic != MAGIC:
        raise PlyError(f"{where}: gzip data but not an .spz file (no 'NGSP' magic)")
    if not (4 if ngsp else 1) <= version <= 4:
        raise PlyError(f"{where}: unsupported .spz version {version} in a "
                       f"{'NGSP' if ngsp else 'gzip'} container (this reader knows 1-3 gzip, 4 NGSP)")
    if degree >= len(SH_DIM):
        raise PlyError(f"{where}: bad .spz header: SH degree {degree} (0..4 allowed)")
    if bits > MAX_FRACTIONAL_BITS:
        raise PlyError(f"{where}: bad .spz header: {bits} fractional bits (0..{MAX_FRACTIONAL_BITS} allowed)")
    return SpzHeader(version, count, degree, bits, flags), tuple(rest)


def _gzip_error(where: str, exc: Exception) -> PlyError:
    return PlyError(f"{where}: corrupt gzip data: {exc}")


def _read_legacy(data: bytes, where: str):
    d = zlib.decompressobj(wbits=31)
    try:
        raw = d.decompress(data, _LEGACY.size)
    except zlib.error as exc:
        raise _gzip_error(where, exc) from None
    if len(raw) < _LEGACY.size:
        raise PlyError(f"{where}: truncated: the gzip stream ends inside the .spz header")
    header, _ = _check(_LEGACY.unpack(raw), where, False)
    sizes = header.stream_sizes()
    need = sum(size for _, size in sizes)
    limit = need + (_MAX_EXTENSION_BYTES if header.flags & FLAG_EXTENSIONS else 1)
    try:
        body = d.decompress(d.unconsumed_tail, limit)
    except zlib.error as exc:
        raise _gzip_error(where, exc) from None
    if not d.eof:
        if len(body) >= limit:
            raise PlyError(f"{where}: the gzip stream holds more than the {header.count} Gaussians "
                           f"({need} bytes) its header declares")
        raise PlyError(f"{where}: truncated: the gzip stream stops after {len(body)} of the {need} bytes "
                       f"of {header.count} Gaussians")
    if d.unused_data:
        raise PlyError(f"{where}: {len(d.unused_data)} bytes follow the end of the gzip stream")
    if len(body) < need:
        raise PlyError(f"{where}: truncated: the header declares {header.count} Gaussians ({need} bytes) "
                       f"but the stream holds {len(body)}")
    start = 0
    extra = len(body) - need
    if extra and not header.flags & FLAG_EXTENSIONS:
        raise PlyError(f"{where}: the gzip stream holds more than the {header.count} Gaussians ({need} bytes) "
                       "its header declares")
    if extra:
        # Extension records: after the data (Niantic's library today) or, in files of its first
        # extension-aware releases, between the header and the data.
        if _records_fill(body[need:]):
            start = 0
        elif _records_fill(body[:extra]):
            start = extra
        else:
            raise PlyError(f"{where}: {extra} bytes beside the data that are not well-formed extension records")
    return header, _split(body, start, sizes)


def _records_fill(buf: bytes) -> bool:
    """Whether `buf` is exactly a sequence of extension records (uint32 type, uint32 length, payload)."""
    pos = 0
    while pos < len(buf):
        if len(buf) - pos < 8:
            return False
        _, length = struct.unpack_from("<II", buf, pos)
        pos += 8 + length
    return pos == len(buf)


def _split(body: bytes, start: int, sizes) -> dict[str, np.ndarray]:
    out, pos = {}, start
    for name, size in sizes:
        out[name] = np.frombuffer(body, np.uint8, size, pos)
        pos += size
    return out


def _zstandard(where: str):
    try:
        import zstandard  # noqa: PLC0415 - optional: only version-4 files need it
    except ImportError:
        raise PlyError(f"{where}: an .spz version 4 file (zstd streams); reading it needs the 'zstandard' "
                       "package (pip install zstandard; Blender bundles it)") from None
    return zstandard


def _read_ngsp(data: bytes, where: str):
    if len(data) < _NGSP.size:
        raise PlyError(f"{where}: truncated: the file ends inside the 32-byte .spz header")
    header, (num_streams, toc) = _check(_NGSP.unpack_from(data), where, True)
    sizes = [(name, size) for name, size in header.stream_sizes() if size]
    if num_streams != len(sizes):
        raise PlyError(f"{where}: bad .spz header: {num_streams} streams, expected {len(sizes)} for "
                       f"{header.count} Gaussians of SH degree {header.sh_degree}")
    toc_end = toc + _TOC_ENTRY * num_streams
    if toc < _NGSP.size or toc_end > len(data):
        raise PlyError(f"{where}: truncated or bad .spz header: table of contents at bytes {toc}..{toc_end} "
                       f"of a {len(data)}-byte file")
    entries = struct.unpack_from(f"<{2 * num_streams}Q", data, toc)
    zstd = _zstandard(where) if sizes else None
    out, pos = {name: np.zeros(0, np.uint8) for name in STREAMS}, toc_end
    for i, (name, size) in enumerate(sizes):
        packed, unpacked = entries[2 * i], entries[2 * i + 1]
        if unpacked != size:
            raise PlyError(f"{where}: the {name} stream holds {unpacked} bytes; {header.count} Gaussians "
                           f"need {size}")
        if packed > len(data) - pos:
            raise PlyError(f"{where}: truncated: the {name} stream needs {packed} bytes, "
                           f"{len(data) - pos} are left")
        try:
            with zstd.ZstdDecompressor().stream_reader(data[pos:pos + packed]) as reader:
                raw = reader.read(size + 1)
        except zstd.ZstdError as exc:
            raise PlyError(f"{where}: corrupt zstd data in the {name} stream: {exc}") from None
        if len(raw) != size:
            raise PlyError(f"{where}: the {name} stream decompresses to {len(raw)} bytes, not {size}")
        out[name] = np.frombuffer(raw, np.uint8)
        pos += packed
    if pos != len(data):
        raise PlyError(f"{where}: {len(data) - pos} bytes follow the last stream")
    return header, out


def _int24(buf: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) int32 of little-endian signed 24-bit integers."""
    b = buf.reshape(-1, 3)
    w = np.empty((len(b), 4), np.uint8)
    w[:, :3] = b
    w[:, 3] = (b[:, 2] >> 7) * np.uint8(255)  # sign extension
    return w.view("<i4").reshape(n, 3)


def _smallest_three(comp: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w unit quaternions of version-3 packed rotations."""
    big = comp >> 30
    f = [_SMALL_OF_CODE[(comp >> shift) & 0x3FF] for shift in (20, 10, 0)]
    m = np.sqrt(np.maximum(0.0, 1.0 - (f[0] * f[0] + f[1] * f[1] + f[2] * f[2])))
    q = np.empty((len(comp), 4), np.float32)
    for j in range(4):
        # Component j is the largest, or the rank-th smaller one, rank = j or j - 1.
        below = f[j] if j < 3 else None
        above = f[j - 1] if j > 0 else None
        if below is None:
            q[:, j] = np.where(big == j, m, above)
        elif above is None:
            q[:, j] = np.where(big == j, m, below)
        else:
            q[:, j] = np.where(big == j, m, np.where(big > j, below, above))
    return q


def _first_three(codes: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w of version-1/2 packed rotations (w >= 0 derived)."""
    q = np.empty((len(codes), 4), np.float32)
    q[:, :3] = _XYZ_OF_CODE[codes]
    q[:, 3] = np.sqrt(np.maximum(0.0, 1.0 - (q[:, :3] ** 2).sum(1)))
    return q


def _unpack(header: SpzHeader, s: dict[str, np.ndarray], where: str) -> GaussianCloud:
    n = header.count
    if header.version == 1:
        means = np.frombuffer(s["positions"], "<f2").reshape(n, 3).astype(np.float32)
    else:
        means = _int24(s["positions"], n).astype(np.float32) * np.float32(2.0 ** -header.fractional_bits)
    if header.version >= 3:
        xyzw = _smallest_three(s["rotations"].view("<u4"))
    else:
        xyzw = _first_three(s["rotations"].reshape(n, 3))
    quats = np.empty((n, 4), np.float32)
    quats[:, 0], quats[:, 1:] = xyzw[:, 3], xyzw[:, :3]
    dim = SH_DIM[header.sh_degree]
    codes = s["sh"].reshape(n, dim, 3)
    if dim > SH_DIM[3]:
        warnings.warn(f"{where}: SH degree {header.sh_degree} read as degree 3 (the project's largest); "
                      "the degree-4 coefficients are dropped", stacklevel=3)
        codes = codes[:, :SH_DIM[3]]
    sh = codes.astype(np.float32)  # (code - 128) / 128, exact in float32, without an index array
    sh -= np.float32(128.0)
    sh *= np.float32(1.0 / 128.0)
    return GaussianCloud(means=means, scales=_LOG_SCALE_OF_CODE[s["scales"]].reshape(n, 3), quats=quats,
                         opacities=OPACITY_OF_CODE[s["alphas"]], sh_dc=_DC_OF_CODE[s["colors"]].reshape(n, 3),
                         sh_rest=sh)


# ----------------------------------------------------------------------------------- write

def write_spz(cloud: GaussianCloud, path, *, version: int = WRITE_VERSION, sh1_bits: int = DEFAULT_SH1_BITS,
              sh_rest_bits: int = DEFAULT_SH_REST_BITS, compresslevel: int | None = None) -> Path:
    """Write `cloud` as an .spz file (atomic): version 3 (gzip) by default, 2 (gzip, 3-byte
    rotations) or 4 (zstd streams; needs the `zstandard` package). `sh1_bits` / `sh_rest_bits`
    (1..8) are the precision kept for degree-1 and higher SH coefficients (Niantic's defaults 5, 4);
    `compresslevel` the gzip or zstd level (default GZIP_LEVEL, ZSTD_LEVEL).
    Refuses (PlyError) non-finite rows and positions beyond what 24 bits hold; extra properties
    are not stored (a warning says so)."""
    path = Path(path)
    where = str(path)
    if version not in (2, 3, 4):
        raise ValueError(f"write_spz: version must be 2, 3 or 4, not {version}")
    if not (1 <= sh1_bits <= 8 and 1 <= sh_rest_bits <= 8):
        raise ValueError(f"write_spz: SH bits must be 1..8, not {sh1_bits}, {sh_rest_bits}")
    c = writable(cloud, ".spz", where)
    bits = _fractional_bits(c.means, where)
    header = SpzHeader(version, len(c), c.sh_degree, bits, 0)
    streams = _pack(c, header, sh1_bits, sh_rest_bits)
    if version <= 3:
        head = _LEGACY.pack(MAGIC, version, len(c), c.sh_degree, bits, 0, 0)

        def write_body(f) -> None:
            z = zlib.compressobj(GZIP_LEVEL if compresslevel is None else compresslevel, zlib.DEFLATED, 31, 9)
            f.write(z.compress(head))
            for name in STREAMS:
                f.write(z.compress(streams[name]))
            f.write(z.flush())
    else:
        zstd = _zstandard(where)
        compressor = zstd.ZstdCompressor(level=ZSTD_LEVEL if compresslevel is None else compresslevel)
        frames = [(len(streams[name]), compressor.compress(streams[name]))
                  for name in STREAMS if len(streams[name])]
        head = _NGSP.pack(MAGIC, version, len(c), c.sh_degree, bits, 0, len(frames), _NGSP.size)
        toc = b"".join(struct.pack("<QQ", len(frame), size) for size, frame in frames)

        def write_body(f) -> None:
            f.write(head + toc)
            for _, frame in frames:
                f.write(frame)
    return atomic_write(path, write_body)


def _fractional_bits(means: np.ndarray, where: str) -> int:
    """12, or fewer where the largest |coordinate| needs them to fit 24 signed bits."""
    top = float(np.abs(means).max(initial=0.0))
    for bits in range(12, -1, -1):
        if round_half_away(top * 2.0 ** bits) <= _FIXED_MAX:
            return bits
    raise PlyError(f"{where}: a coordinate of {top:g} is beyond what .spz holds (24-bit fixed point, "
                   f"|x| <= {_FIXED_MAX})")


def _pack(c: GaussianCloud, header: SpzHeader, sh1_bits: int, sh_rest_bits: int) -> dict[str, np.ndarray]:
    """The attribute streams (flat uint8), in float32 arithmetic as Niantic's encoder does it."""
    f32 = np.float32
    fixed = round_half_away(c.means * f32(2.0 ** header.fractional_bits)).astype("<i4")
    positions = fixed.reshape(-1, 1).view(np.uint8)[:, :3]
    colors = byte_codes(c.sh_dc * (f32(COLOR_SCALE) * f32(255.0)) + f32(0.5 * 255.0))
    scales = byte_codes((c.scales + f32(10.0)) * f32(16.0))
    rotations = _pack_rotations(c.quats, header.version)
    sh = c.sh_rest
    sh = np.empty(c.sh_rest.shape, np.uint8)
    for lo, hi, bits in ((0, SH_DIM[1], sh1_bits), (SH_DIM[1], sh.shape[1], sh_rest_bits)):
        if hi > lo:  # round(128 x) + 128, then to the nearest multiple of the bucket (exact in float32)
            q = round_half_away(c.sh_rest[:, lo:hi] * f32(128.0)) + f32(128.0)
            bucket = f32(1 << (8 - bits))
            sh[:, lo:hi] = np.clip(np.floor((q + bucket // 2) / bucket) * bucket, 0, 255)
    streams = {"positions": positions, "alphas": opacity_codes(c.opacities), "colors": colors, "scales": scales,
               "rotations": rotations, "sh": sh}
    return {name: np.ascontiguousarray(a).reshape(-1) for name, a in streams.items()}


def _pack_rotations(quats: np.ndarray, version: int) -> np.ndarray:
    f32 = np.float32
    q = np.asarray(quats, f32)[:, [1, 2, 3, 0]]  # x, y, z, w
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(((q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]) + q[:, 3] * q[:, 3])
    good = np.isfinite(norm) & (norm > 1e-12)
    q = np.where(good[:, None], q / np.where(good, norm, f32(1.0))[:, None], f32([0, 0, 0, 1]))
    if version < 3:
        sign = np.where(q[:, 3] < 0, f32(-127.5), f32(127.5))
        return byte_codes(q[:, :3] * sign[:, None] + f32(127.5))
    rows = np.arange(len(q))
    big = np.argmax(np.abs(q), axis=1)
    negate = q[rows, big] < 0
    comp = big.astype(np.uint32) << np.uint32(30)
    for k, shift in enumerate((20, 10, 0)):
        v = q[rows, _OTHERS[big, k]]
        neg = (v < 0) ^ negate
        mag = np.minimum((f32(511.0) * (np.abs(v) / _SQRT1_2) + f32(0.5)).astype(np.uint32), 511)
        comp |= ((neg.astype(np.uint32) << np.uint32(9)) | mag) << np.uint32(shift)
    return comp.astype("<u4").view(np.uint8)
