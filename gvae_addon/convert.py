"""Blender mesh <-> `GaussianCloud`: the only place that moves Gaussian data in and out of Blender.

A splat object is a mesh whose vertices are the Gaussian centres. Every other PLY property is a
point attribute under its PLY name (`f_dc_0`, `f_rest_12`, `opacity`, `scale_0`, `rot_0`, ...),
stored losslessly so that export writes back exactly what was imported:
- the parameters and float32/float16 extras as FLOAT;
- int8 extras as INT8, bool as BOOLEAN, uint8/int16/uint16/int32 as INT (same values);
- uint32 as INT and float64/int64/uint64 as INT32_2D holding the raw bits.
The mesh's custom property `gvae_ply` (JSON) records the SH degree and the extra properties with
their dtypes, in file order, and the background the cloud was trained over (when it is known).
All transfers are vectorised (`foreach_get`/`foreach_set`).

Blender 5.3 and later also draw Gaussian splats themselves: a point cloud of type GAUSSIAN_SPLAT
(`pointcloud_from_cloud`, `cloud_from_pointcloud`) with the attributes Blender's own PLY importer
gives one: `position`, `radiance:base` (f_dc and the opacity after the sigmoid), `scale` (exp of the
log-scales), `rotation` (unit quaternion w, x, y, z) and `radiance:sh_0..` (one per SH rest
coefficient, RGB); extra properties as point attributes, recorded in `gvae_ply` as on a mesh.
"""

from __future__ import annotations

import json

import bpy
import numpy as np

from gvae_core.cloud import GaussianCloud
from gvae_core.conventions import LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_REST_COUNTS, sigmoid

LAYOUT_KEY = "gvae_ply"
STEP_ATTR = "gvae_step"
#: The object's custom property naming the file its Gaussians were imported from (New from Photos: its
#: run's last stage): where Compact looks for the cameras its training left (`capture.training_cameras`).
SOURCE_PROP = "gvae_source"
#: Names the add-on keeps for itself: never stored as a PLY extra property.
_RESERVED = {"position", STEP_ATTR}

# dtype char code -> (Blender attribute type, storage kind): "value" keeps values, "bits" raw bytes.
_EXTRA_STORAGE = {
    "f4": ("FLOAT", "value"), "f2": ("FLOAT", "value"),
    "i1": ("INT8", "value"), "b1": ("BOOLEAN", "value"),
    "u1": ("INT", "value"), "i2": ("INT", "value"), "u2": ("INT", "value"), "i4": ("INT", "value"),
    "u4": ("INT", "bits"),
    "f8": ("INT32_2D", "bits"), "i8": ("INT32_2D", "bits"), "u8": ("INT32_2D", "bits"),
}
_BUFFER_DTYPE = {"FLOAT": np.float32, "INT": np.int32, "INT8": np.int8, "BOOLEAN": bool,
                 "INT32_2D": np.int32}


