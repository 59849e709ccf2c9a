"""The Geometry Nodes group and the material that draw a splat object.

Geometry Nodes: one low-poly ellipsoid (an icosphere with the unit sphere's volume) instanced per
Gaussian centre, rotated by
the w,x,y,z quaternion `rot_0..3` and scaled by exp(clamped `scale_0..2`) times a user factor.
Instances are not realised. Display inputs on the modifier: the fraction of splats shown, points
only (a point cloud instead of ellipsoids) and the lowest opacity shown.

Material: colour = max(SH_C0 * f_dc + 0.5, 0) and alpha = sigmoid(opacity), read with Attribute
nodes, emitted (splat colours are radiance, not albedo) over a transparent BSDF; it works in EEVEE
and Cycles. Back faces are transparent, so each ellipsoid is blended once. Attributes are looked
up both as instancer attributes (ellipsoids) and as geometry attributes (points only); the
missing lookup reads zero, so their sum is the value.
"""

from __future__ import annotations

import math

import bpy

from gvae_core.conventions import LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_C0

GROUP_NAME = "GaussianVAE Splats"
MATERIAL_NAME = "GaussianVAE Splat"
MODIFIER_NAME = "GaussianVAE Splats"
#: Bumped when the node setup changes; an older group in a blend file is rebuilt in place.
NODES_VERSION = 2
#: Default size of an ellipsoid in standard deviations: sqrt(2) gives a solid ellipse the same
#: integrated opacity as the Gaussian it stands for (pi k^2 = 2 pi for k = sqrt 2).
DEFAULT_SCALE_FACTOR = math.sqrt(2.0)

# Interface: (name, socket type, default, min, max, description)
INPUTS = (
    ("Scale Factor", "NodeSocketFloat", DEFAULT_SCALE_FACTOR, 0.0, 100.0,
     "Ellipsoid semi-axes in standard deviations of the Gaussian"),
    ("Display Fraction", "NodeSocketFloat", 1.0, 0.0, 1.0,
     "Fraction of the splats shown (a fixed random subset, for large scenes)"),
    ("Points Only", "NodeSocketBool", False, None, None,
     "Show one point per Gaussian instead of ellipsoids (fast for large scenes)"),
    ("Min Opacity", "NodeSocketFloat", 0.0, 0.0, 1.0, "Hide splats whose opacity is below this"),
    ("Detail", "NodeSocketInt", 1, 1, 4, "Subdivisions of the icosphere drawn per Gaussian"),
    ("Material", "NodeSocketMaterial", None, None, None, "Material of the splats"),
)


class _Builder:
    """Small helper to add and link nodes with less noise."""

    def __init__(self, tree):
        self.tree = tree
        self.x = 0

    def node(self, kind: str, x: float, y: float, **props):
        n = self.tree.nodes.new(kind)
        n.location = (x, y)
        for key, value in props.items():
            setattr(n, key, value)
        return n

    def link(self, out, inp):
        self.tree.links.new(out, inp)

    def math(self, op: str, a, b=None, x=0, y=0):
        n = self.node("ShaderNodeMath", x, y, operation=op)
        for sock, value in ((n.inputs[0], a), (n.inputs[1], b)):
            if value is None:
                continue
            if isinstance(value, (int, float)):
                sock.default_value = value
            else:
                self.link(value, sock)
        return n.outputs[0]


def _named(b: _Builder, name: str, x: float, y: float):
    n = b.node("GeometryNodeInputNamedAttribute", x, y, data_type="FLOAT")
    n.inputs["Name"].default_value = name
    return n.outputs["Attribute"]


