"""The Geometry Nodes group and the material that draw a splat object as the Gaussians it holds.

Geometry Nodes (one group per SH degree, since the `f_rest_*` layout depends on it), per Gaussian,
following the reference renderer (DESIGN.md, Rendering semantics) for the scene's active camera:
- size: the standard deviations exp(clamped `scale_0..2`) times the Scale Factor, each variance
  widened by the cloud's anti-aliasing (`gvae_core.antialias`, the renderer's "auto" mode):
  Mip-Splatting's 3D filter `filter_3D` (+f², opacity x prod s / sqrt(s² + f²)) and its 2D
  filter (0.1 px², opacity compensated), or for a cloud without `filter_3D` the classic
  dilation (0.3 px², opacity unchanged; held at least at `gvae_dilation_3D`² when the cloud
  has it). A screen-space variance v px² becomes the isotropic world variance v (z / f)² at
  the Gaussian's depth z from the camera (f: the camera's focal length in pixels of the render,
  the "Focal Length (px)" input that `render_setup` keeps in step): its projection is the
  renderer's v I in pixels;
- a refined cloud (`gvae_core.octaves`, as `gvae_core.render` draws it): t = the octaves above the
  Gaussian's training rate (from its stored anti-aliasing size) at which the scene camera draws its
  stored centre (0 at the training resolution); every parameter with a change per octave is drawn
  as p + t dp: the centre (`gvae_octave_position_*`: the instance is placed there, and the depth,
  view direction and filters are the drawn centre's), the w,x,y,z quaternion, log-scales, opacity
  logit, DC colour and SH coefficients (`gvae_octave_rest_<3 j + c>` for `f_rest_<c K + j>`); the
  anti-aliasing size (filter_3D or gvae_dilation_3D) times e^min(t dsize, 0). A Gaussian added by
  refinement (opacity below 1/255 at its training rate) so appears only above that rate;
- colour: SH_C0 * f_dc + 0.5 plus, with View-Dependent Colour on, the SH bands for the direction
  camera -> centre in the object's own frame; clamped at 0 and converted from sRGB to linear
  (splat colours are display-referred: the Standard view transform gives them back);
- one primitive instanced at the centre, rotated by the w,x,y,z quaternion `rot_0..3` and scaled
  so that instance space is the Gaussian's whitened frame in units of the radius where its
  alpha can reach 1/255, sqrt(2 ln(255 o)) std-devs (Gaussians below 1/255 opacity are not
  drawn at all): in the viewport a low-poly icosphere enclosing that ellipsoid (right from every
  side); in renders (Camera-Facing in Renders, the default) a disc through the centre turned, in
  that frame, to face the scene camera: one surface per Gaussian, met where the ray crosses the
  plane through the centre, so Cycles and EEVEE composite the Gaussians in the order of their
  centres' depths as the reference does, with half the transparent bounces.
The colour and the opacity are stored on the instances (points with Points Only) as
`gvae_color` (linear) and `gvae_alpha`; every other attribute is dropped before instancing.

Material: alpha = min(0.99, o exp(-d²/2)) with d the Mahalanobis distance of the ray's closest
approach to the centre (computed in instance space from the hit point and the ray direction),
zero below 1/255; written o (255 o)^(-q) with q = d² / radius², which needs only o, and the same
for any primitive shape or turn in that frame. Emitted colour `gvae_color` over a transparent
BSDF; back faces are transparent (each Gaussian is blended once). Cycles and EEVEE. With Points
Only, a point cloud of constant alpha (a preview).
"""
from __future__ import annotations

import math

import bpy

from gvae_core.antialias import CLASSIC_DILATION, DILATION_KEY, FILTER_3D_VARIANCE, FILTER_KEY
from gvae_core.octaves import DEADBAND as OCTAVE_DEADBAND
from gvae_core.octaves import LIMIT_KEY as OCTAVE_LIMIT_KEY
from gvae_core.octaves import SIZE, field_keys
from gvae_core.conventions import (ALPHA_MAX, ALPHA_MIN, LOG_SCALE_RANGE, MIP_2D_VARIANCE, OPACITY_LOGIT_RANGE,
                                   SH_C0, SH_C1, SH_C2, SH_C3, SH_REST_COUNTS, SRGB_EOTF)

from .convert import layout, native_sh_degree

GROUP_NAME = "GaussianVAE Splats"
#: The group of the modifier on Blender 5.3+'s own Gaussian-splat point clouds (`add_native_modifier`).
NATIVE_GROUP_NAME = "GaussianVAE Native Splats"
GROUP_NAMES = (GROUP_NAME, NATIVE_GROUP_NAME)
MATERIAL_NAME = "GaussianVAE Splat"
MODIFIER_NAME = "GaussianVAE Splats"
COLOR_ATTR = "gvae_color"
ALPHA_ATTR = "gvae_alpha"
#: Bumped when the node setup changes; an older group or material in a blend file is rebuilt in place.
NODES_VERSION = 6
#: Multiplies every Gaussian's standard deviations (1: the Gaussians as trained).
DEFAULT_SCALE_FACTOR = 1.0
#: Circumradius of Blender's icosphere (subdivisions d) that encloses the unit sphere is
#: 1 + a * b^(1 - d): 1.2585, 1.0706, 1.0193, 1.0053 >= the exact 1.2584, 1.0705, 1.0181, 1.0045.
_ICO_ENCLOSE = (0.2585, 3.66)
#: The camera-facing disc (whitened frame, unit = the visible radius): an octagon around the
#: circle of radius DISC_RADIUS. A disc through the centre of the unit sphere, perpendicular to
#: the direction of a camera at distance D, holds the sphere's silhouette when its radius is
#: D / sqrt(D² - 1): 1.1 covers D >= 2.4 visible radii; nearer, only alpha below 1.3% (D >= 1.5)
#: is cut.
DISC_RADIUS, DISC_SIDES = 1.1, 8