def param_columns(sh_degree: int) -> list[str]:
    """PLY names of the per-Gaussian parameters held as FLOAT attributes (all but x, y, z)."""
    k = SH_REST_COUNTS[sh_degree]
    return (["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * k)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _transposed(a: np.ndarray, axes: tuple[int, ...], along: int = 0,
                out: np.ndarray | None = None) -> np.ndarray:
    """`np.ascontiguousarray(a.transpose(axes))` (into `out` when given), copied in blocks of
    about 256 KiB along the long input axis `along` so that each block stays in the CPU cache (the
    (N, C) <-> (C, N) moves of big clouds take less CPU time than numpy's strided copy)."""
    shape = tuple(a.shape[i] for i in axes)
    if out is None:
        out = np.empty(shape, a.dtype)
    elif out.shape != shape:
        raise ValueError(f"_transposed: out has shape {out.shape}, expected {shape}")
    per_slice = a.itemsize * (a.size // max(1, a.shape[along]))
    step = max(64, (256 << 10) // max(1, per_slice))
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    for start in range(0, a.shape[along], step):
        src[along] = dst[axes.index(along)] = slice(start, start + step)
        out[tuple(dst)] = a[tuple(src)].transpose(axes)
    return out


def _param_table(cloud: GaussianCloud) -> np.ndarray:
    """(C, N) float32 table whose rows are the `param_columns` of `cloud`."""
    n, k = len(cloud), SH_REST_COUNTS[cloud.sh_degree]
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    table = np.empty((len(param_columns(cloud.sh_degree)), n), np.float32)
    _transposed(f32(cloud.sh_dc), (1, 0), out=table[0:3])
    if k:  # PLY f_rest is channel-major: row c*K + k holds sh_rest[:, k, c]
        _transposed(f32(cloud.sh_rest), (2, 1, 0), out=table[3:3 + 3 * k].reshape(3, k, n))
    table[3 + 3 * k] = f32(cloud.opacities)
    _transposed(f32(cloud.scales), (1, 0), out=table[4 + 3 * k:7 + 3 * k])
    _transposed(f32(cloud.quats), (1, 0), out=table[7 + 3 * k:])
    return table


def _check_extra_name(name: str) -> None:
    if name in _RESERVED or name.startswith("."):
        raise ValueError(f"PLY property {name!r} cannot be stored as a Blender attribute "
                         "(the name is reserved)")


def _new_attribute(me, name: str, kind: str):
    """A new point attribute that really has `name` (Blender refuses some built-in names and
    renames on collisions or overlong names: that would silently lose the PLY name)."""
    attr = me.attributes.new(name, kind, "POINT")
    if attr is None or attr.name != name:
        raise ValueError(f"PLY property {name!r} cannot be stored as a Blender attribute under that "
                         "name (reserved by Blender, duplicate, or longer than 63 bytes)")
    return attr


def _extra_to_buffer(a: np.ndarray) -> tuple[str, np.ndarray]:
    """An extra column as (Blender attribute type, flat buffer for foreach_set)."""
    code = a.dtype.str[1:]
    if code not in _EXTRA_STORAGE:
        raise ValueError(f"extra property of dtype {a.dtype} has no Blender attribute type")
    kind, storage = _EXTRA_STORAGE[code]
    native = a.astype(a.dtype.newbyteorder("="), copy=False)
    if storage == "bits":
        buf = np.ascontiguousarray(native).view(np.int32)
    else:
        buf = native.astype(_BUFFER_DTYPE[kind])
    return kind, np.ascontiguousarray(buf).ravel()


def _extra_from_buffer(buf: np.ndarray, dtype: np.dtype) -> np.ndarray:
    storage = _EXTRA_STORAGE[dtype.str[1:]][1]
    native = dtype.newbyteorder("=")
    if storage == "bits":
        return buf.view(native).astype(dtype, copy=False)
    return buf.astype(dtype)


def _set(attr, prop: str, buf: np.ndarray) -> None:
    attr.data.foreach_set(prop, buf)


def mesh_from_cloud(cloud: GaussianCloud, name: str, steps: np.ndarray | None = None) -> bpy.types.Mesh:
    """A new mesh holding `cloud` (vertices = centres, one attribute per PLY property).

    `steps` (N,) ints, when given, becomes the `gvae_step` attribute. On any failure the
    half-built mesh is removed, so the blend file is left as it was."""
    cloud = cloud.numpy()
    n = len(cloud)
    extras = list(cloud.extra.items())
    for key, value in extras:
        _check_extra_name(key)
        if value.shape != (n,):
            raise ValueError(f"extra property {key!r} has shape {value.shape}; one value per "
                             "Gaussian is expected")
    buffers = [(key, *_extra_to_buffer(value)) for key, value in extras]
    me = bpy.data.meshes.new(name)
    try:
        me.vertices.add(n)
        _set(me.attributes["position"], "vector",
             np.ascontiguousarray(cloud.means, np.float32).ravel())
        for col, values in zip(param_columns(cloud.sh_degree), _param_table(cloud)):
            _set(_new_attribute(me, col, "FLOAT"), "value", values)
        for key, kind, buf in buffers:
            _set(_new_attribute(me, key, kind), "value", buf)
        if steps is not None:
            _set(_new_attribute(me, STEP_ATTR, "INT"), "value",
                 np.ascontiguousarray(steps, np.int32).ravel())
        me[LAYOUT_KEY] = _layout_json(cloud)
        me.update()
    except BaseException:
        bpy.data.meshes.remove(me)
        raise
    return me


def _layout_json(cloud: GaussianCloud) -> str:
    """What `gvae_ply` records of a cloud: SH degree, extra properties, the background it was
    trained over (when known)."""
    info = {"sh_degree": cloud.sh_degree, "extra": [[key, value.dtype.str] for key, value in cloud.extra.items()]}
    if cloud.background is not None:
        info["background"] = list(cloud.background)
    return json.dumps(info)


def layout(me: bpy.types.Mesh) -> dict:
    """The stored PLY layout of a splat mesh; for a mesh without one (made by hand or by another
    add-on) it is inferred from the attributes: SH degree from the `f_rest_*` count, no extras."""
    raw = me.get(LAYOUT_KEY)
    if raw is not None:
        return json.loads(raw)
    rest = sum(1 for a in me.attributes if a.name.startswith("f_rest_") and a.name[7:].isdigit())
    degree = {3 * k: d for d, k in SH_REST_COUNTS.items()}.get(rest)
    if degree is None:
        raise ValueError(f"mesh {me.name!r} has {rest} f_rest_* attributes; expected 0, 9, 24 or 45")
    return {"sh_degree": degree, "extra": []}


def is_splat(obj) -> bool:
    """A mesh object that carries Gaussian attributes (made by the importer or compatible)."""
    if obj is None or obj.type != "MESH":
        return False
    me = obj.data
    return LAYOUT_KEY in me or all(c in me.attributes for c in ("f_dc_0", "opacity", "scale_0", "rot_0"))


def _get(me, name: str, kind: str, width: int, n: int, out: np.ndarray | None = None) -> np.ndarray:
    attr = me.attributes.get(name)
    if attr is None:
        raise ValueError(f"mesh {me.name!r} has no attribute {name!r}: not a complete Gaussian splat")
    if attr.domain != "POINT" or attr.data_type != kind:
        raise ValueError(f"attribute {name!r} of mesh {me.name!r} is {attr.data_type} on "
                         f"{attr.domain}; expected {kind} on POINT")
    buf = np.empty(n * width, _BUFFER_DTYPE.get(kind, np.float32)) if out is None else out
    attr.data.foreach_get("vector" if name == "position" else "value", buf)
    return buf


def cloud_from_mesh(me: bpy.types.Mesh) -> tuple[GaussianCloud, np.ndarray | None]:
    """The Gaussians of a splat mesh, and its `gvae_step` values (or None when it has none)."""
    info = layout(me)
    n = len(me.vertices)
    degree = int(info["sh_degree"])
    k = SH_REST_COUNTS[degree]
    means = _get(me, "position", "FLOAT_VECTOR", 3, n).reshape(n, 3)
    names = param_columns(degree)
    table = np.empty((len(names), n), np.float32)
    for row, name in zip(table, names):
        _get(me, name, "FLOAT", 1, n, out=row)
    rows = _transposed(table, (1, 0), along=1)  # (N, C): row-major again, as the PLY writer wants it
    extra = {}
    for key, dt in info["extra"]:
        dtype = np.dtype(dt)
        kind = _EXTRA_STORAGE[dtype.str[1:]][0]
        width = 2 if kind == "INT32_2D" else 1
        extra[key] = _extra_from_buffer(_get(me, key, kind, width, n), dtype)
    o = 3 + 3 * k
    cloud = GaussianCloud(means=means, sh_dc=rows[:, 0:3],
                          sh_rest=rows[:, 3:o].reshape(n, 3, k).transpose(0, 2, 1),
                          opacities=rows[:, o], scales=rows[:, o + 1:o + 4], quats=rows[:, o + 4:o + 8],
                          extra=extra, background=info.get("background"))
    steps = _get(me, STEP_ATTR, "INT", 1, n) if STEP_ATTR in me.attributes else None
    return cloud, steps


def cloud_from_object(obj) -> tuple[GaussianCloud, np.ndarray | None]:
    """The Gaussians of a splat object's own (unevaluated) data, edit-mode changes included: a
    splat mesh (`cloud_from_mesh`) or a Blender 5.3+ Gaussian-splat point cloud (`cloud_from_pointcloud`),
    and its `gvae_step` values (None when it has none)."""
    if not (is_splat(obj) or is_native_splat(obj)):
        raise ValueError(f"object {getattr(obj, 'name', None)!r} is not a Gaussian splat object "
                         "(import one with File > Import > Gaussian Splat)")
    if obj.mode == "EDIT":
        obj.update_from_editmode()
    if is_native_splat(obj):
        pc = obj.data
        steps = _get(pc, STEP_ATTR, "INT", 1, len(pc.points)) if STEP_ATTR in pc.attributes else None
        return cloud_from_pointcloud(pc), steps
    return cloud_from_mesh(obj.data)


# ------------------------------------------------------------------ Blender's own Gaussian splats

NATIVE_BASE, NATIVE_SCALE, NATIVE_ROTATION = "radiance:base", "scale", "rotation"
_NATIVE_RESERVED = {"position", NATIVE_BASE, NATIVE_SCALE, NATIVE_ROTATION}


def native_sh(j: int) -> str:
    """The attribute of SH rest coefficient j (0-based, in `sh_rest` order) of a native splat."""
    return f"radiance:sh_{j}"


def native_available() -> bool:
    """Whether this Blender draws Gaussian splats itself (point clouds of type GAUSSIAN_SPLAT, 5.3+)."""
    point_cloud = getattr(bpy.types, "PointCloud", None)
    prop = point_cloud.bl_rna.properties.get("type") if point_cloud is not None else None
    return prop is not None and "GAUSSIAN_SPLAT" in prop.enum_items.keys()


def is_native_splat(obj) -> bool:
    return obj is not None and obj.type == "POINTCLOUD" and getattr(obj.data, "type", None) == "GAUSSIAN_SPLAT"


def is_any_splat(obj) -> bool:
    """A splat object of either kind: the add-on's splat mesh or Blender's own Gaussian-splat point cloud."""
    return is_splat(obj) or is_native_splat(obj)


def splat_count(obj) -> int:
    """How many Gaussians a splat object of either kind holds."""
    return len(obj.data.points) if is_native_splat(obj) else len(obj.data.vertices)


def native_sh_degree(pc) -> int:
    """The SH degree of a Gaussian-splat point cloud, from its `radiance:sh_*` attributes."""
    k = sum(1 for a in pc.attributes if a.name.startswith("radiance:sh_") and a.name[12:].isdigit())
    degree = {count: d for d, count in SH_REST_COUNTS.items()}.get(k)
    if degree is None or any(native_sh(j) not in pc.attributes for j in range(k)):
        raise ValueError(f"point cloud {pc.name!r} has {k} radiance:sh_* attributes; expected 0, 3, 8 or 15 "
                         "numbered from 0")
    return degree


def pointcloud_from_cloud(cloud: GaussianCloud, name: str, steps: np.ndarray | None = None) -> bpy.types.PointCloud:
    """A new Gaussian-splat point cloud (Blender 5.3+) holding `cloud`, the attributes as Blender's own
    PLY importer makes them (exp and sigmoid in float64; quaternions normalised, zero: the identity);
    extra properties as point attributes; `steps` (N,) ints, when given, the `gvae_step` attribute. Removed
    again if anything fails."""
    if not native_available():
        raise ValueError(f"Blender {bpy.app.version_string} has no Gaussian-splat point clouds (5.3 and later)")
    c = cloud.numpy()
    n, k = len(c), c.sh_rest.shape[1]
    extras = list(c.extra.items())
    for key, value in extras:
        if key in _NATIVE_RESERVED or key.startswith(("radiance:", ".")):
            raise ValueError(f"extra property {key!r} cannot be stored beside a Gaussian splat's own attributes")
        if value.shape != (n,):
            raise ValueError(f"extra property {key!r} has shape {value.shape}; one value per Gaussian is expected")
    buffers = [(key, *_extra_to_buffer(value)) for key, value in extras]
    q = np.asarray(c.quats, np.float64)
    norm = np.linalg.norm(q, axis=1)
    good = norm > 1e-12
    q = np.where(good[:, None], q / np.where(good, norm, 1.0)[:, None], (1.0, 0.0, 0.0, 0.0))
    base = np.empty((n, 4), np.float32)
    base[:, :3] = c.sh_dc
    base[:, 3] = sigmoid(c.opacities.astype(np.float64))
    with np.errstate(over="ignore"):
        linear = np.exp(c.scales.astype(np.float64)).astype(np.float32)
    pc = bpy.data.pointclouds.new(name)
    try:
        pc.resize(n)
        pc.type = "GAUSSIAN_SPLAT"
        _set(pc.attributes["position"], "vector", np.ascontiguousarray(c.means, np.float32).ravel())
        _set(_new_attribute(pc, NATIVE_BASE, "FLOAT4"), "vector", base.ravel())
        _set(_new_attribute(pc, NATIVE_SCALE, "FLOAT_VECTOR"), "vector", linear.ravel())
        _set(_new_attribute(pc, NATIVE_ROTATION, "QUATERNION"), "value", q.astype(np.float32).ravel())
        for j in range(k):
            _set(_new_attribute(pc, native_sh(j), "FLOAT_VECTOR"), "vector",
                 np.ascontiguousarray(c.sh_rest[:, j], np.float32).ravel())
        for key, kind, buf in buffers:
            _set(_new_attribute(pc, key, kind), "value", buf)
        if steps is not None:
            _set(_new_attribute(pc, STEP_ATTR, "INT"), "value", np.ascontiguousarray(steps, np.int32).ravel())
        pc[LAYOUT_KEY] = _layout_json(c)
    except BaseException:
        bpy.data.pointclouds.remove(pc)
        raise
    return pc


#: The PLY type a point attribute that `gvae_ply` does not record is read back as (Blender's own PLY importer
#: keeps a file's extra properties as point attributes of these types).
_PLAIN_EXTRA = {"FLOAT": "<f4", "INT": "<i4", "INT8": "|i1", "BOOLEAN": "|b1"}


def _unrecorded_extras(pc, info: dict) -> list:
    """[name, dtype] of the point attributes of a Gaussian-splat point cloud that are extra properties
    but not recorded in its `gvae_ply` (all of them for one made by Blender's own PLY importer, which
    keeps a file's extra properties, `filter_3D` or a refinement's `gvae_octave_*`, as attributes):
    plain one-value attributes, in the cloud's order, but the add-on's own and Blender's point `radius`."""
    known = {key for key, _ in info["extra"]} | _NATIVE_RESERVED | _RESERVED | {"radius"}
    return [[a.name, _PLAIN_EXTRA[a.data_type]] for a in pc.attributes
            if a.domain == "POINT" and a.data_type in _PLAIN_EXTRA and a.name not in known
            and not a.name.startswith((".", "radiance:"))]


def cloud_from_pointcloud(pc) -> GaussianCloud:
    """The Gaussians of a Gaussian-splat point cloud (made here or by Blender itself): log-scales and
    logits in float64 of its linear values, a zero scale read as a flat axis (LOG_SCALE_RANGE[0]) and
    an opacity of 0 or 1 as the ends of OPACITY_LOGIT_RANGE; extras as recorded in `gvae_ply`, then every
    other plain point attribute (`_unrecorded_extras`)."""
    n = len(pc.points)
    for name, kind in (("position", "FLOAT_VECTOR"), (NATIVE_BASE, "FLOAT4"), (NATIVE_SCALE, "FLOAT_VECTOR"),
                       (NATIVE_ROTATION, "QUATERNION")):
        attr = pc.attributes.get(name)
        if attr is None or attr.domain != "POINT" or attr.data_type != kind:
            raise ValueError(f"point cloud {pc.name!r} has no {kind} point attribute {name!r}: not a complete "
                             "Gaussian splat")
    k = SH_REST_COUNTS[native_sh_degree(pc)]

    def get(name: str, prop: str, width: int) -> np.ndarray:
        buf = np.empty(n * width, np.float32)
        pc.attributes[name].data.foreach_get(prop, buf)
        return buf.reshape(n, width)

    base = get(NATIVE_BASE, "vector", 4)
    with np.errstate(divide="ignore"):
        scales = np.log(get(NATIVE_SCALE, "vector", 3).astype(np.float64))
        p = base[:, 3].astype(np.float64)
        logits = np.log(p / (1.0 - p))
    scales[np.isneginf(scales)] = LOG_SCALE_RANGE[0]
    logits = np.clip(logits, *OPACITY_LOGIT_RANGE)
    rest = np.empty((n, k, 3), np.float32)
    for j in range(k):
        rest[:, j] = get(native_sh(j), "vector", 3)
    extra = {}
    info = json.loads(pc.get(LAYOUT_KEY, '{"extra": []}'))
    for key, dt in info["extra"] + _unrecorded_extras(pc, info):
        dtype = np.dtype(dt)
        kind = _EXTRA_STORAGE[dtype.str[1:]][0]
        extra[key] = _extra_from_buffer(_get(pc, key, kind, 2 if kind == "INT32_2D" else 1, n), dtype)
    return GaussianCloud(means=get("position", "vector", 3), scales=scales.astype(np.float32),
                         quats=get(NATIVE_ROTATION, "value", 4), opacities=logits.astype(np.float32),
                         sh_dc=np.ascontiguousarray(base[:, :3]), sh_rest=rest, extra=extra,
                         background=info.get("background"))