def _build_group(ng) -> None:
    ng.nodes.clear()
    ng.interface.clear()
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    for name, kind, default, lo, hi, desc in INPUTS:
        s = ng.interface.new_socket(name, description=desc, in_out="INPUT", socket_type=kind)
        if default is not None:
            s.default_value = default
        if lo is not None:
            s.min_value, s.max_value = lo, hi
        if kind == "NodeSocketFloat" and hi == 1.0:
            s.subtype = "FACTOR"

    b = _Builder(ng)
    gin = b.node("NodeGroupInput", -1400, 0)
    gout = b.node("NodeGroupOutput", 1000, 0)

    # Rotation from the w,x,y,z quaternion (normalised by the node).
    q = b.node("FunctionNodeQuaternionToRotation", -800, 300)
    for i, comp in enumerate("WXYZ"):
        b.link(_named(b, f"rot_{i}", -1100, 450 - 80 * i), q.inputs[comp])

    # Scale: exp(clamp(log-scale)) * factor.
    comb = b.node("ShaderNodeCombineXYZ", -600, 0)
    for i, comp in enumerate("XYZ"):
        clamp = b.node("ShaderNodeClamp", -900, 50 - 120 * i)
        clamp.inputs["Min"].default_value, clamp.inputs["Max"].default_value = LOG_SCALE_RANGE
        b.link(_named(b, f"scale_{i}", -1100, 50 - 120 * i), clamp.inputs["Value"])
        b.link(b.math("EXPONENT", clamp.outputs[0], x=-750, y=50 - 120 * i), comb.inputs[comp])
    scale = b.node("ShaderNodeVectorMath", -400, 0, operation="SCALE")
    b.link(comb.outputs[0], scale.inputs[0])
    b.link(gin.outputs["Scale Factor"], scale.inputs["Scale"])

    # Selection: a fixed random subset of the given fraction, opacity at least the threshold.
    logit = _named(b, "opacity", -1100, -450)
    clamped = b.node("ShaderNodeClamp", -950, -450)
    clamped.inputs["Min"].default_value, clamped.inputs["Max"].default_value = OPACITY_LOGIT_RANGE
    b.link(logit, clamped.inputs["Value"])
    expo = b.math("EXPONENT", b.math("MULTIPLY", clamped.outputs[0], -1.0, -800, -450), x=-650, y=-450)
    alpha = b.math("DIVIDE", 1.0, b.math("ADD", expo, 1.0, -500, -450), -350, -450)
    keep_op = b.node("FunctionNodeCompare", -200, -450, data_type="FLOAT", operation="GREATER_EQUAL")
    b.link(alpha, keep_op.inputs[0])
    b.link(gin.outputs["Min Opacity"], keep_op.inputs[1])
    rand = b.node("FunctionNodeRandomValue", -500, -650, data_type="FLOAT")
    rand.inputs["Seed"].default_value = 0
    keep_frac = b.node("FunctionNodeCompare", -200, -650, data_type="FLOAT", operation="LESS_THAN")
    b.link(rand.outputs[1], keep_frac.inputs[0])
    b.link(gin.outputs["Display Fraction"], keep_frac.inputs[1])
    select = b.node("FunctionNodeBooleanMath", 0, -500, operation="AND")
    b.link(keep_op.outputs[0], select.inputs[0])
    b.link(keep_frac.outputs[0], select.inputs[1])

    # Evaluate rotation, scale and selection on the full points, then drop the attributes the
    # instances do not need (SH rest, scales, rotations) so they are not copied per instance.
    cap = b.node("GeometryNodeCaptureAttribute", 0, 200, domain="POINT")
    for name, kind in (("Rotation", "ROTATION"), ("Scale", "VECTOR"), ("Selection", "BOOLEAN")):
        cap.capture_items.new(kind, name)
    b.link(gin.outputs["Geometry"], cap.inputs["Geometry"])
    b.link(q.outputs[0], cap.inputs["Rotation"])
    b.link(scale.outputs[0], cap.inputs["Scale"])
    b.link(select.outputs[0], cap.inputs["Selection"])
    geo = cap.outputs["Geometry"]
    for i, pattern in enumerate(("f_rest_*", "scale_*", "rot_*")):
        rm = b.node("GeometryNodeRemoveAttribute", 200 + 150 * i, 300)
        rm.inputs["Pattern Mode"].default_value = "Wildcard"
        rm.inputs["Name"].default_value = pattern
        b.link(geo, rm.inputs["Geometry"])
        geo = rm.outputs["Geometry"]

    # Ellipsoids: an icosphere with the material, instanced per selected point.
    # Radius of the icosphere whose volume is the unit sphere's: an icosahedron (Detail 1) inscribed
    # in the unit sphere holds 0.61 of its volume; the gap shrinks about 4x per subdivision
    # (1 + 0.182 / 4^(d-1) matches the exact 1.182, 1.046, 1.012, 1.003 within 0.1%).
    level = b.math("SUBTRACT", gin.outputs["Detail"], 1.0, 0, -250)
    radius_ico = b.math("MULTIPLY_ADD", b.math("POWER", 0.25, level, 150, -250), 0.182, 300, -250)
    radius_ico.node.inputs[2].default_value = 1.0
    ico = b.node("GeometryNodeMeshIcoSphere", 300, -100)
    b.link(radius_ico, ico.inputs["Radius"])
    b.link(gin.outputs["Detail"], ico.inputs["Subdivisions"])
    ico_mat = b.node("GeometryNodeSetMaterial", 500, -100)
    b.link(ico.outputs["Mesh"], ico_mat.inputs["Geometry"])
    b.link(gin.outputs["Material"], ico_mat.inputs["Material"])
    inst = b.node("GeometryNodeInstanceOnPoints", 700, 100)
    b.link(geo, inst.inputs["Points"])
    b.link(cap.outputs["Selection"], inst.inputs["Selection"])
    b.link(ico_mat.outputs["Geometry"], inst.inputs["Instance"])
    b.link(cap.outputs["Rotation"], inst.inputs["Rotation"])
    b.link(cap.outputs["Scale"], inst.inputs["Scale"])

    # Points only: a point cloud with the mean semi-axis as radius.
    radius = b.node("ShaderNodeVectorMath", 500, -350, operation="LENGTH")
    b.link(cap.outputs["Scale"], radius.inputs[0])
    pts = b.node("GeometryNodeMeshToPoints", 700, -300)
    b.link(geo, pts.inputs["Mesh"])
    b.link(cap.outputs["Selection"], pts.inputs["Selection"])
    b.link(b.math("MULTIPLY", radius.outputs["Value"], 1.0 / math.sqrt(3.0), 600, -450),
           pts.inputs["Radius"])
    pts_mat = b.node("GeometryNodeSetMaterial", 850, -300)
    b.link(pts.outputs["Points"], pts_mat.inputs["Geometry"])
    b.link(gin.outputs["Material"], pts_mat.inputs["Material"])

    switch = b.node("GeometryNodeSwitch", 900, 0, input_type="GEOMETRY")
    b.link(gin.outputs["Points Only"], switch.inputs["Switch"])
    b.link(inst.outputs["Instances"], switch.inputs["False"])
    b.link(pts_mat.outputs["Geometry"], switch.inputs["True"])
    b.link(switch.outputs[0], gout.inputs["Geometry"])
    gout.location = (1100, 0)
    ng["gvae_nodes_version"] = NODES_VERSION