# Interface: (name, socket type, default, min, max, description)
INPUTS = (
    ("Scale Factor", "NodeSocketFloat", DEFAULT_SCALE_FACTOR, 0.0, 100.0,
     "Multiplies every Gaussian's size (1: as trained)"),
    ("View-Dependent Colour", "NodeSocketBool", True, None, None,
     "Spherical-harmonics colour seen from the scene camera; off: the base (DC) colour only, "
     "faster and independent of the camera"),
    ("Display Fraction", "NodeSocketFloat", 1.0, 0.0, 1.0,
     "Fraction of the splats shown (a fixed random subset, for large scenes)"),
    ("Points Only", "NodeSocketBool", False, None, None,
     "Show one point per Gaussian instead of ellipsoids (fast for large scenes)"),
    ("Min Opacity", "NodeSocketFloat", 0.0, 0.0, 1.0, "Hide splats whose opacity is below this"),
    ("Viewport Only", "NodeSocketBool", True, None, None,
     "Display Fraction and Points Only act in the viewport only; renders show every splat as itself"),
    ("Camera-Facing in Renders", "NodeSocketBool", True, None, None,
     "Renders draw each Gaussian as one disc through its centre facing the scene camera (composited "
     "in the order of the centres' depths, as the reference renderer does, and half the transparent "
     "bounces); off, or in the viewport: the ellipsoid, right from every side"),
    ("Detail", "NodeSocketInt", 1, 1, 4, "Subdivisions of the icosphere drawn per Gaussian"),
    ("Material", "NodeSocketMaterial", None, None, None, "Material of the splats"),
)
#: Inputs the import sets (not in the sidebar; the modifier shows them): the screen-space
#: anti-aliasing of the reference renderer, emulated per Gaussian at its depth from the scene
#: camera, and the camera's focal length in pixels (render_setup's handlers keep it in step with
#: the scene's camera and render size).
HIDDEN_INPUTS = (
    ("Screen Filter", "NodeSocketFloat", CLASSIC_DILATION, 0.0, 10.0,
     "Screen-space variance (px²) added to every Gaussian at the render resolution, as the reference "
     "renderer does: 0.3 without opacity change (3DGS) or 0.1 with Compensate (Mip-Splatting)"),
    ("Compensate Screen Filter", "NodeSocketBool", False, None, None,
     "Scale the opacity so that the screen filter keeps each Gaussian's integral (Mip-Splatting's 2D filter)"),
    ("Focal Length (px)", "NodeSocketFloat", 0.0, 0.0, 1e7,
     "Focal length of the scene camera in pixels of the render (driven); 0 turns the screen filter off"),
)


#: The inputs of the modifier on a Gaussian-splat point cloud (beside HIDDEN_INPUTS).
NATIVE_INPUTS = (
    ("Refinement", "NodeSocketBool", True, None, None,
     "A refined splat's changes per octave, drawn by the rate the scene camera samples each Gaussian at (none "
     "at or below its training resolution); off: the splat as it was before refining"),
    ("Anti-Aliasing", "NodeSocketBool", True, None, None,
     "The reference renderer's anti-aliasing for the scene camera (3DGS's screen-space dilation, or "
     "Mip-Splatting's filters for a splat trained with them), as gvae render and 3DGS viewers draw it; off: "
     "Blender draws the stored Gaussians as they are (thinner, aliased where they are smaller than a pixel)"),
)


#: Socket type (`NodeSocket.type`) of each interface socket type and node data type used here.
SOCKET_KIND = {"NodeSocketFloat": "VALUE", "NodeSocketBool": "BOOLEAN", "NodeSocketInt": "INT",
               "NodeSocketMaterial": "MATERIAL", "NodeSocketGeometry": "GEOMETRY", "FLOAT": "VALUE",
               "FLOAT_VECTOR": "VECTOR", "VECTOR": "VECTOR", "BOOLEAN": "BOOLEAN", "ROTATION": "ROTATION",
               "GEOMETRY": "GEOMETRY", "QUATERNION": "ROTATION", "FLOAT_COLOR": "RGBA"}


def sockets(node, name: str, kind: str, *, output: bool = False) -> list:
    """The enabled inputs (outputs) of `node` called `name`, by label or identifier (the identifier
    stays when Blender renames a label: Mix Shader's "Fac" is shown as "Factor" from 5.0), whose
    type (`NodeSocket.type`) is `kind`, in the node's order."""
    return [s for s in (node.outputs if output else node.inputs)
            if s.enabled and s.type == kind and name in (s.name, s.identifier)]


def socket(node, name: str, kind: str, *, output: bool = False, nth: int | None = None):
    """The one enabled input (output) of `node` called `name` of type `kind`; `nth` picks among
    sockets that share name and type (Math's "Value" inputs, in order).

    Every socket the add-on wires is found this way, never by position: the order and number of a
    node's sockets change between Blender versions (Random Value's outputs in 5.2, Capture
    Attribute's new Selection). Raises LookupError naming the node, the socket and the Blender version."""
    found = sockets(node, name, kind, output=output)
    if (len(found) == 1 and not nth) or (nth is not None and nth < len(found)):
        return found[nth or 0]
    side = "output" if output else "input"
    has = ", ".join(f"{s.name} ({s.type})" for s in (node.outputs if output else node.inputs) if s.enabled)
    what = (f"{len(found)} {side}s" if len(found) > 1 and nth is None else f"no {side}" if not found
            else f"{len(found)} {side}s (not #{nth})")
    raise LookupError(f"Blender {bpy.app.version_string}: node {node.bl_idname} \"{node.name}\" has {what} "
                      f"\"{name}\" of type {kind}; its {side}s: {has or 'none'}")


def inp(node, name: str, kind: str, nth: int | None = None):
    return socket(node, name, kind, nth=nth)


def outp(node, name: str, kind: str):
    return socket(node, name, kind, output=True)


class _Builder:
    """Adds and links nodes with less noise; `arrange()` lays them out in columns by link depth."""

    def __init__(self, tree):
        self.tree = tree
        self.nodes = []
        self.edges = []  # (from node index, to node index): RNA look-ups are slow, keep our own

    def node(self, kind: str, **props):
        n = self.tree.nodes.new(kind)
        for key, value in props.items():
            setattr(n, key, value)
        n["gvae_i"] = len(self.nodes)
        self.nodes.append(n)
        return n

    def link(self, src, dst):
        self.tree.links.new(src, dst, verify_limits=False)
        self.edges.append((src.node["gvae_i"], dst.node["gvae_i"]))

    def _feed(self, sock, value):
        if value is None:
            return
        if isinstance(value, (int, float)):
            sock.default_value = (value,) * 3 if sock.type == "VECTOR" else value
        else:
            self.link(value, sock)

    def _operands(self, n, name: str, kind: str, values):
        for i, value in enumerate(values):
            if value is not None:
                self._feed(inp(n, name, kind, i), value)

    def math(self, op: str, a, b=None, c=None):
        n = self.node("ShaderNodeMath", operation=op)
        self._operands(n, "Value", "VALUE", (a, b, c))
        return outp(n, "Value", "VALUE")

    def vmath(self, op: str, a, b=None, c=None, *, scale=None):
        """Vector Math; a float given for a vector input becomes (v, v, v). The float result of
        DOT_PRODUCT / LENGTH is returned for those operations, else the vector."""
        n = self.node("ShaderNodeVectorMath", operation=op)
        self._operands(n, "Vector", "VECTOR", (a, b, c))
        if scale is not None:
            self._feed(inp(n, "Scale", "VALUE"), scale)
        return outp(n, "Value", "VALUE") if op in ("DOT_PRODUCT", "LENGTH", "DISTANCE") else outp(n, "Vector", "VECTOR")

    def combine(self, xyz):
        n = self.node("ShaderNodeCombineXYZ")
        for axis, value in zip("XYZ", xyz):
            self._feed(inp(n, axis, "VALUE"), value)
        return outp(n, "Vector", "VECTOR")

    def separate(self, vec):
        n = self.node("ShaderNodeSeparateXYZ")
        self.link(vec, inp(n, "Vector", "VECTOR"))
        return [outp(n, axis, "VALUE") for axis in "XYZ"]

    def boolean(self, op: str, a, b=None):
        n = self.node("FunctionNodeBooleanMath", operation=op)
        self._operands(n, "Boolean", "BOOLEAN", (a, b))
        return outp(n, "Boolean", "BOOLEAN")

    def switch(self, kind: str, condition, false, true):
        """Switch of `kind` ("FLOAT", "VECTOR", "GEOMETRY"); a branch is a socket or a number."""
        n = self.node("GeometryNodeSwitch", input_type=kind)
        self.link(condition, inp(n, "Switch", "BOOLEAN"))
        self._feed(inp(n, "False", SOCKET_KIND[kind]), false)
        self._feed(inp(n, "True", SOCKET_KIND[kind]), true)
        return outp(n, "Output", SOCKET_KIND[kind])

    def product(self, values):
        out = values[0]
        for v in values[1:]:
            out = self.math("MULTIPLY", out, v)
        return out

    def total(self, values):
        out = values[0]
        for v in values[1:]:
            out = self.math("ADD", out, v)
        return out

    def arrange(self):
        """Columns by the longest chain of links from a node without inputs (readable in the editor)."""
        depth = [0] * len(self.nodes)
        changed = True
        while changed:
            changed = False
            for a, c in self.edges:
                if depth[a] + 1 > depth[c]:
                    depth[c] = depth[a] + 1
                    changed = True
        rows: dict[int, int] = {}
        for n, d in zip(self.nodes, depth):
            n.location = (220.0 * d, -160.0 * rows.get(d, 0))
            rows[d] = rows.get(d, 0) + 1
            del n["gvae_i"]


