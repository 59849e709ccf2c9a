"""PlayCanvas's SOG ("spatially ordered Gaussians"): SuperSplat's web export, quantised into WebP images.

A scene is a `meta.json` and lossless WebP images of W x H RGBA pixels, one pixel per Gaussian in
row-major order (W = 4 * ceil(sqrt(N) / 4), H = 4 * ceil(N / W / 4), as splat-transform makes them;
any size with W * H >= N reads). Bundled, they are one `.sog` file, a zip (stored, not deflated)
holding `meta.json` and the images; unbundled, a folder with `meta.json` beside them.
meta.json (version 2, what splat-transform 3.x and SuperSplat write):

    {"version": 2, "count": N, "asset": {"generator": ...},
     "means":  {"mins": [3], "maxs": [3], "files": ["means_l.webp", "means_u.webp"]},
     "scales": {"codebook": [256], "files": ["scales.webp"]},
     "quats":  {"files": ["quats.webp"]},
     "sh0":    {"codebook": [256], "files": ["sh0.webp"]},
     "shN":    {"count": M, "bands": 1..3, "codebook": [256],
                "files": ["shN_centroids.webp", "shN_labels.webp"]}}      (only with SH rest)

- means_l / means_u: the low and high bytes (R, G, B = x, y, z) of a 16-bit code of
  v = sign(x) ln(|x| + 1) between mins and maxs (of v): x = sign(v) (exp(|v|) - 1),
  v = min + (max - min) code / 65535 (max - min taken as 1 when zero);
- quats: the unit quaternion (rot_0..3 = w, x, y, z) made positive in its largest component; the
  other three in index order in R, G, B as code / 255 * 2 - 1 = sqrt(2) q_i; A = 252 + the index of
  the largest, which is sqrt(1 - sum of the others' squares) (another A: identity);
- scales: R, G, B index the 256 log-scales of the codebook (one codebook for the three axes);
- sh0: R, G, B index the 256 f_dc values of its codebook; A = opacity code: the logit of
  code / 255 clamped to [1e-6, 1 - 1e-6] (so the end codes read as +-13.8, opacity 1e-6 and
  1 - 1e-6: invisible and opaque, as splat-transform reads them);
- shN: a palette of M entries (M <= 65536) of 3K coefficients (K = 3, 8, 15 for bands 1..3): the
  16-bit label of each Gaussian (R low byte, G high byte) picks entry m, stored in
  shN_centroids (64 K wide, ceil(M / 64) high) at row m // 64, columns (m % 64) K + j for
  coefficient j, whose R, G, B index the codebook for the red, green and blue f_rest of that
  coefficient; labels >= M read as zero (as splat-transform does).
Version 1 (meta.json without "version": per-channel mins/maxs instead of codebooks, the opacity a
lerped logit) is read too. Streamed SOG (`lod-meta.json`) is not a single scene: refused.

Reading decodes as splat-transform does (float64, rounded to float32 at the end), so both give the
same values. Writing (`write_sog`): rows in Morton order of their positions (as splat-transform:
neighbours in the images compress better; `morton=False` keeps the cloud's order), codes rounded to
nearest (splat-transform truncates, which doubles the error), codebooks by `_quantize.codebook_1d`
and the SH palette by `_quantize.kmeans` (M = 1024 * min(64, 2**floor(log2(N / 1024))) entries, as
splat-transform; seeded: the same cloud gives the same file). Bounds: position (|x| + 1) times
half a step, (max - min) / 131070, of its axis; rotation 1/255/sqrt 2 ~ 0.0028 for the three smaller
components, three times that for the largest (derived from them); opacity 0.5/255 after the
sigmoid; log-scale and f_dc the nearest codebook entry. Against splat-transform on the same cloud:
half its error where it truncates, a little more where its codebooks and k-means do better
(docs/benchmarks/formats.md).
Extra properties are not stored (a warning says so); non-finite rows are refused.

The WebP images go through a `WebpCodec`: Pillow's by default (`pillow_webp`; lossless, keeping
the colour of transparent pixels); Blender, which bundles no Pillow, passes one built on its own
image loader and writer.
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from ..atomic import atomic_write
from ..cloud import GaussianCloud
from ..conventions import SH_DEGREE_OF_REST, SH_REST_COUNTS
from ..ply import PlyError, drop_nonfinite
from ._codec import opacity_codes, unorm_codes, writable
from ._quantize import codebook_1d, kmeans

__all__ = ["WebpCodec", "pillow_webp", "read_sog", "write_sog", "is_sog_name", "looks_like_sog",
           "morton_order", "palette_size", "META_NAME"]

META_NAME = "meta.json"
ZIP_MAGIC = b"PK\x03\x04"
#: splat-transform's clamp of the decoded opacity before its logit.
OPACITY_EPS = 1e-6
#: Rounds of k-means for the SH palette (splat-transform's `--sh-iterations` default).
SH_ITERATIONS = 10
_TEXTURE_NAMES = {"means": ("means_l.webp", "means_u.webp"), "scales": ("scales.webp",),
                  "quats": ("quats.webp",), "sh0": ("sh0.webp",),
                  "shN": ("shN_centroids.webp", "shN_labels.webp")}
_MAX_META_BYTES = 1 << 24
_MAX_IMAGE_BYTES = 1 << 30
_SQRT2 = math.sqrt(2.0)
# For each index of the largest component, the indices of the other three (index order).
_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])


@dataclass(frozen=True)
class WebpCodec:
    """Lossless WebP both ways: `decode(bytes) -> (H, W, 4) uint8 RGBA` (raising on bad data) and
    `encode((H, W, 4) uint8) -> bytes`."""

    name: str
    decode: Callable[[bytes], np.ndarray]
    encode: Callable[[np.ndarray], bytes]


def pillow_webp() -> WebpCodec:
    """The WebP codec of Pillow (a dependency of gvae_core); PlyError when this Pillow lacks WebP."""
    try:
        from PIL import Image, features  # noqa: PLC0415 - only SOG needs images
    except ImportError:
        raise PlyError("SOG files hold WebP images: reading or writing them needs Pillow (pip install pillow)") \
            from None
    if not features.check("webp"):
        raise PlyError("SOG files hold WebP images: this Pillow was built without WebP support")

    def decode(data: bytes) -> np.ndarray:
        with Image.open(io.BytesIO(data), formats=["WEBP"]) as im:
            return np.asarray(im.convert("RGBA"))

    def encode(rgba: np.ndarray) -> bytes:
        buf = io.BytesIO()
        # quality (effort) 50, method 2: the size of the default (80, 4) on SOG's images, 3x faster
        Image.fromarray(np.ascontiguousarray(rgba, np.uint8), "RGBA").save(buf, "WEBP", lossless=True, exact=True,
                                                                            quality=50, method=2)
        return buf.getvalue()

    return WebpCodec("Pillow", decode, encode)


def is_sog_name(path) -> bool:
    """Whether a name asks for SOG: a `.sog` bundle or a `meta.json` (any name ending so, as
    splat-transform reads them, except a streamed `lod-meta.json`)."""
    name = Path(path).name.lower()
    return name.endswith(".sog") or (name.endswith(META_NAME) and not name.endswith("lod-meta.json"))


def looks_like_sog(path, head: bytes) -> bool:
    """Whether a file (or folder) starting with `head` is a SOG scene: a folder with meta.json, a
    zip, or the start of a JSON object ('{' then a key or '}')."""
    path = Path(path)
    if path.is_dir():
        return (path / META_NAME).is_file()
    text = head.lstrip(b" \t\r\n\xef\xbb\xbf")
    return head.startswith(ZIP_MAGIC) or (text[:1] == b"{" and text[1:].lstrip(b" \t\r\n")[:1] in (b'"', b"}"))


# ------------------------------------------------------------------------------------ read

class _Files:
    """The files of a SOG scene, by the names meta.json gives: members of the zip, or files in the
    folder of meta.json."""

    def __init__(self, path: Path, where: str):
        self.where = where
        self.zip = None
        if path.is_dir():
            path = path / META_NAME
        self.folder = path.parent
        self.meta_name = path.name
        with open(path, "rb") as f:
            head = f.read(4)
        if head.startswith(ZIP_MAGIC):
            try:
                self.zip = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                raise PlyError(f"{where}: not a readable .sog (zip) file: {exc}") from None
            self.meta_name = META_NAME

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()

    def read(self, name: str, limit: int = _MAX_IMAGE_BYTES) -> bytes:
        """The bytes of the file `name` (at most `limit` of them, or a PlyError)."""
        if not isinstance(name, str) or not name or PurePosixPath(name).is_absolute() or ".." in Path(name).parts \
                or "\\" in name:
            raise PlyError(f"{self.where}: meta.json names a file {name!r} outside the scene")
        try:
            if self.zip is not None:
                size = self.zip.getinfo(name).file_size
            else:
                size = (self.folder / name).stat().st_size
            if size > limit:
                raise PlyError(f"{self.where}: {name} is {size} bytes, more than this reader takes ({limit})")
            return self.zip.read(name) if self.zip is not None else (self.folder / name).read_bytes()
        except PlyError:
            raise
        except KeyError:
            raise PlyError(f"{self.where}: the .sog bundle has no {name}") from None
        except FileNotFoundError:
            raise PlyError(f"{self.where}: missing {name} beside {self.meta_name}") from None
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
            raise PlyError(f"{self.where}: cannot read {name}: {exc}") from None


class _Meta:
    """Checked access to meta.json's fields: a PlyError naming the field when one is missing or wrong."""

    def __init__(self, meta, where: str):
        if not isinstance(meta, dict):
            raise PlyError(f"{where}: meta.json is not a JSON object")
        self.meta, self.where = meta, where

    def get(self, *keys, kind=None, optional: bool = False):
        value = self.meta
        for key in keys:
            if not isinstance(value, dict) or key not in value:
                if optional:
                    return None
                raise PlyError(f"{self.where}: meta.json has no {'.'.join(keys)}")
            value = value[key]
        if kind is not None and not _is(value, kind):
            raise PlyError(f"{self.where}: meta.json {'.'.join(keys)} must be {kind}, not {json.dumps(value)[:60]}")
        return value

    def numbers(self, *keys, size: int | None = None) -> np.ndarray:
        """A list of numbers as float64 (null, as JSON writes NaN and infinities, reads as NaN)."""
        value = self.get(*keys, kind="a list")
        if not all(v is None or _is(v, "a number") for v in value) or (size is not None and len(value) != size):
            raise PlyError(f"{self.where}: meta.json {'.'.join(keys)} must be "
                           f"{'a list of numbers' if size is None else f'{size} numbers'}")
        return np.array([np.nan if v is None else v for v in value], np.float64)

    def files(self, key: str, count: int) -> list[str]:
        files = self.get(key, "files", kind="a list")
        if len(files) < count or not all(isinstance(f, str) for f in files[:count]):
            raise PlyError(f"{self.where}: meta.json {key}.files must name {count} image(s)")
        return files[:count]