def ensure_node_group():
    """The shared node group, built (or rebuilt when outdated) on demand."""
    ng = bpy.data.node_groups.get(GROUP_NAME)
    if ng is None or ng.bl_idname != "GeometryNodeTree":
        ng = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    if ng.get("gvae_nodes_version") != NODES_VERSION:
        _build_group(ng)
    return ng


def _attr_sum(b: _Builder, name: str, x: float, y: float):
    """Attribute `name` as instancer attribute plus as geometry attribute (one of them is 0)."""
    inst = b.node("ShaderNodeAttribute", x, y, attribute_type="INSTANCER", attribute_name=name)
    geom = b.node("ShaderNodeAttribute", x, y - 170, attribute_type="GEOMETRY", attribute_name=name)
    return b.math("ADD", inst.outputs["Fac"], geom.outputs["Fac"], x + 200, y)


def _build_material(mat) -> None:
    mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    b = _Builder(tree)
    rgb = b.node("ShaderNodeCombineColor", -100, 300)
    for i, comp in enumerate(("Red", "Green", "Blue")):
        dc = _attr_sum(b, f"f_dc_{i}", -900, 600 - 380 * i)
        lin = b.math("MULTIPLY_ADD", dc, SH_C0, -450, 600 - 380 * i)
        lin.node.inputs[2].default_value = 0.5
        b.link(b.math("MAXIMUM", lin, 0.0, -250, 600 - 380 * i), rgb.inputs[comp])
    logit = _attr_sum(b, "opacity", -900, -600)
    clamped = b.node("ShaderNodeClamp", -450, -600)
    clamped.inputs["Min"].default_value, clamped.inputs["Max"].default_value = OPACITY_LOGIT_RANGE
    b.link(logit, clamped.inputs["Value"])
    expo = b.math("EXPONENT", b.math("MULTIPLY", clamped.outputs[0], -1.0, -300, -600), x=-150, y=-600)
    alpha = b.math("DIVIDE", 1.0, b.math("ADD", expo, 1.0, 0, -600), 150, -600)
    # Only the ellipsoid's front faces draw: a ray through a closed mesh would blend it twice.
    geometry = b.node("ShaderNodeNewGeometry", 0, -800)
    alpha = b.math("MULTIPLY", alpha, b.math("SUBTRACT", 1.0, geometry.outputs["Backfacing"], 150, -800),
                   300, -650)
    emit = b.node("ShaderNodeEmission", 200, 300)
    b.link(rgb.outputs[0], emit.inputs["Color"])
    emit.inputs["Strength"].default_value = 1.0
    transparent = b.node("ShaderNodeBsdfTransparent", 200, 100)
    mix = b.node("ShaderNodeMixShader", 450, 200)
    b.link(alpha, mix.inputs["Fac"])
    b.link(transparent.outputs[0], mix.inputs[1])
    b.link(emit.outputs[0], mix.inputs[2])
    out = b.node("ShaderNodeOutputMaterial", 650, 200)
    b.link(mix.outputs[0], out.inputs["Surface"])
    mat.surface_render_method = "BLENDED"
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
    return next(item.identifier for item in ng.interface.items_tree
                if getattr(item, "in_out", None) == "INPUT" and item.name == name)


def add_splat_modifier(obj, *, scale_factor: float = DEFAULT_SCALE_FACTOR, fraction: float = 1.0,
                       points_only: bool = False, min_opacity: float = 0.0):
    """Give `obj` the splat Geometry Nodes modifier (and material), or update its inputs."""
    ng = ensure_node_group()
    mat = ensure_material()
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is None or mod.type != "NODES":
        mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = ng
    values = {"Scale Factor": float(scale_factor), "Display Fraction": float(fraction),
              "Points Only": bool(points_only), "Min Opacity": float(min_opacity), "Material": mat}
    for name, value in values.items():
        mod[_socket_id(ng, name)] = value
    if mat.name not in obj.data.materials:
        obj.data.materials.append(mat)
    return mod


def splat_modifier(obj):
    """The splat modifier of `obj`, or None."""
    mod = obj.modifiers.get(MODIFIER_NAME) if obj is not None else None
    return mod if mod is not None and mod.type == "NODES" and mod.node_group is not None else None


def modifier_input_id(mod, name: str) -> str:
    return _socket_id(mod.node_group, name)
