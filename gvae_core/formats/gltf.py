"""glTF 2.0 splats: Khronos's `KHR_gaussian_splatting` in a `.glb`, or a `.gltf` with its buffers.

A splat is a mesh primitive of mode POINTS (0) whose `extensions` hold `KHR_gaussian_splatting`
({"kernel": "ellipse", "colorSpace": "srgb_rec709_display", ...}), one point per Gaussian:

    POSITION                                   VEC3   the centre (float; KHR_mesh_quantization's integers read too)
    KHR_gaussian_splatting:ROTATION            VEC4   unit quaternion x, y, z, w (float, normalised byte/short)
    KHR_gaussian_splatting:SCALE               VEC3   linear scale, exp(log-scale) (float, (normalised) ubyte/ushort)
    KHR_gaussian_splatting:OPACITY             SCALAR linear opacity, sigmoid(logit) (float, normalised ubyte/ushort)
    KHR_gaussian_splatting:SH_DEGREE_0_COEF_0  VEC3   f_dc (r, g, b)
    KHR_gaussian_splatting:SH_DEGREE_l_COEF_n  VEC3   f_rest of degree l = 1..3, n = 0..2l (m = n - l), each degree
                                                      complete and the lower ones present; n = 0 is `sh_rest[:, l²-1]`

Any accessor is read as glTF defines it: every component type, `normalized` (signed: max(c / (2^(b-1) - 1), -1),
unsigned: c / (2^b - 1)), byteStride, sparse accessors, accessors without a buffer view (zeros).
Buffers: the GLB's BIN chunk, files beside the .gltf (relative URIs) or base64 data URIs.

Frames. glTF is right-handed with +Y up and +Z forward (x left); a 3DGS PLY is x right, y down,
z forward. The two differ by 180 degrees about z, applied on the way in and out exactly
(`transform.flip_axes`: signs of x and y, of the quaternion's x and y, and of the SH coefficients
odd in (x, y)), so a PLY written as .glb and read back has its own frame again, bit for bit.
The splats of a node are in its local space: the node's global matrix (matrix or TRS, through the
scene's hierarchy) is applied to centres, covariances and SH (`transform.affine`). Every splat
primitive of the default scene is read (one after the other, SH raised to the largest degree).

SPZ companion (`KHR_gaussian_splatting_compression_spz_2` inside the primitive's
KHR_gaussian_splatting object, {"bufferView": i}): the buffer view holds an .spz file (read by
`spz.decode_spz`), which the extension unpacks into glTF's left-up-front frame from SPZ's
right-up-back one: x and z change sign, then glTF's frame as above (in all: y and z flip).

Files written by splat-transform before 2.7.0 (its `asset.generator` says "splat-transform X.Y.Z")
hold log-scales in SCALE, and before 2.0 also the PLY's frame unchanged (checked in 1.10.1, 2.3.1,
2.7.1, 3.7.0); they are read as written, with a warning. Any other file with a negative SCALE is
read as log-scales too (the drafts before the ratified text stored them so; a warning says so).

Reading keeps the raw parameters: log-scale = ln(SCALE) and logit = ln(p / (1 - p)) in float64,
rounded to float32; an OPACITY of exactly 0 or 1 is a logit of -inf / +inf and a SCALE of 0 a flat
axis, read as what they mean (`ply.drop_nonfinite`); an OPACITY outside [0, 1] is refused (or its
rows dropped with `sanitize`). COLOR_0 (a fallback colour) is not read. What else the file holds
(other meshes, materials, images, cameras, animations, ...) is left alone and named in a warning,
as are attributes of the splat primitive that are not read. A file without splats is refused with
a message that says to use a glTF importer.

Writing (`write_gltf`): one node, one mesh, one primitive, every attribute float32 in its own
tightly packed buffer view (as splat-transform writes them), in glTF's frame; SCALE = exp and
OPACITY = sigmoid computed in float64, rounded to float32; quaternions normalised (float64; zero:
the identity); COLOR_0 as normalised ubyte RGBA, the diffuse colour SH_C0 f_dc + 0.5 clamped to
[0, 1] and decoded from sRGB to linear as the extension says, alpha the opacity.
`colorSpace` "srgb_rec709_display" (3DGS colours are fitted to sRGB-encoded images). So PLY -> glTF
-> PLY gives positions, SH and (normalised) rotations back exactly; log-scales within float32
rounding of exp and ln (|error| <= 2^-24 + half an ulp of the value); opacities within float32
rounding of the sigmoid and of the logit read back (2^-25 + a quarter of the logit's ulp); logits
above 17.3 come back as fully opaque (+inf, read as 50) and below -103 as fully transparent.
Extra properties are not stored (a warning says so). A .glb holds at most 4 GiB (about 17M
Gaussians of SH degree 3); a .gltf writes NAME.bin beside it.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import os
import re
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote, unquote

import numpy as np

from .. import quaternions
from ..atomic import atomic_write
from ..cloud import GaussianCloud
from ..conventions import SH_C0, SH_REST_COUNTS, sigmoid, srgb_to_linear
from ..ply import PlyError, drop_nonfinite
from ..transform import affine, flip_axes, sh_rotation
from ._codec import writable
from .spz import decode_spz

__all__ = ["read_gltf", "write_gltf", "has_splats", "is_gltf_name", "looks_like_gltf", "EXTENSION", "SPZ_EXTENSION",
           "PLY_TO_GLTF"]

EXTENSION = "KHR_gaussian_splatting"
SPZ_EXTENSION = "KHR_gaussian_splatting_compression_spz_2"
#: Signs of x, y, z between a 3DGS PLY's frame and glTF's (180 degrees about z; its own inverse).
PLY_TO_GLTF = (-1.0, -1.0, 1.0)
#: SPZ's right-up-back frame to glTF's left-up-front one, as the SPZ companion extension unpacks it.
SPZ_TO_GLTF = (-1.0, 1.0, -1.0)
GLB_MAGIC = b"glTF"
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942
_GLB_HEADER = struct.Struct("<4sII")
_CHUNK_HEADER = struct.Struct("<II")
_MAX_JSON_BYTES = 1 << 28
_GLB_LIMIT = 2 ** 32 - 1
#: component type -> (numpy dtype, the divisor of a normalised integer)
_COMPONENTS = {5120: ("i1", 127.0), 5121: ("u1", 255.0), 5122: ("<i2", 32767.0), 5123: ("<u2", 65535.0),
               5125: ("<u4", 4294967295.0), 5126: ("<f4", None)}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_FLOAT, _UBYTE, _ARRAY_BUFFER = 5126, 5121, 34962
_POINTS = 0
_MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES", 5: "TRIANGLE_STRIP",
          6: "TRIANGLE_FAN"}
ROTATION, SCALE, OPACITY = (f"{EXTENSION}:{name}" for name in ("ROTATION", "SCALE", "OPACITY"))
#: Extensions of the primitive or its data that this reader decodes (others are refused where splats use them).
_KNOWN_PRIMITIVE_EXTENSIONS = {EXTENSION}
#: splat-transform wrote log-scales before this version, and the PLY's frame before 2.0.
_LINEAR_SCALE_SINCE, _GLTF_FRAME_SINCE = (2, 7, 0), (2, 0, 0)
#: Rows the writer makes and writes at a time (about 4 MB of attributes at SH degree 3).
_WRITE_ROWS = 16384
#: Rows per block of the SH transposes (a block of SH degree 3 is 180 kB; measured best of 512..16384).
_BLOCK_ROWS = 1024
_GENERATOR = re.compile(r"^\s*splat-transform v?(\d+)\.(\d+)\.(\d+)")


def sh_attribute(degree: int, n: int) -> str:
    """The attribute name of SH coefficient n (0..2 degree) of `degree`."""
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{n}"


def is_gltf_name(path) -> bool:
    name = Path(path).name.lower()
    return name.endswith(".glb") or name.endswith(".gltf")


def looks_like_gltf(path, head: bytes) -> bool:
    """Whether a file starting with `head` is glTF: a GLB ("glTF" magic), or a JSON object that names
    glTF's `asset` and no SOG field (`means`), or any JSON object named .gltf."""
    if head.startswith(GLB_MAGIC):
        return True
    text = head.lstrip(b" \t\r\n\xef\xbb\xbf")
    if text[:1] != b"{":
        return False
    if Path(path).name.lower().endswith(".gltf"):
        return True
    return b'"asset"' in head and b'"means"' not in head and (b'"accessors"' in head or b'"version"' in head)