def _is(value, kind: str) -> bool:
    if kind == "a number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind == "a count":
        return isinstance(value, int) and not isinstance(value, bool) and value >= 0
    if kind == "a list":
        return isinstance(value, list)
    return True


def read_sog(path, *, sanitize: bool = False, webp: WebpCodec | None = None) -> GaussianCloud:
    """Read a SOG scene into a numpy GaussianCloud: a `.sog` bundle, a `meta.json` or the folder
    holding it (versions 1 and 2, SH degree from `shN.bands`). `webp` decodes the images (default:
    `pillow_webp()`). Bad or truncated files raise PlyError naming the file and the problem;
    non-finite values follow `ply.drop_nonfinite` (refused, or dropped with `sanitize`)."""
    path = Path(path)
    where = str(path)
    if path.name.lower().endswith("lod-meta.json"):
        raise PlyError(f"{where}: a streamed SOG scene (lod-meta.json, levels of detail), not one scene: "
                       "convert it to one .sog with splat-transform first")
    files = _Files(path, where)
    try:
        raw = files.read(files.meta_name, _MAX_META_BYTES)
        try:
            parsed = json.loads(raw.decode("utf-8-sig"))
        except (UnicodeDecodeError, ValueError) as exc:
            raise PlyError(f"{where}: meta.json is not valid JSON: {exc}") from None
        meta = _Meta(parsed, where)
        version = meta.get("version", optional=True)
        if version is None:
            cloud = _decode_v1(meta, files, webp or pillow_webp())
        elif version == 2:
            cloud = _decode_v2(meta, files, webp or pillow_webp())
        else:
            raise PlyError(f"{where}: SOG version {json.dumps(version)[:20]}; this reader knows versions 1 and 2")
    finally:
        files.close()
    finite = np.ones(len(cloud), bool)
    for a in (cloud.means, cloud.scales, cloud.sh_dc, cloud.opacities, cloud.sh_rest):
        if not np.isfinite(a.sum()):
            finite &= np.isfinite(a.reshape(len(cloud), -1)).all(1)
    return drop_nonfinite(cloud, finite, where, sanitize, stacklevel=3)