def _named(b: _Builder, name: str, data_type: str = "FLOAT"):
    """A named attribute (0 where the geometry has none)."""
    n = b.node("GeometryNodeInputNamedAttribute", data_type=data_type)
    inp(n, "Name", "STRING").default_value = name
    return outp(n, "Attribute", SOCKET_KIND[data_type])


def _remove_attributes(b: _Builder, geo, pattern: str):
    """Remove Named Attribute with a wildcard pattern (a node property up to Blender 4.5, a menu
    socket from 5.0)."""
    rm = b.node("GeometryNodeRemoveAttribute")
    mode = sockets(rm, "Pattern Mode", "MENU")
    if mode:
        mode[0].default_value = "Wildcard"
    else:
        rm.pattern_mode = "WILDCARD"
    inp(rm, "Name", "STRING").default_value = pattern
    b.link(geo, inp(rm, "Geometry", "GEOMETRY"))
    return outp(rm, "Geometry", "GEOMETRY")


def _clamp(b: _Builder, value, bounds: tuple[float, float]):
    n = b.node("ShaderNodeClamp")
    inp(n, "Min", "VALUE").default_value, inp(n, "Max", "VALUE").default_value = bounds
    b.link(value, inp(n, "Value", "VALUE"))
    return outp(n, "Result", "VALUE")


def _compare(b: _Builder, op: str, a, c):
    """Float comparison a OP c (a boolean field)."""
    n = b.node("FunctionNodeCompare", data_type="FLOAT", operation=op)
    b.link(a, inp(n, "A", "VALUE"))
    b.link(c, inp(n, "B", "VALUE"))
    return outp(n, "Result", "BOOLEAN")


def _set_material(b: _Builder, geo, material):
    n = b.node("GeometryNodeSetMaterial")
    b.link(geo, inp(n, "Geometry", "GEOMETRY"))
    b.link(material, inp(n, "Material", "MATERIAL"))
    return outp(n, "Geometry", "GEOMETRY")


def _store(b: _Builder, geo, name: str, value, data_type: str):
    st = b.node("GeometryNodeStoreNamedAttribute", data_type=data_type, domain="POINT")
    inp(st, "Name", "STRING").default_value = name
    b.link(geo, inp(st, "Geometry", "GEOMETRY"))
    b.link(value, inp(st, "Value", SOCKET_KIND[data_type]))
    return outp(st, "Geometry", "GEOMETRY")


def sh_basis_terms(b: _Builder, direction, degree: int) -> list:
    """Node outputs of the real SH basis functions 1..(degree+1)²-1 of a unit direction field
    (gvae_core.rendering.sh.sh_basis without the constant band)."""
    dx, dy, dz = b.separate(direction)
    m = b.math
    terms = []
    if degree >= 1:
        terms += [m("MULTIPLY", dy, -SH_C1), m("MULTIPLY", dz, SH_C1), m("MULTIPLY", dx, -SH_C1)]
    if degree >= 2:
        xx, yy, zz = m("MULTIPLY", dx, dx), m("MULTIPLY", dy, dy), m("MULTIPLY", dz, dz)
        xy, yz, xz = m("MULTIPLY", dx, dy), m("MULTIPLY", dy, dz), m("MULTIPLY", dx, dz)
        xx_yy = m("ADD", xx, yy)
        xx_m_yy = m("SUBTRACT", xx, yy)
        terms += [m("MULTIPLY", xy, SH_C2[0]), m("MULTIPLY", yz, SH_C2[1]),
                  m("MULTIPLY", m("SUBTRACT", m("MULTIPLY", zz, 2.0), xx_yy), SH_C2[2]),
                  m("MULTIPLY", xz, SH_C2[3]), m("MULTIPLY", xx_m_yy, SH_C2[4])]
    if degree >= 3:
        zz4_m = m("SUBTRACT", m("MULTIPLY", zz, 4.0), xx_yy)  # 4zz - xx - yy
        terms += [
            m("MULTIPLY", m("MULTIPLY", dy, m("SUBTRACT", m("MULTIPLY", xx, 3.0), yy)), SH_C3[0]),
            m("MULTIPLY", m("MULTIPLY", xy, dz), SH_C3[1]),
            m("MULTIPLY", m("MULTIPLY", dy, zz4_m), SH_C3[2]),
            m("MULTIPLY", m("MULTIPLY", dz, m("SUBTRACT", m("MULTIPLY", zz, 2.0), m("MULTIPLY", xx_yy, 3.0))),
              SH_C3[3]),
            m("MULTIPLY", m("MULTIPLY", dx, zz4_m), SH_C3[4]),
            m("MULTIPLY", m("MULTIPLY", dz, xx_m_yy), SH_C3[5]),
            m("MULTIPLY", m("MULTIPLY", dx, m("SUBTRACT", xx, m("MULTIPLY", yy, 3.0))), SH_C3[6]),
        ]
    return terms


def _srgb_to_linear(b: _Builder, c):
    """The sRGB EOTF of one channel (>= 0), extended above 1 by its power law."""
    thr, slope, off, scale, gamma = SRGB_EOTF
    low = b.math("DIVIDE", c, slope)
    high = b.math("POWER", b.math("DIVIDE", b.math("ADD", c, off), scale), gamma)
    is_low = b.math("LESS_THAN", c, thr)  # 1 where c < thr
    return b.math("ADD", b.math("MULTIPLY", low, is_low), b.math("MULTIPLY", high, b.math("SUBTRACT", 1.0, is_low)))