# ------------------------------------------------------------------------------------ read

@dataclass
class _Source:
    """Where a buffer's bytes are: `length` bytes from byte `start` of the file `path`, or in `data`
    (a data URI's). Read on demand, into fresh arrays, so that a reader never holds the whole file."""

    length: int
    path: Path | None = None
    start: int = 0
    data: np.ndarray | None = None


@dataclass
class _Document:
    """A parsed glTF file: its JSON and checked access to buffers, views and accessors (closed by
    `close`: the files it read from)."""

    gltf: dict
    where: str
    folder: Path
    glb_bin: _Source | None
    buffers: dict[int, _Source] = field(default_factory=dict)
    files: dict[Path, object] = field(default_factory=dict)

    def fail(self, message: str):
        raise PlyError(f"{self.where}: {message}")

    def close(self) -> None:
        for f in self.files.values():
            f.close()
        self.files.clear()

    def items(self, key: str) -> list:
        value = self.gltf.get(key, [])
        if not isinstance(value, list):
            self.fail(f"'{key}' must be a list")
        return value

    def item(self, key: str, index, what: str) -> dict:
        items = self.items(key)
        if not _is_int(index) or not 0 <= index < len(items) or not isinstance(items[index], dict):
            self.fail(f"{what} refers to {key}[{json.dumps(index)[:20]}], which the file does not have "
                      f"({len(items)} {key})")
        return items[index]

    def number(self, obj: dict, key: str, what: str, default=None, minimum: int = 0) -> int:
        value = obj.get(key, default)
        if not _is_int(value) or value < minimum:
            self.fail(f"{what}.{key} must be an integer >= {minimum}, not {json.dumps(value)[:30]}")
        return value

    def read(self, source: _Source, offset: int, nbytes: int, out: np.ndarray | None = None) -> np.ndarray:
        """`nbytes` bytes from `offset` of a buffer (checked to lie in it), into `out` (uint8) or a new
        array."""
        out = np.empty(nbytes, np.uint8) if out is None else out
        if source.data is not None:
            out[:] = source.data[offset:offset + nbytes]
            return out
        f = self.files.get(source.path)
        if f is None:
            f = self.files[source.path] = open(source.path, "rb")  # noqa: SIM115 - closed by close()
        f.seek(source.start + offset)
        if f.readinto(out) != nbytes:
            self.fail(f"truncated while reading {source.path.name} (did the file change?)")
        return out

    def buffer(self, index) -> _Source:
        if index in self.buffers:
            return self.buffers[index]
        buf = self.item("buffers", index, "a buffer view")
        length = self.number(buf, "byteLength", f"buffers[{index}]", minimum=0)
        uri = buf.get("uri")
        if uri is None:
            if index != 0 or self.glb_bin is None:
                self.fail(f"buffers[{index}] has no uri and the file has no GLB binary chunk")
            source = self.glb_bin
        elif not isinstance(uri, str):
            self.fail(f"buffers[{index}].uri must be a string")
        elif uri.startswith("data:"):
            source = self._data_uri(uri, index)
        else:
            source = self._file(uri, index)
        if source.length < length:
            self.fail(f"buffers[{index}] declares {length} bytes; {source.length} are there (truncated?)")
        self.buffers[index] = _Source(length, source.path, source.start, source.data)
        return self.buffers[index]

    def _data_uri(self, uri: str, index: int) -> _Source:
        head, _, payload = uri.partition(",")
        if not head.endswith(";base64"):
            self.fail(f"buffers[{index}] is a data URI that is not base64")
        try:
            data = np.frombuffer(base64.b64decode(payload, validate=True), np.uint8)
        except (binascii.Error, ValueError) as exc:
            self.fail(f"buffers[{index}] holds bad base64 data: {exc}")
        return _Source(len(data), data=data)

    def _file(self, uri: str, index: int) -> _Source:
        if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", uri) or uri.startswith(("/", "\\")):
            self.fail(f"buffers[{index}].uri {uri[:80]!r} is not a relative file name (only files beside "
                      "the .gltf and data URIs are read)")
        path = self.folder / unquote(uri)
        try:
            return _Source(path.stat().st_size, path=path)
        except OSError as exc:
            self.fail(f"cannot read buffers[{index}] from {path}: {exc.strerror or exc}")

    def view(self, index, what: str) -> tuple[_Source, int, int, int | None]:
        """bufferViews[index]: its buffer, byte offset in it, length and byteStride (None: tight)."""
        bv = self.item("bufferViews", index, what)
        where = f"bufferViews[{index}]"
        if bv.get("extensions"):
            self.fail(f"{where} is compressed with {', '.join(bv['extensions'])}, which this reader does not "
                      "decode")
        source = self.buffer(self.number(bv, "buffer", where))
        offset = self.number(bv, "byteOffset", where, default=0)
        length = self.number(bv, "byteLength", where, minimum=1)
        if offset + length > source.length:
            self.fail(f"{where} (bytes {offset}..{offset + length}) runs past the end of its "
                      f"{source.length}-byte buffer")
        stride = bv.get("byteStride")
        if stride is not None and (not _is_int(stride) or not 4 <= stride <= 252):
            self.fail(f"{where}.byteStride must be 4..252, not {json.dumps(stride)[:20]}")
        return source, offset, length, stride

    def locate(self, index, what: str, widths: tuple[int, ...]) -> _Located:
        """Where accessors[index]'s elements are and what they are, checked (nothing read yet)."""
        acc = self.item("accessors", index, what)
        where = f"accessors[{index}] ({what})"
        ctype, kind = _hashable(acc.get("componentType")), _hashable(acc.get("type"))
        if ctype not in _COMPONENTS or kind not in _WIDTHS or _WIDTHS[kind] not in widths:
            self.fail(f"{where} is {kind} of component type {ctype}; expected "
                      f"{'/'.join(k for k, w in _WIDTHS.items() if w in widths)} of a glTF component type")
        count = self.number(acc, "count", where)
        normalized = acc.get("normalized", False) is True
        if normalized and ctype == _FLOAT:
            self.fail(f"{where} is a normalised float")
        dtype, width = _COMPONENTS[ctype][0], _WIDTHS[kind]
        span = None
        if acc.get("bufferView") is not None:
            span = self._span(acc["bufferView"], self.number(acc, "byteOffset", where, default=0), dtype, width,
                              count, None, where)
        return _Located(where, ctype, dtype, width, count, normalized, span, acc.get("sparse"))

    def _span(self, view_index, offset: int, dtype: str, width: int, count: int, stride: int | None,
              where: str) -> tuple[_Source, int, int]:
        """(buffer, byte offset in it, stride) of `count` elements from `offset` of a buffer view, checked."""
        source, view_offset, view_length, view_stride = self.view(view_index, where)
        item = np.dtype(dtype).itemsize
        stride = stride or view_stride or item * width
        end = offset + stride * (count - 1) + item * width if count else offset
        if end > view_length:
            self.fail(f"{where} needs bytes {offset}..{end} of a {view_length}-byte buffer view (truncated?)")
        if stride < item * width:
            self.fail(f"{where}: byteStride {stride} is smaller than an element ({item * width} bytes)")
        return source, view_offset + offset, stride

    def elements(self, span, dtype: str, width: int, count: int) -> np.ndarray:
        """(count, width) elements of `dtype` at `span`, in a new array."""
        source, offset, stride = span
        item = np.dtype(dtype).itemsize
        if stride == item * width:
            return self.read(source, offset, count * stride).view(dtype).reshape(count, width)
        raw = self.read(source, offset, stride * (count - 1) + item * width if count else 0)
        return np.ndarray((count, width), dtype, buffer=raw, strides=(stride, item)).copy()

    def accessor(self, index, what: str, widths: tuple[int, ...]) -> np.ndarray:
        """(count, width) float32 values of accessors[index] as glTF defines them (normalised integers
        divided, sparse values applied; zeros without a buffer view), in a new array."""
        loc = self.locate(index, what, widths)
        if loc.span is None:
            values = np.zeros((loc.count, loc.width), loc.dtype)
        else:
            values = self.elements(loc.span, loc.dtype, loc.width, loc.count)
        if loc.sparse is not None:
            values = self._sparse(loc, values)
        if loc.ctype == _FLOAT:
            return values
        out = values.astype(np.float32)
        if loc.normalized:
            out /= np.float32(_COMPONENTS[loc.ctype][1])
            if loc.dtype.lstrip("<")[0] == "i":
                np.maximum(out, np.float32(-1.0), out=out)
        return out

    def _sparse(self, loc: _Located, values: np.ndarray) -> np.ndarray:
        sparse, where = loc.sparse, loc.where
        if not isinstance(sparse, dict) or not isinstance(sparse.get("indices"), dict) \
                or not isinstance(sparse.get("values"), dict):
            self.fail(f"{where}.sparse must hold count, indices and values")
        n = self.number(sparse, "count", f"{where}.sparse", minimum=1)
        ind, val = sparse["indices"], sparse["values"]
        itype = {5121: "u1", 5123: "<u2", 5125: "<u4"}.get(_hashable(ind.get("componentType")))
        if itype is None:
            self.fail(f"{where}.sparse.indices.componentType must be an unsigned integer type")
        span = self._span(ind.get("bufferView"), self.number(ind, "byteOffset", where, default=0), itype, 1, n,
                          np.dtype(itype).itemsize, f"{where}.sparse.indices")
        idx = self.elements(span, itype, 1, n)[:, 0].astype(np.int64)
        if n and (idx.max() >= loc.count or np.any(np.diff(idx) <= 0)):
            self.fail(f"{where}.sparse.indices must be strictly increasing and below the count {loc.count}")
        span = self._span(val.get("bufferView"), self.number(val, "byteOffset", where, default=0), loc.dtype,
                          loc.width, n, np.dtype(loc.dtype).itemsize * loc.width, f"{where}.sparse.values")
        values[idx] = self.elements(span, loc.dtype, loc.width, n)
        return values