def _image(files: _Files, name: str, webp: WebpCodec) -> np.ndarray:
    """The decoded image `name`, (H, W, 4) uint8."""
    data = files.read(name)
    try:
        rgba = np.asarray(webp.decode(data))
    except PlyError:
        raise
    except Exception as exc:  # each decoder fails in its own way on bad data
        raise PlyError(f"{files.where}: {name} is not a readable WebP image ({type(exc).__name__}: {exc})") from None
    if rgba.ndim != 3 or rgba.shape[2] != 4 or rgba.dtype != np.uint8:
        raise PlyError(f"{files.where}: {name} did not decode to RGBA bytes")
    return rgba


def _texture(files: _Files, name: str, count: int, webp: WebpCodec) -> np.ndarray:
    """The first `count` pixels (count, 4) of the image `name`, one per Gaussian."""
    rgba = _image(files, name, webp)
    if rgba.shape[0] * rgba.shape[1] < count:
        raise PlyError(f"{files.where}: {name} holds {rgba.shape[0] * rgba.shape[1]} pixels, fewer than the "
                       f"{count} Gaussians of meta.json")
    return rgba.reshape(-1, 4)[:count]


def _positions(meta: _Meta, files: _Files, count: int, webp: WebpCodec) -> np.ndarray:
    lo_name, hi_name = meta.files("means", 2)
    lo, hi = _texture(files, lo_name, count, webp), _texture(files, hi_name, count, webp)
    mins, maxs = meta.numbers("means", "mins", size=3), meta.numbers("means", "maxs", size=3)
    code = (lo[:, :3].astype(np.uint16) | (hi[:, :3].astype(np.uint16) << 8)).astype(np.float64)
    span = maxs - mins
    span[span == 0] = 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        v = mins + span * (code / 65535.0)
        return (np.sign(v) * (np.exp(np.abs(v)) - 1.0)).astype(np.float32)