def _octaves_seen(b: _Builder, depth, focal):
    """A refined cloud's octaves above each Gaussian's training rate at which the scene camera
    draws it (`gvae_core.octaves.octaves_seen`): t = clamp(log2((f / z) / nu), 0, limit), 0 below
    the deadband, with nu = sqrt(0.2) / filter_3D where the cloud has that filter, else sqrt(0.3) /
    gvae_dilation_3D. 0 where any of them is missing (Blender's logarithm of 0 is 0; the limit of a
    cloud without changes is 0)."""
    m = b.math
    f3, dil = _named(b, FILTER_KEY), _named(b, DILATION_KEY)
    has_f3 = m("GREATER_THAN", f3, 0.0)
    inv_nu = m("ADD", m("MULTIPLY", has_f3, m("DIVIDE", f3, math.sqrt(FILTER_3D_VARIANCE))),
               m("MULTIPLY", m("SUBTRACT", 1.0, has_f3), m("DIVIDE", dil, math.sqrt(CLASSIC_DILATION))))
    t = m("LOGARITHM", m("DIVIDE", m("MULTIPLY", focal, inv_nu), depth), 2.0)
    t = m("MINIMUM", m("MAXIMUM", t, 0.0), _named(b, OCTAVE_LIMIT_KEY))
    return m("MULTIPLY", t, m("GREATER_THAN", t, OCTAVE_DEADBAND))


def _plus(b: _Builder, value, change: str, octaves):
    """`value` (a node output) plus `octaves` times its change per octave (attribute `change`, 0 if absent)."""
    return b.math("MULTIPLY_ADD", _named(b, change), octaves, value)


class _Raw:
    """Node outputs of each Gaussian's raw parameters as the PLY stores them (log-scales, w,x,y,z
    quaternion, opacity logit, DC colour, SH rest coefficient j's RGB), read from a splat mesh's
    attributes or a Blender 5.3+ Gaussian-splat point cloud's."""

    def __init__(self, log_scales, quat, logit, dc, rest):
        self.log_scales, self.quat, self.logit, self.dc, self.rest = log_scales, quat, logit, dc, rest


def _mesh_raw(b: _Builder, degree: int) -> _Raw:
    """The PLY's columns of a splat mesh (`f_rest` channel-major: coefficient j, channel c is c K + j)."""
    k = SH_REST_COUNTS[degree]
    return _Raw([_named(b, f"scale_{i}") for i in range(3)], [_named(b, f"rot_{i}") for i in range(4)],
                _named(b, "opacity"), [_named(b, f"f_dc_{i}") for i in range(3)],
                [[_named(b, f"f_rest_{c * k + j}") for c in range(3)] for j in range(k)])


def _camera(b: _Builder):
    """(location, forward direction) of the scene's active camera in the object's own frame (the
    frame of the Gaussians' data)."""
    cam = b.node("GeometryNodeObjectInfo", transform_space="RELATIVE")
    b.link(outp(b.node("GeometryNodeInputActiveCamera"), "Active Camera", "OBJECT"), inp(cam, "Object", "OBJECT"))
    forward = b.node("FunctionNodeRotateVector")
    inp(forward, "Vector", "VECTOR").default_value = (0.0, 0.0, -1.0)
    b.link(outp(cam, "Rotation", "ROTATION"), inp(forward, "Rotation", "ROTATION"))
    return outp(cam, "Location", "VECTOR"), outp(forward, "Vector", "VECTOR")


class _Drawn:
    """What the reference renderer draws of each Gaussian for the scene camera (`_drawn`)."""

    def __init__(self, **kw):
        self.__dict__.update(kw)


def _drawn(b: _Builder, gin: dict, raw: _Raw, *, factor=None, filters=None, refine=None) -> _Drawn:
    """Each Gaussian as the reference renderer draws it from the scene camera (module docstring):
    a refined cloud's changes per octave applied (`octaves`: t; `refine`, a boolean input, off: t = 0),
    the centre as drawn, the view direction camera -> centre (`view_dir`; `u` in the Gaussian's own
    frame), the rotation (a rotation socket), the
    standard deviations with the anti-aliasing filters added (`std`, three values; `filters`, a boolean
    input, off: none), the opacity with their compensations, and the refined DC colour and SH
    coefficients (`dc`: three values, `rest[j]`: three values). `factor`: multiplies the std-devs."""
    m = b.math
    octaves, centre, view_dir, screen_var = _seen_from_camera(b, gin, refine)
    # Rotation from the w,x,y,z quaternion (normalised by the node).
    q = b.node("FunctionNodeQuaternionToRotation")
    for comp, value, change in zip("WXYZ", raw.quat, field_keys("quats", 4)):
        b.link(_plus(b, value, change, octaves), inp(q, comp, "VALUE"))
    rotation = outp(q, "Rotation", "ROTATION")
    u, std_tot, ratio_3d, comp_2d = _filtered(b, gin, raw, octaves, view_dir, rotation, screen_var, factor, filters)
    logit = _clamp(b, _plus(b, raw.logit, field_keys("opacities", 1)[0], octaves), OPACITY_LOGIT_RANGE)
    sigmoid = m("DIVIDE", 1.0, m("ADD", m("EXPONENT", m("MULTIPLY", logit, -1.0)), 1.0))
    opacity = b.product([sigmoid, b.product(ratio_3d), comp_2d])
    # A refined cloud's changes per octave of the DC colour and of each SH coefficient (`sh_rest`
    # (K, 3) flattened: column 3 j + c).
    dc = [_plus(b, value, change, octaves) for value, change in zip(raw.dc, field_keys("sh_dc", 3))]
    rest_changes = field_keys("sh_rest", 3 * len(raw.rest))
    rest = [[_plus(b, value, rest_changes[3 * j + c], octaves) for c, value in enumerate(coeff)]
            for j, coeff in enumerate(raw.rest)]
    return _Drawn(octaves=octaves, centre=centre, view_dir=view_dir, u=u, rotation=rotation, std=std_tot,
                  opacity=opacity, dc=dc, rest=rest)


def _seen_from_camera(b: _Builder, gin: dict, refine):
    """(octaves t, centre as drawn, view direction camera -> centre, screen-filter variance in world
    units). A refined cloud is drawn at the octaves above its training rate that the camera sees
    its stored (unchanged) centre at; every other quantity comes from the centre as drawn."""
    m = b.math
    cam_at, forward = _camera(b)
    base = outp(b.node("GeometryNodeInputPosition"), "Position", "VECTOR")
    octaves = _octaves_seen(b, m("ABSOLUTE", b.vmath("DOT_PRODUCT", b.vmath("SUBTRACT", base, cam_at), forward)),
                            gin["Focal Length (px)"])
    if refine is not None:
        octaves = b.switch("FLOAT", refine, 0.0, octaves)
    centre = b.vmath("MULTIPLY_ADD", b.combine([_named(b, key) for key in field_keys("means", 3)]), octaves, base)
    rel = b.vmath("SUBTRACT", centre, cam_at)
    view_dir = b.vmath("NORMALIZE", rel)  # camera -> centre
    depth = m("ABSOLUTE", b.vmath("DOT_PRODUCT", rel, forward))
    # Screen-space filter as a world-space isotropic variance at the Gaussian's depth:
    # variance (px²) x (depth / focal length in px)²; 0 while the focal length is unknown (0).
    pixel = m("DIVIDE", depth, gin["Focal Length (px)"])
    screen_var = m("MULTIPLY", gin["Screen Filter"], m("MULTIPLY", pixel, pixel))
    return octaves, centre, view_dir, screen_var


