"""Reading and writing 3DGS PLY files (the reference layout of DESIGN.md) with numpy alone.

Read: binary little/big endian and ascii; properties by name in any order; float, double or any
PLY scalar type; SH degree 0..3 from the number of `f_rest_*`; unknown properties kept in
`cloud.extra` with their dtype; normals kept in `extra` (as `nx ny nz`) only when not all zero.
Write: binary little endian, the reference order, then the extra properties; to a temporary file
in the same directory that is renamed into place, so a failed write leaves nothing behind.

Integer dtypes PLY has no type for (int64, uint64), bool and float16 are stored in the nearest
PLY type that holds them exactly, with a header comment `gvae_dtype NAME DTYPE` that restores the
dtype on read; other readers see a standard file. The colour a cloud was trained over
(`GaussianCloud.background`) is the header comment `gvae_background R G B`.
"""

from __future__ import annotations

import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write
from .cloud import GaussianCloud
from .conventions import LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_REST_COUNTS

__all__ = ["PlyError", "InfinitiesReadWarning", "read_ply", "write_ply", "BACKGROUND_COMMENT"]

#: Header comment holding the colour a cloud was trained over: `comment gvae_background R G B`.
BACKGROUND_COMMENT = "gvae_background"


class PlyError(ValueError):
    """A PLY file that cannot be read as (or a cloud that cannot be written as) a 3DGS PLY."""


# PLY scalar type names (both spellings) -> numpy type character codes (endianness added later).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
# numpy dtype -> PLY type name used when writing.
_WRITE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
                "u4": "uint", "f4": "float", "f8": "double"}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
# dtypes restored from a `gvae_dtype` header comment.
_COMMENT_DTYPES = ("int64", "uint64", "bool", "float16")
_MAX_HEADER_BYTES = 1 << 20

_NORMALS = ("nx", "ny", "nz")
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def _reference_names(k: int) -> list[str]:
    """Property names of the reference layout for `k` SH rest coefficients per channel."""
    return (["x", "y", "z", *_NORMALS, "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * k)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


# ---------------------------------------------------------------------------------- header

@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str]]  # (name, numpy type code) for scalar properties
    has_list: bool = False


@dataclass
class _Header:
    fmt: str                      # "ascii", "binary_little_endian" or "binary_big_endian"
    elements: list[_Element]
    data_offset: int              # bytes from the file start to the first data byte
    dtype_comments: dict[str, str]
    background: tuple[float, float, float] | None = None  # `comment gvae_background R G B`

    @property
    def byte_order(self) -> str | None:
        """"<" or ">" for binary files, None for ascii."""
        return _FORMATS[self.fmt]