def _quaternions(meta: _Meta, files: _Files, count: int, webp: WebpCodec) -> np.ndarray:
    q = _texture(files, meta.files("quats", 1)[0], count, webp)
    small = [(q[:, i] / 255.0 * 2.0 - 1.0) / _SQRT2 for i in range(3)]
    big = q[:, 3].astype(np.int64) - 252
    largest = np.sqrt(np.maximum(0.0, 1.0 - (small[0] * small[0] + small[1] * small[1] + small[2] * small[2])))
    out = np.empty((count, 4), np.float32)
    for j in range(4):  # component j is the largest, or the j-th or (j-1)-th of the other three
        below = small[j] if j < 3 else largest
        above = small[j - 1] if j > 0 else largest
        out[:, j] = np.where(big == j, largest, np.where(big > j, below, above))
    out[(big < 0) | (big > 3)] = (1.0, 0.0, 0.0, 0.0)  # not a tag: the identity, as splat-transform
    return out


def _lookup(codebook: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """codebook[codes] in float32, codes beyond the codebook NaN."""
    table = np.full(256, np.nan, np.float32)
    table[:min(256, len(codebook))] = codebook[:256]
    return table[codes]


def _palette(centroids: np.ndarray, k: int, entries: int, decode) -> np.ndarray:
    """(entries + 1, k, 3) SH rest of each palette entry, from the palette image (64 entries of k
    pixels per row; R, G, B the red, green and blue codes, which `decode` turns into values), and a
    last entry of zeros for labels beyond the palette."""
    rows, width = centroids.shape[:2]
    codes = centroids.reshape(rows * (width // k), k, 4)[:entries, :, :3]
    out = np.zeros((entries + 1, k, 3), np.float32)
    out[:entries] = decode(codes)
    return out


def _sh_rest(files: _Files, name: str, count: int, webp: WebpCodec, palette: np.ndarray) -> np.ndarray:
    """The SH rest of every Gaussian: its label's palette entry (zeros for labels beyond it)."""
    lab = _texture(files, name, count, webp)
    labels = lab[:, 0].astype(np.intp) | (lab[:, 1].astype(np.intp) << 8)
    return np.take(palette, np.minimum(labels, len(palette) - 1), axis=0)


def _decode_v2(meta: _Meta, files: _Files, webp: WebpCodec) -> GaussianCloud:
    count = meta.get("count", kind="a count")
    means = _positions(meta, files, count, webp)
    quats = _quaternions(meta, files, count, webp)
    scales = _lookup(meta.numbers("scales", "codebook").astype(np.float32),
                     _texture(files, meta.files("scales", 1)[0], count, webp)[:, :3])
    sh0 = _texture(files, meta.files("sh0", 1)[0], count, webp)
    sh_dc = _lookup(meta.numbers("sh0", "codebook").astype(np.float32), sh0[:, :3])
    p = np.clip(np.arange(256) / 255.0, OPACITY_EPS, 1.0 - OPACITY_EPS)
    opacities = np.log(p / (1.0 - p)).astype(np.float32)[sh0[:, 3]]
    bands = meta.get("shN", "bands", optional=True) if meta.get("shN", optional=True) is not None else 0
    if bands not in (0, 1, 2, 3):
        raise PlyError(f"{files.where}: meta.json shN.bands must be 0..3, not {json.dumps(bands)[:20]}")
    k = SH_REST_COUNTS[bands]
    sh_rest = np.zeros((count, 0, 3), np.float32)
    if k:
        palette = meta.get("shN", "count", kind="a count")
        book = meta.numbers("shN", "codebook").astype(np.float32)
        cen_name, lab_name = meta.files("shN", 2)
        centroids = _image(files, cen_name, webp)
        if centroids.shape[1] != 64 * k:
            raise PlyError(f"{files.where}: {cen_name} is {centroids.shape[1]} pixels wide; a palette of "
                           f"{bands}-band SH is {64 * k}")
        if palette > 64 * centroids.shape[0]:
            raise PlyError(f"{files.where}: meta.json shN.count is {palette}; {cen_name} holds "
                           f"{64 * centroids.shape[0]} palette entries")
        sh_rest = _sh_rest(files, lab_name, count, webp, _palette(centroids, k, palette, lambda c: _lookup(book, c)))
    return GaussianCloud(means=means, scales=scales, quats=quats, opacities=opacities, sh_dc=sh_dc, sh_rest=sh_rest)


def _decode_v1(meta: _Meta, files: _Files, webp: WebpCodec) -> GaussianCloud:
    shape = meta.get("means", "shape", kind="a list")
    if not shape or not _is(shape[0], "a count"):
        raise PlyError(f"{files.where}: meta.json means.shape must start with the Gaussian count")
    count = shape[0]

    def lerp(key: str, codes: np.ndarray, size: int) -> np.ndarray:
        lo, hi = meta.numbers(key, "mins", size=size), meta.numbers(key, "maxs", size=size)
        return (lo + (hi - lo) * (codes / 255.0)).astype(np.float32)

    means = _positions(meta, files, count, webp)
    quats = _quaternions(meta, files, count, webp)
    scales = lerp("scales", _texture(files, meta.files("scales", 1)[0], count, webp)[:, :3], 3)
    sh0 = lerp("sh0", _texture(files, meta.files("sh0", 1)[0], count, webp), 4)
    sh_rest = np.zeros((count, 0, 3), np.float32)
    if meta.get("shN", optional=True) is not None:
        cen_name, lab_name = meta.files("shN", 2)
        centroids = _image(files, cen_name, webp)
        bands = {192: 1, 512: 2, 960: 3}.get(centroids.shape[1])
        if bands is None:
            raise PlyError(f"{files.where}: {cen_name} is {centroids.shape[1]} pixels wide; a version-1 SH palette "
                           "is 192, 512 or 960")
        k = SH_REST_COUNTS[bands]
        lo, hi = (meta.get("shN", key, kind="a number") for key in ("mins", "maxs"))
        entries = (centroids.shape[1] // k) * centroids.shape[0]
        palette = _palette(centroids, k, entries, lambda c: lo + (hi - lo) * (c / 255.0))
        sh_rest = _sh_rest(files, lab_name, count, webp, palette)
    return GaussianCloud(means=means, scales=scales, quats=quats, opacities=np.ascontiguousarray(sh0[:, 3]),
                         sh_dc=np.ascontiguousarray(sh0[:, :3]), sh_rest=sh_rest)


# ----------------------------------------------------------------------------------- write

def palette_size(n: int) -> int:
    """splat-transform's SH palette size for n Gaussians: 1024 * min(64, 2**floor(log2(n / 1024)))."""
    if n <= 0:
        return 0
    return int(min(64.0, 2.0 ** math.floor(math.log2(n / 1024.0))) * 1024)


def texture_size(n: int) -> tuple[int, int]:
    """(width, height) of the images for n Gaussians, splat-transform's (at least 4 x 4)."""
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    return width, max(4, math.ceil(n / width / 4) * 4)


def morton_order(means: np.ndarray) -> np.ndarray:
    """Row order along a Morton (Z-order) curve over 10-bit cells of the bounding box (stable)."""
    p = np.asarray(means, np.float64)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    lo, hi = p.min(0), p.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    cells = np.clip(((p - lo) / span * 1024.0).astype(np.int64), 0, 1023).astype(np.uint64)
    code = np.zeros(len(p), np.uint64)
    for axis in range(3):
        v = cells[:, axis]
        for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        code |= v << np.uint64(2 - axis)
    return np.argsort(code, kind="stable")


def write_sog(cloud: GaussianCloud, path, *, webp: WebpCodec | None = None, morton: bool = True,
              iterations: int = SH_ITERATIONS, seed: int = 0) -> Path:
    """Write `cloud` as a SOG scene (version 2): a `.sog` bundle, or with a name ending in
    `meta.json` that file and its images beside it (means_l.webp ... shN_labels.webp, replaced;
    the folder is made when missing).
    Rows in Morton order unless `morton` is false; the SH palette by `iterations` rounds of
    k-means from `seed`. `webp` encodes the images (default: `pillow_webp()`). Nothing is written
    until every image is encoded, and each file atomically. Non-finite rows are refused
    (PlyError); extra properties are not stored (a warning says so)."""
    path = Path(path)
    where = str(path)
    c = writable(cloud, "SOG", where)
    webp = webp or pillow_webp()
    images, meta = encode_sog(c, morton=morton, iterations=iterations, seed=seed)
    files = {name: webp.encode(rgba) for name, rgba in images.items()}
    meta_bytes = json.dumps(meta, separators=(",", ":")).encode("utf-8")
    if path.name.lower().endswith(META_NAME):
        path.parent.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            atomic_write(path.parent / name, lambda f, d=data: f.write(d))
        return atomic_write(path, lambda f: f.write(meta_bytes))

    def write_zip(f) -> None:
        with zipfile.ZipFile(f, "w", zipfile.ZIP_STORED) as z:
            z.writestr(_zip_info(META_NAME), meta_bytes)
            for name, data in files.items():
                z.writestr(_zip_info(name), data)

    return atomic_write(path, write_zip)


def _zip_info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))  # the same cloud gives the same bytes
    info.compress_type = zipfile.ZIP_STORED
    return info


def encode_sog(c: GaussianCloud, *, morton: bool = True, iterations: int = SH_ITERATIONS,
               seed: int = 0) -> tuple[dict[str, np.ndarray], dict]:
    """The images ((H, W, 4) uint8 by file name) and meta.json (a dict) of a finite numpy cloud."""
    n = len(c)
    order = morton_order(c.means) if morton else np.arange(n)
    width, height = texture_size(n)

    def image(pixels: np.ndarray, rows: int = height, cols: int = width) -> np.ndarray:
        out = np.zeros((rows * cols, 4), np.uint8)
        out[:len(pixels)] = pixels
        return out.reshape(rows, cols, 4)

    def with_alpha(rgb: np.ndarray, alpha=255) -> np.ndarray:
        out = np.empty((len(rgb), 4), np.uint8)
        out[:, :3] = rgb
        out[:, 3] = alpha
        return out

    means = c.means[order].astype(np.float64)
    v = np.sign(means) * np.log(np.abs(means) + 1.0)
    mins, maxs = (v.min(0), v.max(0)) if n else (np.zeros(3), np.zeros(3))
    span = np.where(maxs > mins, maxs - mins, 1.0)
    code = unorm_codes(np.where(maxs > mins, (v - mins) / span, 0.0), 65535)
    images = {"means_l.webp": image(with_alpha(code & 0xFF)), "means_u.webp": image(with_alpha(code >> 8))}

    q = c.unit_quats()[order].astype(np.float64)
    rows = np.arange(n)
    big = np.argmax(np.abs(q), axis=1)
    q = np.where((q[rows, big] < 0)[:, None], -q, q)
    small = np.stack([q[rows, _OTHERS[big, k]] for k in range(3)], 1) if n else np.zeros((0, 3))
    images["quats.webp"] = image(with_alpha(unorm_codes(small * (_SQRT2 * 0.5) + 0.5, 255), 252 + big))

    scale_book, scale_codes = codebook_1d(c.scales[order])
    images["scales.webp"] = image(with_alpha(scale_codes))
    dc_book, dc_codes = codebook_1d(c.sh_dc[order])
    images["sh0.webp"] = image(with_alpha(dc_codes, opacity_codes(c.opacities[order])))
    meta = {"version": 2, "asset": {"generator": "gvae_core"}, "count": n,
            "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": list(_TEXTURE_NAMES["means"])},
            "scales": {"codebook": scale_book.tolist(), "files": list(_TEXTURE_NAMES["scales"])},
            "quats": {"files": list(_TEXTURE_NAMES["quats"])},
            "sh0": {"codebook": dc_book.tolist(), "files": list(_TEXTURE_NAMES["sh0"])}}
    k = c.sh_rest.shape[1]
    if k and n:
        rest = c.sh_rest[order].transpose(0, 2, 1).reshape(n, 3 * k)  # channel-major, as the palette
        centroids, labels = kmeans(rest, palette_size(n), iterations=iterations, seed=seed)
        m = len(centroids)
        sh_book, sh_codes = codebook_1d(centroids)
        palette = sh_codes.reshape(m, 3, k).transpose(0, 2, 1).reshape(m * k, 3)  # entry-major pixels
        cen = image(with_alpha(palette), rows=-(-m // 64), cols=64 * k)
        images["shN_centroids.webp"] = cen
        images["shN_labels.webp"] = image(with_alpha(np.stack([labels & 0xFF, labels >> 8, 0 * labels], 1)))
        meta["shN"] = {"count": m, "bands": SH_DEGREE_OF_REST[k], "codebook": sh_book.tolist(),
                       "files": list(_TEXTURE_NAMES["shN"])}
    return images, meta