def _filtered(b: _Builder, gin: dict, raw: _Raw, octaves, view_dir, rotation, screen_var, factor, filters):
    """(u, std-devs, 3D-filter opacity ratios, screen-filter compensation) of each Gaussian with
    the anti-aliasing filters. Variances: s² (std-devs exp(clamp(log-scale)) x factor); with the
    3D filter f: s² + f²; with the screen filter v: + v. Opacity compensations, each exactly 1
    when its filter is 0: 3D filter prod s / sqrt(s² + f²) (the reference's rule); screen filter
    (only with Compensate, the Mip 2D filter) sqrt(det Σ2D / det(Σ2D + v I)), with the 2D
    covariance of the projection along the view direction u (in the Gaussian's frame):
    det Σ2D = det Σ · uᵀ Σ⁻¹ u."""
    m = b.math
    # A refined cloud's anti-aliasing size (either one) times e^min(t x its change per octave, 0).
    shrink = m("EXPONENT", m("MINIMUM", m("MULTIPLY", octaves, _named(b, field_keys(SIZE, 1)[0])), 0.0))
    if filters is not None:  # filters off: no size, no screen variance
        shrink = b.switch("FLOAT", filters, 0.0, shrink)
        screen_var = b.switch("FLOAT", filters, 0.0, screen_var)
    f = m("MULTIPLY", _named(b, FILTER_KEY), shrink)
    ff = m("MULTIPLY", f, f)
    # "matched" (a cloud with the classic dilation held in world units, DILATION_KEY = d): the
    # added variance is max(d², screen variance), opacity unchanged; not with the Mip filters.
    d = b.product([_named(b, DILATION_KEY), shrink, m("SUBTRACT", 1.0, gin["Compensate Screen Filter"])])
    screen_var = m("MAXIMUM", m("MULTIPLY", d, d), screen_var)
    u = b.node("FunctionNodeRotateVector")
    b.link(view_dir, inp(u, "Vector", "VECTOR"))
    inv_q = b.node("FunctionNodeInvertRotation")
    b.link(rotation, inp(inv_q, "Rotation", "ROTATION"))
    b.link(outp(inv_q, "Rotation", "ROTATION"), inp(u, "Rotation", "ROTATION"))
    u = outp(u, "Vector", "VECTOR")
    uu = [m("MULTIPLY", c, c) for c in b.separate(u)]
    std_tot, ratio_3d, ratio_det, quad_eff, quad_tot = [], [], [], [], []
    for i, change in enumerate(field_keys("scales", 3)):
        s = m("EXPONENT", _clamp(b, _plus(b, raw.log_scales[i], change, octaves), LOG_SCALE_RANGE))
        if factor is not None:
            s = m("MULTIPLY", s, factor)
        var_eff = m("MULTIPLY_ADD", s, s, ff)
        var_tot = m("ADD", var_eff, screen_var)
        std_tot.append(m("SQRT", var_tot))
        ratio_3d.append(m("DIVIDE", s, m("SQRT", var_eff)))  # in (0, 1]
        ratio_det.append(m("DIVIDE", var_eff, var_tot))  # in (0, 1]
        quad_eff.append(m("DIVIDE", uu[i], var_eff))
        quad_tot.append(m("DIVIDE", uu[i], var_tot))
    det_ratio = m("MULTIPLY", b.product(ratio_det), m("DIVIDE", b.total(quad_eff), b.total(quad_tot)))
    comp_2d = b.switch("FLOAT", gin["Compensate Screen Filter"], 1.0, m("SQRT", det_ratio))
    return u, std_tot, ratio_3d, comp_2d


def _new_interface(ng, inputs) -> None:
    """Give `ng` a geometry input and output and the `inputs` (INPUTS-style rows)."""
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    for name, kind, default, lo, hi, desc in inputs:
        s = ng.interface.new_socket(name, description=desc, in_out="INPUT", socket_type=kind)
        if default is not None:
            s.default_value = default
        if lo is not None:
            s.min_value, s.max_value = lo, hi
        if kind == "NodeSocketFloat" and hi == 1.0:
            s.subtype = "FACTOR"


def _group_io(b: _Builder, inputs) -> tuple[dict, object]:
    """The group's input sockets by name ("Geometry" too) and its output node."""
    group_in = b.node("NodeGroupInput")
    gin = {name: outp(group_in, name, SOCKET_KIND[kind]) for name, kind, *_ in inputs}
    gin["Geometry"] = outp(group_in, "Geometry", "GEOMETRY")
    return gin, b.node("NodeGroupOutput")


def _build_group(ng, degree: int) -> None:
    ng.nodes.clear()
    ng.interface.clear()
    _new_interface(ng, INPUTS + HIDDEN_INPUTS)
    b = _Builder(ng)
    gin, gout = _group_io(b, INPUTS + HIDDEN_INPUTS)
    g = _drawn(b, gin, _mesh_raw(b, degree), factor=gin["Scale Factor"])
    scale = _instance_scale(b, g)
    select, points_only, is_viewport = _selection(b, gin, g.opacity)
    linear = _colour(b, gin, g, degree)
    geo, got = _captured(b, gin, g, scale, select, linear)
    instances = _ellipsoids(b, gin, geo, got, is_viewport)
    points = _points_only(b, gin, geo, got)
    shown = b.switch("GEOMETRY", points_only, instances, points)
    b.link(shown, inp(gout, "Geometry", "GEOMETRY"))
    b.arrange()
    ng["gvae_nodes_version"] = NODES_VERSION
    ng["gvae_sh_degree"] = degree


def _instance_scale(b: _Builder, g):
    """The instance scale: the std-devs times the radius of the visible part, sqrt(2 ln(255 o))
    std-devs (the icosphere encloses that ellipsoid)."""
    m = b.math
    radius = m("SQRT", m("MAXIMUM", m("MULTIPLY", m("LOGARITHM", m("MULTIPLY", g.opacity, 1.0 / ALPHA_MIN), math.e),
                                        2.0), 0.0))
    return b.vmath("SCALE", b.combine(g.std), scale=radius)


def _selection(b: _Builder, gin, opacity):
    """(shown, points only, is viewport): a fixed random subset of the Display Fraction, visible
    (o >= 1/255) and o >= Min Opacity; Display Fraction and Points Only act where "display"
    applies: always, or in the viewport only."""
    rand = b.node("FunctionNodeRandomValue", data_type="FLOAT")
    inp(rand, "Seed", "INT").default_value = 0
    is_viewport = outp(b.node("GeometryNodeIsViewport"), "Is Viewport", "BOOLEAN")
    display = b.boolean("OR", is_viewport, b.boolean("NOT", gin["Viewport Only"]))  # viewport, or not viewport-only
    fraction = b.switch("FLOAT", display, 1.0, gin["Display Fraction"])
    points_only = b.boolean("AND", gin["Points Only"], display)
    select = b.boolean("AND", _compare(b, "GREATER_EQUAL", opacity, b.math("MAXIMUM", gin["Min Opacity"], ALPHA_MIN)),
                       _compare(b, "LESS_THAN", outp(rand, "Value", "VALUE"), fraction))
    return select, points_only, is_viewport