def _parse_header(raw: bytes, where: str) -> _Header:
    """Parse the header at the start of `raw` (which holds at least the whole header)."""
    if not (raw.startswith(b"ply\n") or raw.startswith(b"ply\r\n")):
        raise PlyError(f"{where}: not a PLY file (it does not start with 'ply')")
    end = raw.find(b"\nend_header") + 1
    if end <= 0:
        raise PlyError(f"{where}: bad header: no 'end_header' line "
                       f"(file shorter than its header, or header over {_MAX_HEADER_BYTES} bytes)")
    eol = raw.find(b"\n", end)
    if eol < 0:
        raise PlyError(f"{where}: truncated: the file ends inside the header's 'end_header' line")
    if raw[end:eol].rstrip(b"\r") != b"end_header":
        raise PlyError(f"{where}: bad header: malformed 'end_header' line")
    try:
        text = raw[:end].decode("ascii")
    except UnicodeDecodeError:
        raise PlyError(f"{where}: bad header: it contains non-ASCII bytes") from None

    fmt = None
    elements: list[_Element] = []
    comments: dict[str, str] = {}
    background = None
    for lineno, line in enumerate(text.splitlines()[1:], start=2):
        words = line.split()
        if not words:
            continue
        key = words[0]
        bad = f"{where}: bad header line {lineno} {line.strip()!r}"
        if key in ("comment", "obj_info"):
            if len(words) == 4 and words[1] == "gvae_dtype" and words[3] in _COMMENT_DTYPES:
                comments[words[2]] = words[3]
            elif len(words) == 5 and words[1] == BACKGROUND_COMMENT:
                background = _background(words[2:], f"{where}: bad header line {lineno} {line.strip()!r}")
            continue
        if key == "format":
            if fmt is not None:
                raise PlyError(f"{bad}: second 'format' line")
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise PlyError(f"{bad}: expected 'format ascii|binary_little_endian|binary_big_endian 1.0'")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"{bad}: expected 'element NAME COUNT'")
            elements.append(_Element(words[1], int(words[2]), []))
        elif key == "property":
            if not elements:
                raise PlyError(f"{bad}: property before any element")
            el = elements[-1]
            if len(words) == 5 and words[1] == "list":
                if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                    raise PlyError(f"{bad}: unknown list type")
                el.has_list = True
                el.props.append((words[4], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                el.props.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise PlyError(f"{bad}: expected 'property TYPE NAME' with TYPE one of "
                               f"{sorted(set(_WRITE_NAMES.values()))}")
        else:
            raise PlyError(f"{bad}: unknown keyword {key!r}")
    if fmt is None:
        raise PlyError(f"{where}: bad header: no 'format' line")
    return _Header(fmt, elements, eol + 1, comments, background)


def _background(words: list[str], bad: str) -> tuple[float, float, float]:
    try:
        rgb = tuple(float(w) for w in words)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise PlyError(f"{bad}: expected '{BACKGROUND_COMMENT} R G B' with each in [0, 1]")
    return rgb  # type: ignore[return-value]


def _read_header_bytes(f, where: str) -> bytes:
    """Read from the start of the file until the header's end is in the buffer."""
    buf = b""
    while True:
        chunk = f.read(65536)
        buf += chunk
        end = buf.find(b"\nend_header")
        if end >= 0 and buf.find(b"\n", end + 1) >= 0:
            return buf
        if not chunk or len(buf) > _MAX_HEADER_BYTES:
            return buf  # _parse_header reports what is wrong


def read_header(f, where: str) -> _Header:
    """The parsed header of the PLY file `f` (open in binary mode at its start): its format, its
    elements with their scalar properties, and where the data start. PlyError if malformed."""
    return _parse_header(_read_header_bytes(f, where), where)


# ------------------------------------------------------------------------------------ read

def read_ply(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read a 3DGS PLY file into a numpy GaussianCloud (float32 parameters).

    Rows with non-finite parameters raise PlyError naming them, unless `sanitize` is true:
    then they are dropped with a warning saying how many."""
    path = Path(path)
    where = str(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        header = read_header(f, where)
        vertex, skip_bytes, skip_values = _locate_vertex(header, where)
        _check_properties([name for name, _ in vertex.props], where)
        n = vertex.count
        body = size - header.data_offset
        if header.fmt == "ascii":
            records = _read_ascii(f, header, vertex, skip_values, body, where)
            dtype, chunks = records.dtype, _memory_chunks(records)
        else:
            dtype = np.dtype([(name, _FORMATS[header.fmt] + code) for name, code in vertex.props])
            need = skip_bytes + n * dtype.itemsize
            if need > body:  # checked before anything is allocated
                raise PlyError(f"{where}: truncated: the header declares {n} vertices "
                               f"({need} bytes of data) but only {body} bytes follow the header")
            f.seek(header.data_offset + skip_bytes)
            chunks = _file_chunks(f, dtype, n, where)
        cloud, finite = _cloud_from_records(chunks, dtype, n, header.dtype_comments)
    return drop_nonfinite(cloud.replace(background=header.background), finite, where, sanitize, stacklevel=3)


class InfinitiesReadWarning(UserWarning):
    """A file held infinite values with a meaning (an opacity logit of +-inf, a log-scale of -inf),
    read as that meaning: the clamped finite value the renderer uses."""


def drop_nonfinite(cloud: GaussianCloud, finite: np.ndarray, where: str, sanitize: bool, *,
                   stacklevel: int = 2) -> GaussianCloud:
    """The reading policy for rows with non-finite parameters (`finite` is False for them).

    First, infinities with a meaning are read as that meaning (DESIGN.md, Numerical guards): an
    opacity logit of +inf / -inf is opacity 1 / 0 and becomes the end of OPACITY_LOGIT_RANGE, a
    log-scale of -inf is a flat axis and becomes LOG_SCALE_RANGE[0]; the row is kept and an
    InfinitiesReadWarning says how many. What is still non-finite (NaN anywhere, an infinite
    position or colour, a log-scale of +inf) raises a PlyError naming the rows, or with `sanitize`
    the cloud without them and a warning saying how many. `cloud`'s arrays are changed in place."""
    if finite.all():
        return cloud
    bad = np.flatnonzero(~finite)
    finite[bad] = _read_meaningful_infinities(cloud, bad, where, stacklevel + 1)
    if finite.all():
        return cloud
    bad = np.flatnonzero(~finite)
    if not sanitize:
        head = ", ".join(str(i) for i in bad[:5]) + (", ..." if len(bad) > 5 else "")
        raise PlyError(f"{where}: {len(bad)} Gaussian(s) with non-finite (NaN or infinite) "
                       f"parameters, rows [{head}]; read with sanitize=True to drop them")
    warnings.warn(f"{where}: dropped {len(bad)} of {len(finite)} Gaussians with non-finite parameters",
                  stacklevel=stacklevel)
    return cloud.select(finite)


def _read_meaningful_infinities(cloud: GaussianCloud, rows: np.ndarray, where: str, stacklevel: int) -> np.ndarray:
    """Clamp the infinite opacity logits and the -inf log-scales of `rows` in place (warning with
    their numbers); whether each of those rows is finite now."""
    opacities, scales = cloud.opacities[rows], cloud.scales[rows]
    infinite_opacity = np.isinf(opacities)
    flat = np.isneginf(scales)
    n_opacity, n_flat = int(infinite_opacity.sum()), int(flat.sum())
    if n_opacity:
        cloud.opacities[rows] = np.where(infinite_opacity, np.clip(opacities, *OPACITY_LOGIT_RANGE), opacities)
    if n_flat:
        cloud.scales[rows] = np.where(flat, np.float32(LOG_SCALE_RANGE[0]), scales)
    if n_opacity or n_flat:
        said = []
        if n_opacity:
            said.append(f"{n_opacity} opacity logit(s) of +-inf as +-{OPACITY_LOGIT_RANGE[1]:g} (opacity 1 or 0)")
        if n_flat:
            said.append(f"{n_flat} log-scale(s) of -inf as {LOG_SCALE_RANGE[0]:g} (flat axes)")
        warnings.warn(f"{where}: read " + " and ".join(said), InfinitiesReadWarning, stacklevel=stacklevel)
    ok = np.ones(len(rows), bool)
    for a in cloud.arrays().values():
        ok &= np.isfinite(a[rows].reshape(len(rows), -1)).all(1)
    return ok


def _locate_vertex(header: _Header, where: str) -> tuple[_Element, int, int]:
    """The vertex element, and how many bytes (binary) or values (ascii) precede its data."""
    vertices = [e for e in header.elements if e.name == "vertex"]
    if len(vertices) != 1:
        raise PlyError(f"{where}: bad header: expected one 'vertex' element, found {len(vertices)}")
    vertex = vertices[0]
    if vertex.has_list:
        lists = [n for n, t in vertex.props if t == "list"]
        raise PlyError(f"{where}: vertex list properties are not supported: {lists}")
    skip_bytes = skip_values = 0
    for el in header.elements:
        if el is vertex:
            break
        if el.has_list:
            raise PlyError(f"{where}: element {el.name!r} with list properties before the vertex "
                           "element is not supported")
        skip_bytes += el.count * sum(int(t[1]) for _, t in el.props)
        skip_values += el.count * len(el.props)
    after = header.elements[header.elements.index(vertex) + 1:]
    if any(e.count for e in after):
        warnings.warn(f"{where}: ignoring element(s) after the vertex data: "
                      + ", ".join(f"{e.name} ({e.count})" for e in after), stacklevel=3)
    return vertex, skip_bytes, skip_values


def _check_properties(names: list[str], where: str) -> None:
    dup = sorted(name for name, count in Counter(names).items() if count > 1)
    if dup:
        raise PlyError(f"{where}: bad header: duplicate vertex properties {dup}")
    missing = [n for n in _REQUIRED if n not in names]
    if missing and "packed_position" in names:
        raise PlyError(f"{where}: a compressed (SuperSplat) PLY, not the reference layout: read it with "
                       "gvae_core.read_splat_file")
    if missing:
        raise PlyError(f"{where}: missing required vertex properties: {', '.join(missing)}")
    rest = [n for n in names if n.startswith("f_rest_") and n[7:].isdigit()]
    if len(rest) not in (0, 9, 24, 45):
        raise PlyError(f"{where}: {len(rest)} f_rest_* properties; expected 0, 9, 24 or 45 "
                       "(SH degree 0..3)")
    want = {f"f_rest_{i}" for i in range(len(rest))}
    if set(rest) != want:
        raise PlyError(f"{where}: f_rest_* properties are not numbered 0..{len(rest) - 1}: "
                       f"missing {sorted(want - set(rest))[:5]}")


def _read_ascii(f, header: _Header, vertex: _Element, skip: int, body: int, where: str) -> np.ndarray:
    """The vertex records of an ascii file as a structured array (native byte order)."""
    p = len(vertex.props)
    need = skip + vertex.count * p
    # Every value takes at least one character and one separator: refuse before allocating.
    if need > (body + 1) // 2:
        raise PlyError(f"{where}: truncated: the header declares {vertex.count} vertices "
                       f"({need} ascii values) but only {body} bytes follow the header")
    f.seek(header.data_offset)
    text = f.read()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            values = np.fromstring(text, dtype=np.float64, sep=" ")
        except ValueError:  # numpy versions where unparsable data raises
            values = np.zeros(0)
    if len(values) < need:
        raise PlyError(f"{where}: truncated or invalid ascii data: expected {need} numbers, "
                       f"could read {len(values)}")
    if header.elements[-1] is vertex and len(values) > need:
        raise PlyError(f"{where}: ascii data has more values ({len(values)}) than the header "
                       f"declares ({need})")
    table = values[skip:need].reshape(vertex.count, p)
    records = np.zeros(vertex.count, [(name, code) for name, code in vertex.props])
    with np.errstate(over="ignore", invalid="ignore"):  # float32 overflow -> inf, reported later
        for i, (name, code) in enumerate(vertex.props):
            col = table[:, i]
            if code[0] in "iu":
                info = np.iinfo(code)
                if not (np.all(col == np.round(col)) and np.all((col >= info.min) & (col <= info.max))):
                    raise PlyError(f"{where}: ascii property {name!r} ({code}) holds non-integer "
                                   "or out-of-range values")
            records[name] = col
    return records


# Rows are converted in chunks of about this many bytes, which stay in cache between steps.
_CHUNK_BYTES = 1 << 19


def _chunk_rows(itemsize: int) -> int:
    return max(1, _CHUNK_BYTES // max(1, itemsize))


def _file_chunks(f, dtype: np.dtype, n: int, where: str):
    """(start, records) chunks read from the file's current position into one reused buffer."""
    rows = _chunk_rows(dtype.itemsize)
    buf = np.empty(min(rows, n), dtype)
    raw = buf.view(np.uint8)
    for start in range(0, n, rows):
        m = min(rows, n - start)
        nbytes = m * dtype.itemsize
        if f.readinto(raw[:nbytes]) != nbytes:
            raise PlyError(f"{where}: truncated while reading (did the file change?)")
        yield start, buf[:m]


def _memory_chunks(records: np.ndarray):
    rows = _chunk_rows(records.dtype.itemsize)
    for start in range(0, len(records), rows):
        yield start, records[start:start + rows]


def _block(records: np.ndarray, names: list[str]) -> np.ndarray:
    """(rows, len(names)) array of these fields of `records`: a strided view when they are
    consecutive and of one type (the usual case, and writable), otherwise a stacked copy."""
    fields = records.dtype.fields
    types = [fields[name][0] for name in names]
    offsets = [fields[name][1] for name in names]
    t = types[0]
    if (len(records) and all(x == t for x in types)
            and all(b - a == t.itemsize for a, b in zip(offsets, offsets[1:]))):
        return np.ndarray((len(records), len(names)), t, buffer=records, offset=offsets[0],
                          strides=(records.dtype.itemsize, t.itemsize))
    return np.stack([records[name] for name in names], 1)


def _copy_columns(dst: np.ndarray, src: np.ndarray) -> None:
    """dst[...] = src for (rows, few) arrays, one column at a time: numpy's inner loop then runs
    along the rows instead of along 3 or 4 values."""
    for i in range(dst.shape[1]):
        dst[:, i] = src[:, i]


def _check_finite(values: np.ndarray, ok: np.ndarray) -> None:
    """ok &= row-wise all-finite of `values` (rows, ...). The sum is a cheap test: it is finite
    whenever every value is (or the sum overflows, which the exact test then clears)."""
    if not np.isfinite(values.sum()):
        ok &= np.isfinite(values.reshape(len(values), -1)).all(1)


def _param_groups(k: int) -> list[tuple[str, list[str]]]:
    """Cloud field -> its PLY properties (f_rest channel-major)."""
    return [("means", ["x", "y", "z"]), ("sh_dc", ["f_dc_0", "f_dc_1", "f_dc_2"]),
            ("sh_rest", [f"f_rest_{i}" for i in range(3 * k)]), ("opacities", ["opacity"]),
            ("scales", ["scale_0", "scale_1", "scale_2"]),
            ("quats", ["rot_0", "rot_1", "rot_2", "rot_3"])]


def _cloud_from_records(chunks, dtype: np.dtype, n: int, dtype_comments: dict[str, str]):
    """Convert record chunks into a float32 cloud; also returns the mask of all-finite rows."""
    names = list(dtype.names)
    k = sum(1 for s in names if s.startswith("f_rest_") and s[7:].isdigit()) // 3
    shapes = {"means": (n, 3), "sh_dc": (n, 3), "sh_rest": (n, k, 3), "opacities": (n,),
              "scales": (n, 3), "quats": (n, 4)}
    out = {key: np.empty(shape, np.float32) for key, shape in shapes.items()}
    groups = [(key, cols) for key, cols in _param_groups(k) if cols]
    known = set(_reference_names(k))
    normals = np.empty((n, 3), np.float32) if all(s in names for s in _NORMALS) else None
    if normals is None:
        known -= set(_NORMALS)  # a partial set of normals is kept as ordinary extras
    extra = {name: np.empty(n, dtype[name].newbyteorder("=")) for name in names if name not in known}
    finite = np.empty(n, bool)
    with np.errstate(over="ignore", invalid="ignore"):  # float64 overflow -> inf, reported below
        for start, rec in chunks:
            stop = start + len(rec)
            finite[start:stop] = True
            for key, cols in groups:
                dst = out[key][start:stop]
                if key == "sh_rest":  # PLY: all K red, then green, then blue; cloud: (N, K, 3)
                    dst[...] = _block(rec, cols).reshape(len(rec), 3, k).transpose(0, 2, 1)
                else:
                    _copy_columns(dst.reshape(len(rec), -1), _block(rec, cols))
                _check_finite(dst, finite[start:stop])
            if normals is not None:
                normals[start:stop] = _block(rec, list(_NORMALS))
            for name, arr in extra.items():
                arr[start:stop] = rec[name]
    extras = {}
    if normals is not None and np.any(normals != 0):
        extras.update({s: np.ascontiguousarray(normals[:, i]) for i, s in enumerate(_NORMALS)})
    for name, col in extra.items():
        want = dtype_comments.get(name)
        if want is not None:
            cast = col.astype(want)
            if np.array_equal(cast.astype(col.dtype), col):
                col = cast
        extras[name] = col
    return GaussianCloud(**out, extra=extras), finite


# ----------------------------------------------------------------------------------- write

def write_ply(cloud: GaussianCloud, path) -> Path:
    """Write `cloud` as a binary little-endian 3DGS PLY (reference order, then `extra`).

    Atomic: the data goes to a temporary file in the same directory, renamed into place only
    when complete. Refuses (PlyError) clouds with non-finite parameters and extras PLY cannot
    hold. Returns the path."""
    path = Path(path)
    where = str(path)
    if cloud.is_torch:
        cloud = cloud.numpy()
    n, k = len(cloud), SH_REST_COUNTS[cloud.sh_degree]
    ref = _reference_names(k)
    extras, comments = _prepare_extras(cloud.extra, n, ref, where)
    normals = [np.asarray(_np(cloud.extra[s])).reshape(n) if s in cloud.extra else None
               for s in _NORMALS]
    props = [(name, "<f4") for name in ref] + [(name, a.dtype.str) for name, a in extras]
    dtype = np.dtype(props)
    groups = [(key, cols) for key, cols in _param_groups(k) if cols]
    with np.errstate(over="ignore", invalid="ignore"):  # float64 beyond float32 -> inf, refused below
        params = {key: np.asarray(a, np.float32) for key, a in cloud.arrays().items()}

    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment gvae_dtype {name} {dt}" for name, dt in comments]
    if cloud.background is not None:
        lines.append(f"comment {BACKGROUND_COMMENT} " + " ".join(repr(float(v)) for v in cloud.background))
    lines.append(f"element vertex {n}")
    lines += [f"property {_WRITE_NAMES[np.dtype(t).str[1:]]} {name}" for name, t in props]
    lines.append("end_header")
    head = ("\n".join(lines) + "\n").encode("ascii")

    def write_body(f) -> None:
        f.write(head)
        rows = _chunk_rows(dtype.itemsize)
        buf = np.empty(min(rows, n), dtype)
        raw = buf.view(np.uint8)
        finite = np.empty(n, bool)
        with np.errstate(over="ignore", invalid="ignore"):  # sums may overflow: exact test then
            for start in range(0, n, rows):
                stop = min(n, start + rows)
                rec = buf[:stop - start]
                finite[start:stop] = True
                for key, cols in groups:
                    dst = _block(rec, cols)
                    src = params[key][start:stop]
                    if key == "sh_rest":
                        dst.reshape(len(rec), 3, k)[...] = src.transpose(0, 2, 1)
                    else:
                        _copy_columns(dst, src.reshape(len(rec), -1))
                    _check_finite(src, finite[start:stop])
                dst = _block(rec, list(_NORMALS))
                for i, v in enumerate(normals):
                    dst[:, i] = 0.0 if v is None else v[start:stop]
                for name, a in extras:
                    rec[name] = a[start:stop]
                f.write(raw[:len(rec) * dtype.itemsize])
        if not finite.all():
            bad = np.flatnonzero(~finite)
            head_rows = ", ".join(str(i) for i in bad[:5]) + (", ..." if len(bad) > 5 else "")
            raise PlyError(f"{where}: refusing to write {len(bad)} Gaussian(s) with non-finite "
                           f"parameters, rows [{head_rows}]; use cloud.sanitize() first")

    return atomic_write(path, write_body)


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if type(x).__module__.startswith("torch") else np.asarray(x)


def _prepare_extras(extra: dict, n: int, ref: list[str], where: str):
    """Extra columns as (name, little-endian array) in a PLY type, plus dtype comments."""
    reserved = set(ref)
    out, comments = [], []
    for name, value in extra.items():
        if name in _NORMALS:
            continue
        if (name in reserved or not name or not name.isascii() or any(c.isspace() for c in name)
                or (name.startswith("f_rest_") and name[7:].isdigit())):
            raise PlyError(f"{where}: cannot write extra property {name!r}: not a valid or free "
                           "PLY property name")
        a = _np(value)
        if a.shape != (n,):
            raise PlyError(f"{where}: cannot write extra property {name!r} of shape {a.shape}: "
                           f"PLY holds one scalar per Gaussian, shape ({n},)")
        a, original = _ply_storable(a, name, where)
        if original is not None:
            comments.append((name, original))
        out.append((name, a.astype(a.dtype.newbyteorder("<"), copy=False)))
    return out, comments


def _ply_storable(a: np.ndarray, name: str, where: str):
    """`a` in a PLY scalar type that holds it exactly, and the dtype name to restore (or None)."""
    code = a.dtype.str[1:]
    if code in _WRITE_NAMES:
        return a, None
    kind = a.dtype.name
    if kind == "bool":
        return a.astype(np.uint8), "bool"
    if kind == "float16":
        return a.astype(np.float32), "float16"
    if kind in ("int64", "uint64"):
        for target in ((np.int32, np.float64) if kind == "int64" else (np.uint32, np.float64)):
            if target is np.float64:
                ok = len(a) == 0 or int(np.abs(a.astype(np.float64)).max()) <= 2 ** 53
            else:
                info = np.iinfo(target)
                ok = len(a) == 0 or (int(a.min()) >= info.min and int(a.max()) <= info.max)
            if ok and np.array_equal(a.astype(target).astype(a.dtype), a):
                return a.astype(target), kind
        raise PlyError(f"{where}: cannot write extra property {name!r}: {kind} values beyond "
                       "2**53 have no exact PLY type")
    raise PlyError(f"{where}: cannot write extra property {name!r} of dtype {a.dtype}: "
                   "PLY holds 8..32-bit integers, float32 and float64")