@dataclass(frozen=True)
class _Located:
    """An accessor, checked: what its elements are and where (`span`: buffer, byte offset, stride;
    None without a buffer view)."""

    where: str
    ctype: int
    dtype: str
    width: int
    count: int
    normalized: bool
    span: tuple | None
    sparse: object


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _hashable(v):
    """`v` when it can be a dictionary key (JSON numbers and strings), else None."""
    return v if isinstance(v, (int, float, str)) else None


def _list(v) -> list:
    return v if isinstance(v, list) else []


def _dict(v) -> dict:
    return v if isinstance(v, dict) else {}


def has_splats(path) -> bool:
    """Whether a glTF file (.glb or .gltf) has a mesh primitive with KHR_gaussian_splatting; reads
    only its JSON (a GLB's first chunk). PlyError for a file that is not readable glTF."""
    path = Path(path)
    doc = _load(path, str(path), json_only=True)
    return any(_is_splat(p) for mesh in doc.items("meshes") for p in _list(_dict(mesh).get("primitives")))


def _load(path: Path, where: str, *, json_only: bool = False) -> _Document:
    try:
        with open(path, "rb") as f:
            head = f.read(len(GLB_MAGIC))
        size = path.stat().st_size
    except OSError as exc:
        raise PlyError(f"{where}: cannot read: {exc.strerror or exc}") from None
    if head == GLB_MAGIC:
        json_bytes, glb_bin = _glb(path, where, size, json_only)
    else:
        if size > _MAX_JSON_BYTES:
            raise PlyError(f"{where}: a {size}-byte .gltf; this reader takes JSON up to {_MAX_JSON_BYTES} bytes")
        json_bytes, glb_bin = path.read_bytes(), None
    try:
        gltf = json.loads(json_bytes.decode("utf-8-sig"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise PlyError(f"{where}: the glTF JSON is not valid: {exc}") from None
    if not isinstance(gltf, dict) or not isinstance(gltf.get("asset"), dict):
        raise PlyError(f"{where}: not a glTF file: the JSON has no 'asset' object")
    version = str(gltf["asset"].get("version", ""))
    if not version.startswith("2."):
        raise PlyError(f"{where}: glTF version {version[:10]!r}; this reader knows glTF 2.x")
    return _Document(gltf, where, path.parent, glb_bin)


def _glb(path: Path, where: str, size: int, json_only: bool) -> tuple[bytes, _Source | None]:
    """A GLB file's JSON chunk and where its (first) BIN chunk is (not read), checked against the
    header's length and the file's size."""
    with open(path, "rb") as f:
        head = f.read(_GLB_HEADER.size + _CHUNK_HEADER.size)
        if len(head) < _GLB_HEADER.size + _CHUNK_HEADER.size:
            raise PlyError(f"{where}: truncated: a GLB file of {size} bytes has no room for its JSON chunk")
        _, version, length = _GLB_HEADER.unpack_from(head)
        if version != 2:
            raise PlyError(f"{where}: GLB container version {version}; this reader knows version 2")
        if length > size:
            raise PlyError(f"{where}: truncated: the GLB header declares {length} bytes, the file has {size}")
        json_size, kind = _CHUNK_HEADER.unpack_from(head, _GLB_HEADER.size)
        pos = _GLB_HEADER.size + _CHUNK_HEADER.size
        if kind != _JSON_CHUNK:
            raise PlyError(f"{where}: a GLB file whose first chunk is not JSON")
        if pos + json_size > length:
            raise PlyError(f"{where}: truncated: the JSON chunk of {json_size} bytes runs past the end ({length} "
                           "bytes)")
        if json_size > _MAX_JSON_BYTES:
            raise PlyError(f"{where}: a {json_size}-byte JSON chunk; this reader takes JSON up to {_MAX_JSON_BYTES} "
                           "bytes")
        text = f.read(json_size)
        pos += json_size
        bin_chunk = None
        while not json_only and bin_chunk is None and pos + _CHUNK_HEADER.size <= length:
            f.seek(pos)
            chunk_size, kind = _CHUNK_HEADER.unpack(f.read(_CHUNK_HEADER.size))
            pos += _CHUNK_HEADER.size
            if pos + chunk_size > length:
                raise PlyError(f"{where}: truncated: a GLB chunk of {chunk_size} bytes at byte {pos} runs past the "
                               f"end ({length} bytes)")
            if kind == _BIN_CHUNK:
                bin_chunk = _Source(chunk_size, path=path, start=pos)
            pos += chunk_size
    return text, bin_chunk


def read_gltf(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read the Gaussian splats of a .glb or .gltf file (KHR_gaussian_splatting, or its SPZ companion)
    into a numpy GaussianCloud in the 3DGS PLY's frame. Bad or truncated files, and files without
    splats, raise PlyError naming the file; what else the file holds is named in a warning."""
    path = Path(path)
    where = str(path)
    doc = _load(path, where)
    try:
        placed, notes = _splat_primitives(doc)
        legacy = _legacy(doc.gltf)
        clouds = []
        for mesh_i, prim_i, matrix in placed:
            what = f"meshes[{mesh_i}].primitives[{prim_i}]"
            if not np.isfinite(matrix).all():
                doc.fail(f"{what} is placed by a node transform that is not finite")
            if abs(np.linalg.det(matrix[:3, :3])) < 1e-30:
                notes.append(f"{what} is placed by a node transform of scale zero (nothing to draw): left out")
                continue
            cloud, prim_notes = _primitive(doc, doc.gltf["meshes"][mesh_i]["primitives"][prim_i], what, legacy,
                                           sanitize, matrix)
            notes += prim_notes
            clouds.append(cloud)
    finally:
        doc.close()
    for note in dict.fromkeys(notes):
        warnings.warn(f"{where}: {note}", stacklevel=2)
    cloud = GaussianCloud.concat(clouds) if len(clouds) != 1 else clouds[0]
    if not clouds:
        cloud = GaussianCloud.empty()
    finite = np.ones(len(cloud), bool)
    for a in cloud.arrays().values():
        with np.errstate(invalid="ignore", over="ignore"):
            total = a.sum()
        if not np.isfinite(total):
            finite &= np.isfinite(a.reshape(len(cloud), -1)).all(1)
    return drop_nonfinite(cloud, finite, where, sanitize, stacklevel=3)


def _legacy(gltf: dict) -> tuple[int, int, int] | None:
    """splat-transform's version when it wrote the file before 2.7.0 (log-scales), else None."""
    match = _GENERATOR.match(str(gltf["asset"].get("generator", "")))
    if match:
        version = tuple(int(v) for v in match.groups())
        if version < _LINEAR_SCALE_SINCE:
            return version
    return None


def _node_matrix(doc: _Document, node: dict, where: str) -> np.ndarray:
    if "matrix" in node:
        m = node["matrix"]
        if not isinstance(m, list) or len(m) != 16 or not all(isinstance(v, (int, float)) for v in m):
            doc.fail(f"{where}.matrix must be 16 numbers")
        return np.array(m, np.float64).reshape(4, 4).T  # column-major
    t, r, s = node.get("translation", [0, 0, 0]), node.get("rotation", [0, 0, 0, 1]), node.get("scale", [1, 1, 1])
    for key, value, size in (("translation", t, 3), ("rotation", r, 4), ("scale", s, 3)):
        if not isinstance(value, list) or len(value) != size or not all(isinstance(v, (int, float)) for v in value):
            doc.fail(f"{where}.{key} must be {size} numbers")
    out = np.eye(4)
    q = quaternions.normalize(np.array([r[3], r[0], r[1], r[2]], np.float64))
    out[:3, :3] = quaternions.to_rotmat(q) * np.array(s, np.float64)[None, :]
    out[:3, 3] = t
    return out


def _is_splat(prim) -> bool:
    return isinstance(prim, dict) and isinstance(prim.get("extensions"), dict) and EXTENSION in prim["extensions"]


def _splat_primitives(doc: _Document) -> tuple[list[tuple[int, int, np.ndarray]], list[str]]:
    """(mesh, primitive, global matrix) of every splat primitive the default scene places, and notes
    naming what else the file holds."""
    gltf, meshes, nodes = doc.gltf, doc.items("meshes"), doc.items("nodes")
    scenes = doc.items("scenes")
    if scenes:
        scene_i = gltf.get("scene", 0)
        roots = doc.item("scenes", scene_i, "'scene'").get("nodes", [])
    else:
        children = {c for n in nodes if isinstance(n, dict) for c in _list(n.get("children")) if _is_int(c)}
        roots = [i for i in range(len(nodes)) if i not in children]
    placed = []
    stack = [(r, np.eye(4), ()) for r in reversed(roots if isinstance(roots, list) else [])]
    while stack:
        index, parent, path = stack.pop()
        node = doc.item("nodes", index, "a scene")
        if index in path:
            doc.fail(f"nodes[{index}] is its own ancestor (a cycle in the node hierarchy)")
        matrix = parent @ _node_matrix(doc, node, f"nodes[{index}]")
        mesh_i = node.get("mesh")
        if mesh_i is not None:
            mesh = doc.item("meshes", mesh_i, f"nodes[{index}]")
            splats = [i for i, p in enumerate(_list(mesh.get("primitives"))) if _is_splat(p)]
            if splats and isinstance(node.get("extensions"), dict) and "EXT_mesh_gpu_instancing" in node["extensions"]:
                doc.fail(f"nodes[{index}] instances its splats with EXT_mesh_gpu_instancing, which this reader "
                         "does not expand")
            placed += [(mesh_i, i, matrix) for i in splats]
        for child in reversed(_list(node.get("children"))):
            stack.append((child, matrix, path + (index,)))
    notes = []
    if not placed:  # splats that no node of the scene places: read them where their mesh has them
        placed = [(m, i, np.eye(4)) for m, mesh in enumerate(meshes)
                  for i, p in enumerate(_list(_dict(mesh).get("primitives"))) if _is_splat(p)]
        if placed:
            notes.append(f"{len(placed)} splat primitive(s) that no node of the scene places, read in their "
                         "mesh's own frame")
    if not placed:
        held = _contents(doc, set())
        raise PlyError(f"{doc.where}: a glTF file without Gaussian splats (no mesh primitive with the "
                       f"{EXTENSION} extension){'; it holds ' + held if held else ''}; import it with a glTF "
                       "importer (in Blender: File > Import > glTF 2.0)")
    other = _contents(doc, {(m, i) for m, i, _ in placed})
    if other:
        notes.append("holds more than splats, left unread: " + other)
    return placed, notes


def _contents(doc: _Document, splats: set) -> str:
    """What the file holds beyond the primitives in `splats`, in words ('' for nothing)."""
    modes: dict[str, int] = {}
    for m, mesh in enumerate(doc.items("meshes")):
        for i, prim in enumerate(_list(_dict(mesh).get("primitives"))):
            if (m, i) in splats:
                continue
            kind = "splat" if _is_splat(prim) else _MODES.get(_hashable(_dict(prim).get("mode", 4)), "unknown mode")
            modes[kind] = modes.get(kind, 0) + 1
    parts = []
    if modes:
        parts.append(f"{sum(modes.values())} mesh primitive(s) ("
                     + ", ".join(f"{k} {v}" for k, v in sorted(modes.items())) + ")")
    for key in ("materials", "textures", "images", "cameras", "skins", "animations"):
        n = len(_list(doc.gltf.get(key)))
        if n:
            parts.append(f"{n} {key[:-1] if n == 1 else key}")
    lights = _dict(_dict(doc.gltf.get("extensions")).get("KHR_lights_punctual")).get("lights")
    if _list(lights):
        parts.append(f"{len(lights)} light(s)")
    scenes = _list(doc.gltf.get("scenes"))
    if len(scenes) > 1:
        parts.append(f"{len(scenes) - 1} other scene(s)")
    return ", ".join(parts)


def _primitive(doc: _Document, prim: dict, what: str, legacy, sanitize: bool, matrix: np.ndarray):
    """(cloud in the PLY's frame, notes) of one splat primitive placed by the global `matrix`: the
    data turned into glTF's frame (SPZ: its own frame first), moved by the matrix, turned into the
    PLY's frame (not for splat-transform's files before 2.0); exact sign flips when the matrix is
    the identity, done while the data is unpacked."""
    if prim.get("mode", 4) != _POINTS:
        doc.fail(f"{what} has the {EXTENSION} extension but mode {prim.get('mode', 4)}, not POINTS (0)")
    unknown = [k for k in prim["extensions"] if k not in _KNOWN_PRIMITIVE_EXTENSIONS]
    if unknown:
        doc.fail(f"{what} is encoded with {', '.join(unknown)}, which this reader does not decode")
    ext = prim["extensions"][EXTENSION]
    if not isinstance(ext, dict):
        doc.fail(f"{what}: the {EXTENSION} object is not a JSON object")
    notes = _extension_notes(ext, what)
    attrs = prim.get("attributes")
    if not isinstance(attrs, dict):
        doc.fail(f"{what} has no attributes object")
    inner = ext.get("extensions") or {}
    if not isinstance(inner, dict):
        doc.fail(f"{what}: {EXTENSION}.extensions is not a JSON object")
    unknown = [k for k in inner if k != SPZ_EXTENSION]
    if unknown:
        doc.fail(f"{what} is encoded with {', '.join(unknown)}, which this reader does not decode")
    to_gltf = np.array(SPZ_TO_GLTF if SPZ_EXTENSION in inner else (1.0, 1.0, 1.0))
    to_ply = np.array((1.0, 1.0, 1.0) if legacy is not None and legacy < _GLTF_FRAME_SINCE else PLY_TO_GLTF)
    identity = np.array_equal(matrix, np.eye(4))
    signs = to_gltf * to_ply if identity else np.ones(3)
    if SPZ_EXTENSION in inner:
        cloud = _spz_primitive(doc, inner[SPZ_EXTENSION], attrs, what, sanitize)
        if not np.all(signs == 1):
            cloud = flip_axes(cloud, signs)
    else:
        cloud, more = _attribute_primitive(doc, attrs, what, legacy, sanitize, signs)
        notes += more
    if not identity:
        cloud = affine(cloud, np.diag([*to_ply, 1.0]) @ matrix @ np.diag([*to_gltf, 1.0]))
    return cloud, notes


def _extension_notes(ext: dict, what: str) -> list[str]:
    notes = []
    kernel, space = ext.get("kernel"), ext.get("colorSpace")
    if kernel != "ellipse":
        notes.append(f"{what}: kernel {json.dumps(kernel)[:40]}, read as the 'ellipse' kernel (the only one "
                     "defined)")
    if space != "srgb_rec709_display":
        notes.append(f"{what}: colorSpace {json.dumps(space)[:40]}, read as it is; the project draws colours "
                     "as sRGB-encoded ('srgb_rec709_display')")
    if ext.get("projection", "perspective") != "perspective":
        notes.append(f"{what}: projection {json.dumps(ext.get('projection'))[:40]}, drawn as 'perspective'")
    return notes


def _spz_primitive(doc: _Document, spz, attrs: dict, what: str, sanitize: bool) -> GaussianCloud:
    if not isinstance(spz, dict):
        doc.fail(f"{what}: {SPZ_EXTENSION} is not a JSON object")
    source, offset, length, _ = doc.view(spz.get("bufferView"), f"{what} {SPZ_EXTENSION}")
    data = doc.read(source, offset, length).tobytes()
    cloud = decode_spz(data, f"{doc.where} ({what}, {SPZ_EXTENSION})", sanitize=sanitize)
    position = attrs.get("POSITION")
    if position is not None:
        count = doc.item("accessors", position, f"{what} POSITION").get("count")
        if count != len(cloud):
            doc.fail(f"{what}: POSITION's accessor counts {count} points; its SPZ data holds {len(cloud)}")
    return cloud


def _attribute_primitive(doc: _Document, attrs: dict, what: str, legacy, sanitize: bool, signs: np.ndarray):
    """(cloud, notes) of a primitive of float or integer attributes, turned by the axis flip `signs`
    (`transform.flip_axes`, exact) as it is unpacked."""
    required = ("POSITION", ROTATION, SCALE, OPACITY, sh_attribute(0, 0))
    missing = [a for a in required if a not in attrs]
    if missing:
        doc.fail(f"{what} lacks the attribute(s) {', '.join(missing)}")
    degree = 0
    for band in (1, 2, 3):
        names = [sh_attribute(band, n) for n in range(2 * band + 1)]
        have = [n for n in names if n in attrs]
        if have and (len(have) < len(names) or degree != band - 1):
            doc.fail(f"{what}: SH degree {band} is incomplete or lower degrees are missing: it lacks "
                     + ", ".join([sh_attribute(b, n) for b in range(1, band) for n in range(2 * b + 1)
                                  if sh_attribute(b, n) not in attrs] + [n for n in names if n not in attrs]))
        if have:
            degree = band
    known = set(required) | {sh_attribute(b, n) for b in (1, 2, 3) for n in range(2 * b + 1)} | {"COLOR_0"}
    notes = [f"{what}: attribute(s) not read: {', '.join(sorted(k for k in attrs if k not in known))}"] \
        if any(k not in known for k in attrs) else []
    names = [sh_attribute(b, m) for b in range(1, degree + 1) for m in range(2 * b + 1)]
    located = {name: doc.locate(attrs[name], f"{what} {name.split(':')[-1]}", (4,) if name == ROTATION else
                                (1,) if name == OPACITY else (3,)) for name in (*required, *names)}
    n = located["POSITION"].count
    for name, loc in located.items():
        if loc.count != n:
            doc.fail(f"{what}: {name} has {loc.count} values for {n} points")
    means = doc.accessor(attrs["POSITION"], f"{what} POSITION", (3,))
    xyzw = doc.accessor(attrs[ROTATION], f"{what} ROTATION", (4,))
    linear = doc.accessor(attrs[SCALE], f"{what} SCALE", (3,))
    alpha = doc.accessor(attrs[OPACITY], f"{what} OPACITY", (1,))[:, 0]
    dc = doc.accessor(attrs[sh_attribute(0, 0)], f"{what} SH_DEGREE_0_COEF_0", (3,))
    s32 = signs.astype(np.float32)
    means *= s32
    quats = np.empty((n, 4), np.float32)
    quats[:, 0] = xyzw[:, 3]
    np.multiply(xyzw[:, :3], s32, out=quats[:, 1:])
    sign = _sh_signs(len(names), signs)
    run = _consecutive([located[name] for name in names], n)
    if run is not None:  # the usual layout (this writer's, splat-transform's): read and turned in blocks
        rest = _read_gaussian_major(doc, *run, n, sign)
    else:
        coefficients = [doc.accessor(attrs[name], f"{what} {name.split(':')[-1]}", (3,)) for name in names]
        rest = _gaussian_major(np.stack(coefficients) if names else np.zeros((0, n, 3), np.float32), sign)
    with np.errstate(divide="ignore", invalid="ignore"):
        if legacy is not None:
            notes.append(f"written by splat-transform {'.'.join(map(str, legacy))} (before 2.7.0): SCALE read as "
                         "log-scales, as it wrote them"
                         + (", and positions in the PLY's frame (before 2.0)" if legacy < _GLTF_FRAME_SINCE else ""))
            scales = linear
        elif (linear < 0).any():
            notes.append(f"{what}: negative SCALE values: read as log-scales, as drafts of the extension stored "
                         "them (the ratified one stores linear scales)")
            scales = linear
        else:
            scales = np.log(linear.astype(np.float64)).astype(np.float32)
        p = alpha.astype(np.float64)
        outside = ~((p >= 0) & (p <= 1))
        if outside.any():
            rows = np.flatnonzero(outside)
            if not sanitize:
                head = ", ".join(str(i) for i in rows[:5]) + (", ..." if len(rows) > 5 else "")
                doc.fail(f"{what}: {len(rows)} OPACITY value(s) outside [0, 1] (or NaN), rows [{head}]; read with "
                         "sanitize=True to drop them")
            p[outside] = np.nan
        opacities = np.log(p / (1.0 - p)).astype(np.float32)
    return GaussianCloud(means=means, scales=scales, quats=quats, opacities=opacities, sh_dc=dc, sh_rest=rest), notes


# ----------------------------------------------------------------------------------- write

def write_gltf(cloud: GaussianCloud, path) -> Path:
    """Write `cloud` (in a 3DGS PLY's frame) as KHR_gaussian_splatting glTF: a .glb, or with a name
    ending in .gltf that JSON file and NAME.bin beside it. Atomic (the .bin first). Non-finite rows
    and an empty cloud are refused (PlyError); extra properties are not stored (a warning says so).
    The attributes are made and written in blocks of rows (no copy of the whole cloud is made)."""
    path = Path(path)
    where = str(path)
    c = writable(cloud, "glTF", where)
    if len(c) == 0:
        raise PlyError(f"{where}: no Gaussians to write (glTF accessors hold at least one element)")
    layout = _layout(c.sh_degree)
    gltf, total = _document(layout, c)
    huge, sh_signs = [], _sh_signs(c.sh_rest.shape[1], PLY_TO_GLTF)

    def write_bin(f, start: int = 0) -> None:
        f.flush()  # then each block goes to its place in the file straight (os.pwrite)
        for row in range(0, len(c), _WRITE_ROWS):
            offset = start
            for (_, _, kind, _), data in zip(layout, _encode(c, row, row + _WRITE_ROWS, sh_signs, huge)):
                _pwrite(f.fileno(), np.ascontiguousarray(data), offset + row * data.itemsize * _WIDTHS[kind])
                offset += len(c) * data.itemsize * _WIDTHS[kind]
        if sum(huge):
            warnings.warn(f"{where}: {sum(huge)} log-scale(s) above {math.log(np.finfo(np.float32).max):.2f} "
                          "written as the largest float32", stacklevel=4)

    if path.name.lower().endswith(".gltf"):
        bin_path = path.with_name(path.name[:-len(".gltf")] + ".bin")
        gltf["buffers"][0]["uri"] = quote(bin_path.name)
        atomic_write(bin_path, write_bin)
        return atomic_write(path, lambda f: f.write(json.dumps(gltf, separators=(",", ":")).encode("utf-8")))
    text = json.dumps(gltf, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    head = _GLB_HEADER.size + 2 * _CHUNK_HEADER.size + len(text)
    if head + total > _GLB_LIMIT:
        raise PlyError(f"{where}: {len(c)} Gaussians need {head + total} bytes; a .glb holds at most 4 GiB: write "
                       "a .gltf (with its .bin) instead")

    def write_glb(f) -> None:
        f.write(_GLB_HEADER.pack(GLB_MAGIC, 2, head + total))
        f.write(_CHUNK_HEADER.pack(len(text), _JSON_CHUNK) + text)
        f.write(_CHUNK_HEADER.pack(total, _BIN_CHUNK))
        write_bin(f, head)

    return atomic_write(path, write_glb)


def _pwrite(fd: int, data: np.ndarray, offset: int) -> None:
    view = memoryview(data).cast("B")
    while len(view):
        done = os.pwrite(fd, view, offset)
        view, offset = view[done:], offset + done


def _layout(degree: int) -> list[tuple[str, int, str, bool]]:
    """(attribute, component type, accessor type, normalised) of what the writer writes, in file order."""
    out = [("POSITION", _FLOAT, "VEC3", False), ("COLOR_0", _UBYTE, "VEC4", True), (ROTATION, _FLOAT, "VEC4", False),
           (SCALE, _FLOAT, "VEC3", False), (OPACITY, _FLOAT, "SCALAR", False),
           (sh_attribute(0, 0), _FLOAT, "VEC3", False)]
    return out + [(sh_attribute(b, m), _FLOAT, "VEC3", False) for b in range(1, degree + 1) for m in range(2 * b + 1)]


def _encode(c: GaussianCloud, start: int, stop: int, sh_signs: np.ndarray, huge: list[int]) -> list[np.ndarray]:
    """The attribute arrays (`_layout`'s order) of rows start:stop of a finite numpy cloud, in glTF's
    frame (`sh_signs`: of each SH rest coefficient); the number of log-scales too large for float32
    is appended to `huge`."""
    f32 = np.float32
    signs = np.array(PLY_TO_GLTF, f32)
    means = c.means[start:stop] * signs
    q = c.quats[start:stop]
    norm = np.sqrt(np.einsum("ij,ij->i", q, q, dtype=np.float64))
    good = norm > 1e-12  # (a zero quaternion: the identity)
    inverse = np.divide(1.0, norm, out=np.zeros_like(norm), where=good)[:, None]
    xyzw = np.empty((len(q), 4), f32)
    np.multiply(q[:, 1:], inverse * signs, out=xyzw[:, :3], casting="same_kind")
    np.multiply(q[:, 0], inverse[:, 0], out=xyzw[:, 3], casting="same_kind")
    xyzw[~good, 3] = 1.0
    with np.errstate(over="ignore"):
        linear = np.exp(c.scales[start:stop].astype(np.float64)).astype(f32)
        alpha = sigmoid(c.opacities[start:stop].astype(np.float64)).astype(f32)
    inf = np.isinf(linear)
    huge.append(int(inf.sum()))
    linear[inf] = np.finfo(f32).max
    dc = c.sh_dc[start:stop]
    color = np.empty((len(dc), 4), np.uint8)
    diffuse = np.clip(dc * f32(SH_C0) + f32(0.5), f32(0.0), f32(1.0))
    color[:, :3] = np.rint(srgb_to_linear(diffuse, np.float32) * f32(255.0))
    color[:, 3] = np.rint(alpha * f32(255.0))
    return [means, color, xyzw, linear, alpha, dc, *_coefficient_major(c.sh_rest[start:stop], sh_signs)]


def _sh_signs(k: int, signs) -> np.ndarray:
    """The sign of each of k SH rest coefficients under the axis flip `signs` (float32)."""
    if k == 0:
        return np.zeros(0, np.float32)
    return np.diag(sh_rotation(np.diag(signs), {v: d for d, v in SH_REST_COUNTS.items()}[k])).astype(np.float32)


def _consecutive(located: list[_Located], n: int) -> tuple[_Source, int, int] | None:
    """(buffer, byte offset of the first, spacing) when the SH coefficient accessors are tightly packed
    float32 (n, 3) blocks one after the other at one spacing in one buffer, without sparse values."""
    if not located or any(loc.ctype != _FLOAT or loc.sparse is not None or loc.span is None
                          or loc.span[2] != 12 for loc in located):
        return None
    source, first = located[0].span[:2]
    step = located[1].span[1] - first if len(located) > 1 else 12 * n
    if step < 12 * n or any(loc.span[0] is not source or loc.span[1] != first + j * step
                            for j, loc in enumerate(located)):
        return None
    return source, first, step


def _read_gaussian_major(doc: _Document, source: _Source, first: int, step: int, n: int,
                         sign: np.ndarray) -> np.ndarray:
    """(n, k, 3) sh_rest of k coefficient blocks laid out as `_consecutive` found them, each times its
    sign, read `_WRITE_ROWS` rows of every coefficient at a time (the file is never held whole)."""
    k = len(sign)
    out = np.empty((n, k, 3), np.float32)
    block = np.empty((k, min(n, _WRITE_ROWS), 3), np.float32)
    for row in range(0, n, _WRITE_ROWS):
        m = min(_WRITE_ROWS, n - row)
        for j in range(k):
            doc.read(source, first + j * step + 12 * row, 12 * m, out=block[j, :m].reshape(-1).view(np.uint8))
        _gaussian_major(block[:, :m], sign, out=out[row:row + m])
    return out


def _gaussian_major(coefficients: np.ndarray, sign: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(n, k, 3) sh_rest (into `out` when given) of (k, n, 3) coefficients, each multiplied by its sign,
    transposed in blocks of rows that stay in cache, one colour channel at a time (numpy's inner loop
    then runs along k)."""
    k, n = coefficients.shape[:2]
    out = np.empty((n, k, 3), np.float32) if out is None else out
    for start in range(0, n, _BLOCK_ROWS):
        stop = start + _BLOCK_ROWS
        for ch in range(3):
            np.multiply(coefficients[:, start:stop, ch].T, sign, out=out[start:stop, :, ch])
    return out


def _coefficient_major(sh_rest: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """The inverse of `_gaussian_major`: (k, n, 3) of (n, k, 3), each coefficient times its sign
    (copied in blocks, then the negative ones flipped in place: 20% faster than multiplying)."""
    n, k = sh_rest.shape[:2]
    out = np.empty((k, n, 3), np.float32)
    for start in range(0, n, _BLOCK_ROWS):
        stop = start + _BLOCK_ROWS
        for ch in range(3):
            out[:, start:stop, ch] = sh_rest[start:stop, :, ch].T
    for j in np.flatnonzero(sign < 0):
        np.negative(out[j], out=out[j])
    return out


def _document(layout: list, c: GaussianCloud) -> tuple[dict, int]:
    """The glTF JSON of the attributes of `layout` for cloud `c`, one tightly packed buffer view
    each in one buffer, and the buffer's length."""
    views, accessors, attributes, pos, n = [], [], {}, 0, len(c)
    for i, (name, ctype, kind, normalized) in enumerate(layout):
        size = n * _WIDTHS[kind] * np.dtype(_COMPONENTS[ctype][0]).itemsize  # a multiple of 4: no padding
        views.append({"buffer": 0, "byteOffset": pos, "byteLength": size, "target": _ARRAY_BUFFER})
        acc = {"bufferView": i, "componentType": ctype, "count": n, "type": kind}
        if normalized:
            acc["normalized"] = True
        if name == "POSITION":  # the bounds of the positions as the file holds them (glTF's frame)
            lo = [c.means[:, i].min() for i in range(3)]  # (column by column: 40x faster than min(0))
            hi = [c.means[:, i].max() for i in range(3)]
            flip = np.array(PLY_TO_GLTF) < 0
            acc["min"] = [float(-h if f else v) for v, h, f in zip(lo, hi, flip)]
            acc["max"] = [float(-v if f else h) for v, h, f in zip(lo, hi, flip)]
        accessors.append(acc)
        attributes[name] = i
        pos += size
    gltf = {"asset": {"version": "2.0", "generator": "gvae_core (GaussianVAE for Blender)"},
            "extensionsUsed": [EXTENSION], "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "name": "splats"}],
            "meshes": [{"name": "splats", "primitives": [{
                "attributes": attributes, "mode": _POINTS,
                "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                           "projection": "perspective", "sortingMethod": "cameraDistance"}}}]}],
            "buffers": [{"byteLength": pos}], "bufferViews": views, "accessors": accessors}
    return gltf, pos