def _colour(b: _Builder, gin, g, degree: int):
    """The linear colour: SH_C0 * f_dc + 0.5 (+ the SH bands seen from the active camera, with
    View-Dependent Colour), clamped at 0, from sRGB."""
    colour = b.vmath("MULTIPLY_ADD", b.combine(g.dc), SH_C0, 0.5)
    if g.rest:
        rest = None
        for coeff, basis in zip(g.rest, sh_basis_terms(b, g.view_dir, degree)):
            coeff = b.combine(coeff)
            rest = (b.vmath("SCALE", coeff, scale=basis) if rest is None
                    else b.vmath("MULTIPLY_ADD", coeff, basis, rest))
        colour = b.vmath("ADD", colour, b.switch("VECTOR", gin["View-Dependent Colour"], 0.0, rest))
    colour = b.vmath("MAXIMUM", colour, 0.0)
    return b.combine([_srgb_to_linear(b, ch) for ch in b.separate(colour)])


def _captured(b: _Builder, gin, g, scale, select, linear):
    """(the points, what each instance needs by name): everything evaluated on the full points,
    then every named attribute dropped (SH, scales, extras: none is copied per instance), only
    what the material reads stored, the points moved to the centres as drawn (a refined cloud's)."""
    # ("Shown", not "Selection": Capture Attribute has a Selection input of its own from 5.2.)
    cap = b.node("GeometryNodeCaptureAttribute", domain="POINT")
    captured = (("Rotation", "ROTATION", g.rotation), ("Scale", "VECTOR", scale), ("Shown", "BOOLEAN", select),
                ("Colour", "VECTOR", linear), ("Opacity", "FLOAT", g.opacity), ("Std", "VECTOR", b.combine(g.std)),
                ("Facing", "VECTOR", b.vmath("DIVIDE", b.vmath("SCALE", g.u, scale=-1.0), b.combine(g.std))),
                ("Centre", "VECTOR", g.centre))
    for name, kind, _ in captured:
        cap.capture_items.new(kind, name)
    b.link(gin["Geometry"], inp(cap, "Geometry", "GEOMETRY"))
    for name, kind, value in captured:
        b.link(value, inp(cap, name, SOCKET_KIND[kind]))
    got = {name: outp(cap, name, SOCKET_KIND[kind]) for name, kind, _ in captured}
    geo = _remove_attributes(b, outp(cap, "Geometry", "GEOMETRY"), "*")
    geo = _store(b, geo, COLOR_ATTR, got["Colour"], "FLOAT_VECTOR")
    geo = _store(b, geo, ALPHA_ATTR, got["Opacity"], "FLOAT")
    moved = b.node("GeometryNodeSetPosition")
    b.link(geo, inp(moved, "Geometry", "GEOMETRY"))
    b.link(got["Centre"], inp(moved, "Position", "VECTOR"))
    return outp(moved, "Geometry", "GEOMETRY"), got


def _ellipsoids(b: _Builder, gin, geo, got: dict, is_viewport):
    """The shown points as ellipsoids: an icosphere enclosing the unit sphere, instanced per point
    with the Gaussian's rotation and scale (instance space = its whitened frame). Renders
    (Camera-Facing): a disc instead, turned within that frame to face the scene camera, so that a
    ray meets each Gaussian once, where it crosses the plane through the centre; the material's
    closest approach does not depend on the primitive's shape or turn."""
    m = b.math
    radius_ico = m("MULTIPLY_ADD", m("POWER", _ICO_ENCLOSE[1], m("SUBTRACT", 1.0, gin["Detail"])),
                   _ICO_ENCLOSE[0], 1.0)
    ico = b.node("GeometryNodeMeshIcoSphere")
    b.link(radius_ico, inp(ico, "Radius", "VALUE"))
    b.link(gin["Detail"], inp(ico, "Subdivisions", "INT"))
    disc = b.node("GeometryNodeMeshCircle", fill_type="NGON")
    inp(disc, "Vertices", "INT").default_value = DISC_SIDES
    inp(disc, "Radius", "VALUE").default_value = DISC_RADIUS / math.cos(math.pi / DISC_SIDES)
    facing = b.boolean("NIMPLY", gin["Camera-Facing in Renders"], is_viewport)  # camera-facing and not viewport
    shape = b.switch("GEOMETRY", facing, outp(ico, "Mesh", "GEOMETRY"), outp(disc, "Mesh", "GEOMETRY"))
    inst = b.node("GeometryNodeInstanceOnPoints")
    b.link(geo, inp(inst, "Points", "GEOMETRY"))
    b.link(got["Shown"], inp(inst, "Selection", "BOOLEAN"))
    b.link(_set_material(b, shape, gin["Material"]), inp(inst, "Instance", "GEOMETRY"))
    b.link(got["Rotation"], inp(inst, "Rotation", "ROTATION"))
    b.link(got["Scale"], inp(inst, "Scale", "VECTOR"))
    # The camera in the whitened frame is -diag(1 / std) R^T (centre - camera): the disc's normal.
    # Instance transform T R diag(std) becomes T R diag(std) R_turn (Rotate Instances would turn
    # the instance between R and diag(std)).
    turn = b.node("FunctionNodeAlignRotationToVector", axis="Z")
    b.link(got["Facing"], inp(turn, "Vector", "VECTOR"))
    turn_m = b.node("FunctionNodeCombineTransform")
    b.link(outp(turn, "Rotation", "ROTATION"), inp(turn_m, "Rotation", "ROTATION"))
    turned = b.node("FunctionNodeMatrixMultiply")
    b.link(outp(b.node("GeometryNodeInstanceTransform"), "Transform", "MATRIX"), inp(turned, "Matrix", "MATRIX", 0))
    b.link(outp(turn_m, "Transform", "MATRIX"), inp(turned, "Matrix", "MATRIX", 1))
    rotate = b.node("GeometryNodeSetInstanceTransform")
    b.link(outp(inst, "Instances", "GEOMETRY"), inp(rotate, "Instances", "GEOMETRY"))
    b.link(facing, inp(rotate, "Selection", "BOOLEAN"))
    b.link(outp(turned, "Matrix", "MATRIX"), inp(rotate, "Transform", "MATRIX"))
    return outp(rotate, "Instances", "GEOMETRY")


def _points_only(b: _Builder, gin, geo, got: dict):
    """The shown points as a point cloud: radius sqrt(2) x the mean std-dev (a disc of that radius
    holds the Gaussian's integrated opacity), constant alpha."""
    pts = b.node("GeometryNodeMeshToPoints")
    b.link(geo, inp(pts, "Mesh", "GEOMETRY"))
    b.link(got["Shown"], inp(pts, "Selection", "BOOLEAN"))
    b.link(b.math("MULTIPLY", b.vmath("LENGTH", got["Std"]), math.sqrt(2.0 / 3.0)), inp(pts, "Radius", "VALUE"))
    return _set_material(b, outp(pts, "Points", "GEOMETRY"), gin["Material"])


# ------------------------------------------------------------------ Blender's own Gaussian splats (5.3+)

def _native_raw(b: _Builder, degree: int) -> _Raw:
    """The raw parameters of a Gaussian-splat point cloud's attributes (`convert`: `scale` linear,
    `rotation` a unit quaternion, `radiance:base` the DC colour and the opacity, `radiance:sh_j`):
    log-scales (a zero scale is the flat axis LOG_SCALE_RANGE[0]: Blender's logarithm of 0 is 0) and
    the opacity logit (the opacity held inside (0, 1), so that 0 and 1 give finite logits)."""
    m = b.math
    floor = math.exp(LOG_SCALE_RANGE[0])
    scales = b.separate(_named(b, "scale", "FLOAT_VECTOR"))
    log_scales = [m("LOGARITHM", m("MAXIMUM", c, floor), math.e) for c in scales]
    quat = b.node("FunctionNodeRotationToQuaternion")
    b.link(_named(b, "rotation", "QUATERNION"), inp(quat, "Rotation", "ROTATION"))
    base = b.node("FunctionNodeSeparateColor")
    b.link(_named(b, "radiance:base", "FLOAT_COLOR"), inp(base, "Color", "RGBA"))
    a = _clamp(b, outp(base, "Alpha", "VALUE"), (1e-7, 1.0 - 1e-7))
    logit = m("SUBTRACT", m("LOGARITHM", a, math.e), m("LOGARITHM", m("SUBTRACT", 1.0, a), math.e))
    return _Raw(log_scales, [outp(quat, c, "VALUE") for c in "WXYZ"], logit,
                [outp(base, c, "VALUE") for c in ("Red", "Green", "Blue")],
                [b.separate(_named(b, f"radiance:sh_{j}", "FLOAT_VECTOR")) for j in range(SH_REST_COUNTS[degree])])


def _build_native_group(ng, degree: int) -> None:
    """The modifier of a Gaussian-splat point cloud: its own attributes rewritten as `_drawn` gives them
    for the scene camera (Blender then draws them): `position`, `rotation`, `scale` (the filters
    added), `radiance:base` (the refined colour, the compensated opacity) and `radiance:sh_j`."""
    ng.nodes.clear()
    ng.interface.clear()
    inputs = NATIVE_INPUTS + HIDDEN_INPUTS
    _new_interface(ng, inputs)
    b = _Builder(ng)
    gin, gout = _group_io(b, inputs)
    g = _drawn(b, gin, _native_raw(b, degree), filters=gin["Anti-Aliasing"], refine=gin["Refinement"])
    moved = b.node("GeometryNodeSetPosition")
    b.link(gin["Geometry"], inp(moved, "Geometry", "GEOMETRY"))
    b.link(g.centre, inp(moved, "Position", "VECTOR"))
    geo = _store(b, outp(moved, "Geometry", "GEOMETRY"), "rotation", g.rotation, "QUATERNION")
    geo = _store(b, geo, "scale", b.combine(g.std), "FLOAT_VECTOR")
    base = b.node("FunctionNodeCombineColor")
    for channel, value in zip(("Red", "Green", "Blue", "Alpha"), (*g.dc, g.opacity)):
        b.link(value, inp(base, channel, "VALUE"))
    geo = _store(b, geo, "radiance:base", outp(base, "Color", "RGBA"), "FLOAT_COLOR")
    for j, coeff in enumerate(g.rest):
        geo = _store(b, geo, f"radiance:sh_{j}", b.combine(coeff), "FLOAT_VECTOR")
    b.link(geo, inp(gout, "Geometry", "GEOMETRY"))
    b.arrange()
    ng["gvae_nodes_version"] = NODES_VERSION
    ng["gvae_sh_degree"] = degree
    ng["gvae_native"] = True


def group_name(degree: int, native: bool = False) -> str:
    return f"{NATIVE_GROUP_NAME if native else GROUP_NAME} (SH {degree})"


def _builder(native: bool):
    return _build_native_group if native else _build_group


def ensure_node_group(degree: int = 0, native: bool = False):
    """The shared node group of clouds of SH degree `degree` (`native`: of Blender's own Gaussian-splat
    point clouds), built (or rebuilt when outdated)."""
    if degree not in SH_REST_COUNTS:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    name = group_name(degree, native)
    ng = bpy.data.node_groups.get(name)
    if ng is None or ng.bl_idname != "GeometryNodeTree":
        ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    if ng.get("gvae_nodes_version") != NODES_VERSION or ng.get("gvae_sh_degree") != degree:
        _rebuild_group(ng, degree, _builder(native))
    return ng


def _input_defaults(ng) -> dict:
    """Name -> default value of the group's inputs but the geometry (None: no default, a material)."""
    return {item.name: getattr(item, "default_value", None) for item in ng.interface.items_tree
            if getattr(item, "in_out", None) == "INPUT" and item.socket_type != "NodeSocketGeometry"}


def _rebuild_group(ng, degree: int, build=_build_group) -> None:
    """Build `ng` anew, keeping the input values of every modifier that uses it (by name: a rebuilt
    interface has new socket identifiers, and the modifiers' values would otherwise become zeros:
    Scale Factor 0, a Mip-Splatting cloud's Compensate Screen Filter off); inputs new to the group
    get their defaults."""
    old = set(_input_defaults(ng))
    kept = []
    for obj in bpy.data.objects:
        for mod in obj.modifiers:
            if mod.type == "NODES" and mod.node_group == ng:
                values = {}
                for name in old:
                    try:
                        values[name] = get_modifier_input(mod, name)
                    except (LookupError, KeyError, ValueError):
                        pass  # never set: it takes the default
                kept.append((obj, mod, values))
    build(ng, degree)
    defaults = _input_defaults(ng)
    for obj, mod, values in kept:
        for name, default in defaults.items():
            value = values.get(name, default)
            if value is not None:
                set_modifier_input(mod, name, value)
        obj.update_tag()


def upgrade_outdated() -> int:
    """Rebuild the splat node groups and the material of an opened file that an older version of
    the add-on made (its objects then draw as this version does), keeping their modifiers' inputs;
    returns how many groups were rebuilt. Linked (library) data is left alone."""
    count = 0
    for ng in list(bpy.data.node_groups):
        degree = ng.get("gvae_sh_degree")
        if (ng.bl_idname == "GeometryNodeTree" and ng.name.startswith(GROUP_NAMES) and ng.library is None
                and degree in SH_REST_COUNTS and ng.get("gvae_nodes_version") != NODES_VERSION):
            _rebuild_group(ng, int(degree), _builder(bool(ng.get("gvae_native"))))
            count += 1
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is not None and mat.library is None and mat.get("gvae_nodes_version") != NODES_VERSION:
        _build_material(mat)
    return count


def _attr_sum(b: _Builder, name: str, vector: bool = False):
    """Attribute `name` as instancer attribute plus as geometry attribute (one of them is 0)."""
    output = ("Vector", "VECTOR") if vector else ("Fac", "VALUE")  # "Fac" is shown as "Factor" from 5.0
    inst = b.node("ShaderNodeAttribute", attribute_type="INSTANCER", attribute_name=name)
    geom = b.node("ShaderNodeAttribute", attribute_type="GEOMETRY", attribute_name=name)
    return (b.vmath if vector else b.math)("ADD", outp(inst, *output), outp(geom, *output))


def _build_material(mat) -> None:
    if mat.node_tree is None:  # from 5.0 every material has its node tree (use_nodes is deprecated)
        mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    b = _Builder(tree)
    m = b.math
    colour = _attr_sum(b, COLOR_ATTR, vector=True)
    inst_o, pts_o = (outp(b.node("ShaderNodeAttribute", attribute_type=kind, attribute_name=ALPHA_ATTR), "Fac", "VALUE")
                     for kind in ("INSTANCER", "GEOMETRY"))

    # Ellipsoids: the ray p + t v in instance space (the Gaussian's whitened frame, unit = its
    # visible radius): squared distance of the closest approach q = |p|² - (p.v)² / |v|²;
    # alpha = o exp(-radius² q / 2) = o (255 o)^(-q) = o exp(-q ln(255 o)).
    p = outp(b.node("ShaderNodeTexCoord"), "Object", "VECTOR")
    geometry = b.node("ShaderNodeNewGeometry")
    v = b.node("ShaderNodeVectorTransform", vector_type="VECTOR", convert_from="WORLD", convert_to="OBJECT")
    b.link(outp(geometry, "Incoming", "VECTOR"), inp(v, "Vector", "VECTOR"))
    v = outp(v, "Vector", "VECTOR")
    pv = b.vmath("DOT_PRODUCT", p, v)
    q = m("MAXIMUM", m("SUBTRACT", b.vmath("DOT_PRODUCT", p, p),
                       m("DIVIDE", m("MULTIPLY", pv, pv), b.vmath("DOT_PRODUCT", v, v))), 0.0)
    log255o = m("LOGARITHM", m("MULTIPLY", inst_o, 1.0 / ALPHA_MIN), math.e)  # 0 for points (o = 0)
    falloff = m("EXPONENT", m("MULTIPLY", q, m("MULTIPLY", log255o, -1.0)))
    alpha = m("MINIMUM", m("ADD", m("MULTIPLY", inst_o, falloff), pts_o), ALPHA_MAX)
    visible = m("GREATER_THAN", alpha, ALPHA_MIN * (1.0 - 1e-6))  # 1/255 itself is drawn
    # Only front faces draw: a ray through a closed mesh would blend the Gaussian twice.
    front = m("SUBTRACT", 1.0, outp(geometry, "Backfacing", "VALUE"))
    alpha = b.product([alpha, visible, front])

    emit = b.node("ShaderNodeEmission")
    b.link(colour, inp(emit, "Color", "RGBA"))
    inp(emit, "Strength", "VALUE").default_value = 1.0
    mix = b.node("ShaderNodeMixShader")
    b.link(alpha, inp(mix, "Fac", "VALUE"))
    b.link(outp(b.node("ShaderNodeBsdfTransparent"), "BSDF", "SHADER"), inp(mix, "Shader", "SHADER", 0))
    b.link(outp(emit, "Emission", "SHADER"), inp(mix, "Shader", "SHADER", 1))
    b.link(outp(mix, "Shader", "SHADER"), inp(b.node("ShaderNodeOutputMaterial"), "Surface", "SHADER"))
    b.arrange()
    # EEVEE: dithered (stochastic) transparency is order-independent, so the overlapping splats of
    # one object composite in depth order as samples accumulate; "Blended" would sort per object.
    mat.surface_render_method = "DITHERED"
    mat.use_backface_culling = True
    mat["gvae_nodes_version"] = NODES_VERSION


def ensure_material():
    """The shared splat material, built (or rebuilt when outdated) on demand."""
    mat = bpy.data.materials.get(MATERIAL_NAME)
    if mat is None:
        mat = bpy.data.materials.new(MATERIAL_NAME)
    if mat.get("gvae_nodes_version") != NODES_VERSION:
        _build_material(mat)
    return mat


def _socket_id(ng, name: str) -> str:
    found = [item.identifier for item in ng.interface.items_tree
             if getattr(item, "in_out", None) == "INPUT" and item.name == name]
    if not found:
        raise LookupError(f"Blender {bpy.app.version_string}: node group {ng.name!r} has no input {name!r}")
    return found[0]


def modifier_input(mod, name: str) -> tuple:
    """(owner, property path) of the value of the modifier's group input `name`, for
    `layout.prop(owner, path)`: an ID property of the modifier up to Blender 5.1, the `value` of
    its `properties.inputs` item from 5.2 (a Nodes modifier holds no ID properties there)."""
    ident = _socket_id(mod.node_group, name)
    props = getattr(mod, "properties", None)
    if props is not None:
        return getattr(props.inputs, ident), "value"
    return mod, f'["{ident}"]'


def get_modifier_input(mod, name: str):
    owner, path = modifier_input(mod, name)
    return owner.path_resolve(path)


def set_modifier_input(mod, name: str, value) -> None:
    owner, path = modifier_input(mod, name)
    if path == "value":
        owner.value = value
    else:
        owner[path[2:-2]] = value


def _set_modifier(obj, ng, values: dict):
    """`obj`'s splat modifier (made when it has none) on group `ng`, its inputs set from `values` and
    the screen filter of the reference renderer's "auto" mode: Mip-Splatting's 2D filter for a cloud
    with a 3D filter, the classic dilation for one without."""
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is None or mod.type != "NODES":
        mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = ng
    mip = FILTER_KEY in obj.data.attributes
    values = {**values, "Screen Filter": MIP_2D_VARIANCE if mip else CLASSIC_DILATION, "Compensate Screen Filter": mip}
    for name, value in values.items():
        set_modifier_input(mod, name, value)
    obj.update_tag()
    return mod


def add_splat_modifier(obj, *, scale_factor: float = DEFAULT_SCALE_FACTOR, fraction: float = 1.0,
                       points_only: bool = False, min_opacity: float = 0.0, view_dependent: bool = True):
    """Give `obj` the splat Geometry Nodes modifier (and material), or update its inputs."""
    mat = ensure_material()
    mod = _set_modifier(obj, ensure_node_group(int(layout(obj.data)["sh_degree"])), {
        "Scale Factor": float(scale_factor), "View-Dependent Colour": bool(view_dependent),
        "Display Fraction": float(fraction), "Points Only": bool(points_only), "Min Opacity": float(min_opacity),
        "Material": mat})
    if mat.name not in obj.data.materials:
        obj.data.materials.append(mat)
    return mod


def add_native_modifier(obj, *, refinement: bool = True, anti_aliasing: bool = True):
    """Give a Gaussian-splat point cloud object (Blender 5.3+) the modifier that draws it as
    `gvae_core.render` does for the scene camera (`_build_native_group`), or update its inputs."""
    return _set_modifier(obj, ensure_node_group(native_sh_degree(obj.data), native=True),
                         {"Refinement": bool(refinement), "Anti-Aliasing": bool(anti_aliasing)})


def splat_modifier(obj):
    """The splat modifier of `obj`, or None."""
    mod = obj.modifiers.get(MODIFIER_NAME) if obj is not None else None
    return mod if mod is not None and mod.type == "NODES" and mod.node_group is not None else None
