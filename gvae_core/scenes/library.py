"""The benchmark scenes: procedural objects that stress what NeRF-Synthetic's scenes stress.
Each builder fills an empty Blender scene (after `blender.reset`) from a seeded numpy generator;
objects stay within a sphere of radius about 1.3 around the origin, z up, like NeRF-Synthetic.
Builders need bpy (through `blender`), but this module imports without it."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from . import blender
from . import geometry as g


@dataclass(frozen=True)
class SceneSpec:
    name: str
    stresses: str
    build: Callable[[np.random.Generator], None]


def _default_lights():
    b = blender
    b.studio_world(0.5)
    b.add_light("SUN", (3.0, -2.0, 5.0), energy=2.5, angle=math.radians(4.0))
    b.add_light("AREA", (-3.0, 2.5, 2.5), energy=150.0, size=2.0)


# ---------------------------------------------------------------------------------- textures
def _tex_coords(tree, kind="Object"):
    b = blender
    return b.node(tree, "ShaderNodeTexCoord", (-1200, 0)).outputs[kind]


def _wood(scale=6.0, dark=(0.25, 0.12, 0.05), light=(0.55, 0.32, 0.15)):
    def shader(tree, bsdf):
        b = blender
        co = _tex_coords(tree)
        noise = b.node(tree, "ShaderNodeTexNoise", (-900, 200), Scale=3.0, Detail=4.0)
        tree.links.new(co, noise.inputs["Vector"])
        wave = b.node(tree, "ShaderNodeTexWave", (-700, 0), Scale=scale, Distortion=6.0, Detail=3.0,
                      wave_type="RINGS", rings_direction="Z")
        tree.links.new(co, wave.inputs["Vector"])
        mix = b.node(tree, "ShaderNodeMix", (-400, 0), data_type="RGBA", A=(*dark, 1.0), B=(*light, 1.0))
        tree.links.new(wave.outputs["Fac"], mix.inputs["Factor"])
        tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    return shader


def _bricks_texture(tree, bsdf):
    """Small bricks with mortar, each brick's colour jittered by a Voronoi cell pattern, and a
    fine checker overlay: detail from 1 to 20 pixels at 400 px."""
    b = blender
    co = _tex_coords(tree)
    brick = b.node(tree, "ShaderNodeTexBrick", (-700, 200), Scale=6.0, **{
        "Color1": (0.55, 0.16, 0.08, 1.0), "Color2": (0.75, 0.45, 0.2, 1.0), "Mortar": (0.9, 0.88, 0.8, 1.0),
        "Mortar Size": 0.015, "Brick Width": 0.5, "Row Height": 0.2})
    tree.links.new(co, brick.inputs["Vector"])
    checker = b.node(tree, "ShaderNodeTexChecker", (-700, -200), Scale=60.0,
                     Color1=(0.05, 0.05, 0.05, 1.0), Color2=(0.95, 0.95, 0.9, 1.0))
    tree.links.new(co, checker.inputs["Vector"])
    voronoi = b.node(tree, "ShaderNodeTexVoronoi", (-700, -500), Scale=25.0)
    tree.links.new(co, voronoi.inputs["Vector"])
    band = b.node(tree, "ShaderNodeTexWave", (-700, 500), Scale=1.5, bands_direction="Z")
    tree.links.new(co, band.inputs["Vector"])
    # A band of checker across the bricks, the rest tinted per Voronoi cell.
    ramp = b.node(tree, "ShaderNodeMath", (-450, 400), operation="GREATER_THAN", Value=0.5)
    ramp.inputs[1].default_value = 0.75
    tree.links.new(band.outputs["Fac"], ramp.inputs[0])
    tint = b.node(tree, "ShaderNodeMix", (-450, 0), data_type="RGBA", blend_type="MULTIPLY", Factor=0.6)
    tree.links.new(brick.outputs["Color"], tint.inputs["A"])
    tree.links.new(voronoi.outputs["Color"], tint.inputs["B"])
    mix = b.node(tree, "ShaderNodeMix", (-200, 0), data_type="RGBA")
    tree.links.new(ramp.outputs["Value"], mix.inputs["Factor"])
    tree.links.new(tint.outputs["Result"], mix.inputs["A"])
    tree.links.new(checker.outputs["Color"], mix.inputs["B"])
    tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])


def _magic_texture(tree, bsdf):
    """Blender's Magic texture: colourful interference patterns, with fine stripes on top."""
    b = blender
    co = _tex_coords(tree)
    magic = b.node(tree, "ShaderNodeTexMagic", (-700, 0), Scale=9.0, Distortion=2.0, turbulence_depth=4)
    tree.links.new(co, magic.inputs["Vector"])
    wave = b.node(tree, "ShaderNodeTexWave", (-700, -300), Scale=25.0, Distortion=1.0, bands_direction="X")
    tree.links.new(co, wave.inputs["Vector"])
    mix = b.node(tree, "ShaderNodeMix", (-300, 0), data_type="RGBA", blend_type="MULTIPLY", Factor=0.7)
    tree.links.new(magic.outputs["Color"], mix.inputs["A"])
    tree.links.new(wave.outputs["Color"], mix.inputs["B"])
    tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])


def _noise_rings(tree, bsdf):
    """Concentric rings and speckle noise on a sphere."""
    b = blender
    co = _tex_coords(tree)
    noise = b.node(tree, "ShaderNodeTexNoise", (-700, -200), Scale=80.0, Detail=2.0)
    tree.links.new(co, noise.inputs["Vector"])
    wave = b.node(tree, "ShaderNodeTexWave", (-700, 200), Scale=12.0, wave_type="RINGS", rings_direction="Z")
    tree.links.new(co, wave.inputs["Vector"])
    ramp = b.node(tree, "ShaderNodeValToRGB", (-450, 200))
    ramp.color_ramp.elements[0].color = (0.05, 0.15, 0.45, 1.0)
    ramp.color_ramp.elements[1].color = (0.95, 0.85, 0.3, 1.0)
    ramp.color_ramp.interpolation = "CONSTANT"
    ramp.color_ramp.elements[1].position = 0.5
    tree.links.new(wave.outputs["Fac"], ramp.inputs["Fac"])
    mix = b.node(tree, "ShaderNodeMix", (-200, 0), data_type="RGBA", blend_type="OVERLAY", Factor=0.5)
    tree.links.new(ramp.outputs["Color"], mix.inputs["A"])
    tree.links.new(noise.outputs["Color"], mix.inputs["B"])
    tree.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])


# ------------------------------------------------------------------------------------- scenes
def build_plant(rng: np.random.Generator) -> None:
    """A potted plant: a main stem, branches a few pixels wide or less, ~100 thin leaves."""
    b = blender
    _default_lights()
    clay = b.material("clay", (0.6, 0.28, 0.15), roughness=0.7)
    soil = b.material("soil", (0.09, 0.06, 0.04), roughness=1.0)
    bark = b.material("stem", (0.25, 0.35, 0.12), roughness=0.6)
    green = b.material("leaf", (0.1, 0.4, 0.08), roughness=0.45, specular=0.6)
    pot = [(0.0, -1.1), (0.30, -1.1), (0.40, -0.6), (0.44, -0.6), (0.44, -0.54), (0.39, -0.54), (0.37, -0.63),
           (0.0, -0.63)]
    b.add_mesh("pot", g.lathe(pot, 48), clay, smooth=math.radians(40))
    b.add_mesh("soil", g.lathe([(0.372, -0.618), (0.2, -0.612), (0.0, -0.61)], 48), soil, smooth=True)

    stems, leaves = [], []

    def curve(start, direction, length, n, droop, wobble):
        pts = [np.asarray(start, float)]
        d = np.asarray(direction, float) / np.linalg.norm(direction)
        for _ in range(n):
            d = d + np.array([0, 0, -droop]) + rng.normal(0, wobble, 3)
            d /= np.linalg.norm(d)
            pts.append(pts[-1] + d * length / n)
        return np.array(pts)

    main = curve((0, 0, -0.62), (0.02, 0.0, 1.0), 1.55, 16, 0.0, 0.03)
    stems.append(g.tube(main, np.linspace(0.022, 0.007, len(main)), 8))
    n_branch = 8
    for i in range(n_branch):
        t = 0.3 + 0.6 * i / n_branch + rng.uniform(-0.03, 0.03)
        root = main[int(t * (len(main) - 1))]
        az = 2.39996 * i + rng.uniform(-0.3, 0.3)
        out = np.array([math.cos(az), math.sin(az), 0.0])
        length = (0.75 - 0.45 * t) * rng.uniform(0.85, 1.15)
        branch = curve(root, out + np.array([0, 0, 0.9 - 0.3 * t]), length, 10, 0.08, 0.04)
        stems.append(g.tube(branch, np.linspace(0.011, 0.004, len(branch)), 6))
        for k in range(2, len(branch), 2):
            for side in (-1.0, 1.0):
                tangent = branch[min(k + 1, len(branch) - 1)] - branch[k - 1]
                tangent /= np.linalg.norm(tangent)
                side_dir = np.cross(tangent, [0, 0, 1.0])
                side_dir /= max(np.linalg.norm(side_dir), 1e-9)
                axis = 0.55 * tangent + side * side_dir + np.array([0, 0, 0.25])
                axis /= np.linalg.norm(axis)
                size = rng.uniform(0.13, 0.2)
                blade = g.leaf(size, size * rng.uniform(0.45, 0.6), fold=0.3, curl=0.35)
                # Frame: leaf x along `axis`, its normal roughly up.
                up = np.array([0, 0, 1.0]) - np.dot([0, 0, 1.0], axis) * axis
                up /= np.linalg.norm(up)
                m = np.eye(4)
                m[:3, 0], m[:3, 1], m[:3, 2] = axis, np.cross(up, axis), up
                m[:3, :3] = g.rotation(axis, rng.uniform(-0.5, 0.5))[:3, :3] @ m[:3, :3]
                m[:3, 3] = branch[k]
                leaves.append(g.transform(blade, m))
    b.add_mesh("stems", g.merge(*stems), bark, smooth=True)
    b.add_mesh("leaves", g.merge(*leaves), green, smooth=True)


def build_crate(rng: np.random.Generator) -> None:
    """High-frequency texture: a bevelled crate covered in tiny bricks and checker bands, a can
    with an interference pattern and a ball with rings and speckle."""
    b = blender
    _default_lights()
    crate = g.transform(g.box((1.0, 1.0, 1.0)), g.translation((-0.28, 0.12, -0.45)) @ g.rotation((0, 0, 1), 0.35))
    b.add_mesh("crate", crate, b.material("bricks", roughness=0.8, shader=_bricks_texture), bevel=0.03)
    can = g.cylinder(0.3, -0.95, 0.05, (0.55, -0.45), 64)
    b.add_mesh("can", can, b.material("magic", roughness=0.35, shader=_magic_texture), smooth=math.radians(50),
               bevel=0.015)
    ball = g.uv_sphere(0.3, (0.15 + rng.uniform(-0.05, 0.05), 0.75, -0.65), 32, 64)
    b.add_mesh("ball", ball, b.material("rings", roughness=0.5, shader=_noise_rings), smooth=True)


def build_materials(rng: np.random.Generator) -> None:
    """Glossy and specular: seven spheres (mirror chrome, gold, brushed copper, coated plastic,
    black lacquer, glazed ceramic, satin steel) on a matte disc, lit by area lights they reflect."""
    b = blender
    b.studio_world(1.0)
    b.add_light("AREA", (2.5, -2.5, 3.0), energy=400.0, size=1.0)
    b.add_light("AREA", (-3.0, -0.5, 2.0), energy=250.0, size=0.6)
    b.add_light("AREA", (0.5, 3.0, 2.5), energy=200.0, size=1.5)
    disc = g.lathe([(0.0, -0.78), (1.15, -0.78), (1.2, -0.74), (1.2, -0.70), (1.15, -0.66), (0.0, -0.66)], 96)
    b.add_mesh("disc", disc, b.material("matte", (0.2, 0.25, 0.3), roughness=0.9), smooth=math.radians(35))
    specs = [("chrome", (0.95, 0.95, 0.95), 0.02, 1.0, 0.0, 0.0),
             ("gold", (1.0, 0.75, 0.3), 0.12, 1.0, 0.0, 0.0),
             ("copper", (0.95, 0.5, 0.35), 0.3, 1.0, 0.0, 0.8),
             ("plastic", (0.8, 0.05, 0.04), 0.4, 0.0, 1.0, 0.0),
             ("lacquer", (0.02, 0.02, 0.02), 0.05, 0.0, 1.0, 0.0),
             ("ceramic", (0.85, 0.88, 0.92), 0.25, 0.0, 0.6, 0.0),
             ("steel", (0.6, 0.62, 0.65), 0.2, 1.0, 0.0, 0.0)]
    order = rng.permutation(len(specs))
    r = 0.3
    for slot, idx in enumerate(order):
        name, color, rough, metal, coat, aniso = specs[idx]
        if slot == 0:
            center = (0.0, 0.0, -0.66 + r)
        else:
            a = 2 * math.pi * (slot - 1) / 6 + 0.3
            center = (0.72 * math.cos(a), 0.72 * math.sin(a), -0.66 + r)
        mat = b.material(name, color, roughness=rough, metallic=metal, coat=coat, anisotropic=aniso)
        b.add_mesh(name, g.uv_sphere(r, center, 32, 64), mat, smooth=True)


def build_bricks(rng: np.random.Generator) -> None:
    """Fine repeated geometry: a baseplate with 16x16 studs and a small stack of studded bricks."""
    b = blender
    _default_lights()
    pitch, stud_r, stud_h, plate_h, brick_h = 0.1, 0.03, 0.02, 0.04, 0.12
    top = -0.55
    plate = g.box((16 * pitch, 16 * pitch, plate_h), (0, 0, top - plate_h / 2))

    def studs(nx, ny, x0, y0, z):
        return [g.cylinder(stud_r, z, z + stud_h, (x0 + (i + 0.5) * pitch, y0 + (j + 0.5) * pitch), 12)
                for i in range(nx) for j in range(ny)]

    b.add_mesh("baseplate", g.merge(plate, *studs(16, 16, -0.8, -0.8, top)),
               b.material("green", (0.1, 0.45, 0.12), roughness=0.35, specular=0.6), smooth=math.radians(35))
    palette = [(0.75, 0.05, 0.05), (0.95, 0.75, 0.05), (0.05, 0.25, 0.7), (0.9, 0.9, 0.88), (0.1, 0.1, 0.1)]
    mats = [b.material(f"plastic{i}", c, roughness=0.3, specular=0.6) for i, c in enumerate(palette)]
    # Layers of 2x4 / 2x2 bricks on a grid, each layer narrower: a little stepped tower.
    parts: dict[int, list] = {i: [] for i in range(len(mats))}
    occupancy = {}
    for layer in range(5):
        n = 10 - 2 * layer
        z = top + layer * brick_h
        for _ in range(n):
            for _attempt in range(60):
                w, d = (4, 2) if rng.random() < 0.6 else (2, 2)
                if rng.random() < 0.5:
                    w, d = d, w
                span = 10 - 2 * layer
                if w > span or d > span:
                    continue
                i0 = int(rng.integers(-span // 2, span // 2 - w + 1))
                j0 = int(rng.integers(-span // 2, span // 2 - d + 1))
                cells = {(layer, i, j) for i in range(i0, i0 + w) for j in range(j0, j0 + d)}
                supported = layer == 0 or all((layer - 1, i, j) in occupancy for (_, i, j) in cells)
                if supported and not cells & occupancy.keys():
                    color = int(rng.integers(len(mats)))
                    for c in cells:
                        occupancy[c] = color
                    x0, y0 = i0 * pitch, j0 * pitch
                    body = g.box((w * pitch - 0.002, d * pitch - 0.002, brick_h),
                                 (x0 + w * pitch / 2, y0 + d * pitch / 2, z + brick_h / 2))
                    parts[color].append(g.merge(body, *studs(w, d, x0, y0, z + brick_h)))
                    break
    for color, meshes in parts.items():
        if meshes:
            b.add_mesh(f"bricks{color}", g.merge(*meshes), mats[color], smooth=math.radians(35))


def build_chair(rng: np.random.Generator) -> None:
    """A chair with thin splayed legs, thin stretchers, a backrest of thin spindles and a cushion."""
    b = blender
    _default_lights()
    wood = b.material("wood", roughness=0.45, coat=0.3, shader=_wood())
    fabric = b.material("fabric", (0.55, 0.08, 0.1), roughness=0.9)
    seat_z, half = -0.15, 0.38
    b.add_mesh("seat", g.box((2 * half + 0.04, 2 * half + 0.04, 0.06), (0, 0, seat_z)), wood, bevel=0.01)
    legs, splay = [], 0.06
    feet = {}
    for sx in (-1, 1):
        for sy in (-1, 1):
            top_pt = np.array([sx * (half - 0.03), sy * (half - 0.03), seat_z - 0.03])
            foot = top_pt + np.array([sx * splay, sy * splay, -0.85])
            feet[(sx, sy)] = (top_pt, foot)
            legs.append(g.tube(np.linspace(top_pt, foot, 6), np.linspace(0.024, 0.016, 6), 12))
            if sy == 1:  # rear legs continue up as back posts
                post_top = top_pt + np.array([0, 0.08, 1.1])
                legs.append(g.tube(np.linspace(top_pt + [0, 0, 0.03], post_top, 8), np.linspace(0.022, 0.016, 8), 12))
    for (a, c) in [((-1, -1), (1, -1)), ((-1, 1), (1, 1)), ((-1, -1), (-1, 1)), ((1, -1), (1, 1))]:
        (ta, fa), (tc, fc) = feet[a], feet[c]
        pa, pc = ta + 0.6 * (fa - ta), tc + 0.6 * (fc - tc)
        legs.append(g.tube(np.linspace(pa, pc, 4), 0.011, 8))
    back_y = half - 0.03 + 0.08
    rail_z = seat_z + 0.98
    rail = g.box((2 * half, 0.04, 0.12), (0, back_y, rail_z))
    n_spindle = 7 + int(rng.integers(0, 3))
    for k in range(n_spindle):
        x = -half + 0.06 + (2 * half - 0.12) * k / (n_spindle - 1)
        start = np.array([x, half - 0.03 + 0.01, seat_z + 0.03])
        end = np.array([x, back_y, rail_z - 0.06])
        legs.append(g.tube(np.linspace(start, end, 6), 0.008, 6))
    b.add_mesh("frame", g.merge(*legs), wood, smooth=True)
    b.add_mesh("rail", rail, wood, bevel=0.01)
    cushion = g.box((2 * half - 0.08, 2 * half - 0.12, 0.06), (0, -0.02, seat_z + 0.06))
    b.add_mesh("cushion", cushion, fabric, smooth=True, subdivide=3)


def build_tableware(rng: np.random.Generator) -> None:
    """Compound object with large smooth areas: a wide plate, a glazed mug with a handle, an
    orange and an egg-shaped lemon, finely tessellated and smooth-shaded. (No subdivision
    modifier: OpenSubdiv is very slow on the high-valence poles of revolved shapes.)"""
    b = blender
    _default_lights()
    plate = [(0.0, -0.78), (0.4, -0.78), (0.65, -0.78), (0.68, -0.775), (0.70, -0.765), (0.85, -0.72),
             (1.02, -0.665), (1.08, -0.645), (1.12, -0.63), (1.12, -0.615), (1.10, -0.61), (1.06, -0.62),
             (1.00, -0.635), (0.85, -0.68), (0.70, -0.725), (0.66, -0.735), (0.4, -0.735), (0.0, -0.735)]
    b.add_mesh("plate", g.lathe(plate, 128), b.material("porcelain", (0.92, 0.92, 0.9), roughness=0.15, coat=0.5),
               smooth=True)
    mug_xy = (-0.3 + rng.uniform(-0.05, 0.05), -0.15)
    mug = [(0.0, -0.735), (0.24, -0.735), (0.28, -0.70), (0.30, 0.0), (0.30, 0.03), (0.27, 0.03), (0.26, -0.64),
           (0.0, -0.66)]
    mv, mf = g.lathe(mug, 96)
    mv[:, :2] += mug_xy
    glaze = b.material("glaze", (0.1, 0.3, 0.65), roughness=0.2, coat=0.8)
    b.add_mesh("mug", (mv, mf), glaze, smooth=math.radians(50))
    t = np.linspace(-0.5 * math.pi, 0.5 * math.pi, 16)
    handle = np.stack([mug_xy[0] - 0.27 - 0.17 * np.cos(t), np.full_like(t, mug_xy[1]), -0.33 + 0.2 * np.sin(t)], 1)
    b.add_mesh("handle", g.tube(handle, 0.04, 16), glaze, smooth=True)
    b.add_mesh("orange", g.uv_sphere(0.24, (0.45, 0.3, -0.735 + 0.23), 48, 96, squash=(1, 1, 0.95)),
               b.material("orange", (0.9, 0.4, 0.03), roughness=0.5), smooth=True)
    b.add_mesh("lemon", g.transform(g.uv_sphere(0.17, (0, 0, 0), 48, 96, squash=(1.35, 1, 1)),
                                    g.translation((0.5, -0.4, -0.735 + 0.165)) @ g.rotation((0, 0, 1), 0.6)),
               b.material("lemon", (0.95, 0.85, 0.1), roughness=0.4), smooth=True)


def _circle(radius: float, n: int, z: float = 0.0, arc: float = 2 * math.pi, start: float = 0.0) -> np.ndarray:
    """(n,3) points on a circle (or an arc) in the xy plane at height z; a full circle repeats
    its first point at the end so that a tube along it closes."""
    t = start + arc * np.arange(n + 1) / n
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full_like(t, z)], 1)


def _stripes(tree, bsdf):
    """Book spines: colour bands along the spine and fine, text-like ticks across it."""
    b = blender
    co = _tex_coords(tree)
    bands = b.node(tree, "ShaderNodeTexWave", (-700, 200), Scale=3.0, wave_type="BANDS", bands_direction="Z",
                   Distortion=0.0)
    tree.links.new(co, bands.inputs["Vector"])
    ticks = b.node(tree, "ShaderNodeTexChecker", (-700, -150), Scale=90.0)
    tree.links.new(co, ticks.inputs["Vector"])
    ramp = b.node(tree, "ShaderNodeValToRGB", (-450, 200))
    ramp.color_ramp.interpolation = "CONSTANT"
    ramp.color_ramp.elements[0].color = (0.9, 0.82, 0.55, 1.0)
    ramp.color_ramp.elements[1].position = 0.7
    ramp.color_ramp.elements[1].color = (0.05, 0.05, 0.06, 1.0)
    tree.links.new(bands.outputs["Fac"], ramp.inputs["Fac"])
    mix = b.node(tree, "ShaderNodeMix", (-200, 0), data_type="RGBA", blend_type="MULTIPLY", Factor=0.35)
    tree.links.new(ramp.outputs["Color"], mix.inputs["A"])
    tree.links.new(ticks.outputs["Color"], mix.inputs["B"])
    base = b.node(tree, "ShaderNodeMix", (0, 0), data_type="RGBA", blend_type="MULTIPLY", Factor=1.0)
    base.inputs["A"].default_value = bsdf.inputs["Base Color"].default_value
    tree.links.new(mix.outputs["Result"], base.inputs["B"])
    tree.links.new(base.outputs["Result"], bsdf.inputs["Base Color"])


def build_wheel(rng: np.random.Generator) -> None:
    """A bicycle wheel standing upright: tyre, rim, hub and 32 crossed spokes a pixel wide."""
    b = blender
    _default_lights()
    upright = g.rotation((1, 0, 0), math.pi / 2) @ g.rotation((0, 0, 1), rng.uniform(0, 0.3))
    tyre = g.tube(_circle(0.9, 96), 0.065, 12, caps=False)
    rim = g.tube(_circle(0.83, 96), 0.028, 8, caps=False)
    hub = g.cylinder(0.05, -0.11, 0.11, (0, 0), 24)
    spokes = []
    for k in range(32):
        side = 1.0 if k % 2 else -1.0
        a = 2 * math.pi * k / 32
        lace = a + side * 3 * 2 * math.pi / 32 * (1 if k % 4 < 2 else -1)  # three-cross lacing
        start = np.array([0.05 * math.cos(lace), 0.05 * math.sin(lace), side * 0.08])
        end = np.array([0.81 * math.cos(a), 0.81 * math.sin(a), 0.0])
        spokes.append(g.tube(np.linspace(start, end, 3), 0.006, 6))
    b.add_mesh("tyre", g.transform(tyre, upright), b.material("rubber", (0.04, 0.04, 0.04), roughness=0.85),
               smooth=True)
    b.add_mesh("rim", g.transform(rim, upright), b.material("alloy", (0.8, 0.8, 0.82), roughness=0.2, metallic=1.0),
               smooth=True)
    steel = b.material("spokes", (0.7, 0.7, 0.72), roughness=0.3, metallic=1.0)
    b.add_mesh("hub", g.transform(hub, upright), steel, smooth=math.radians(40))
    b.add_mesh("spokes", g.transform(g.merge(*spokes), upright), steel, smooth=True)
    stand = g.box((0.5, 0.3, 0.04), (0, 0, -1.0))
    b.add_mesh("stand", stand, b.material("stand", (0.3, 0.32, 0.35), roughness=0.6), bevel=0.01)


def build_lamp(rng: np.random.Generator) -> None:
    """A desk lamp: a heavy round base, two thin arms with ball joints, a glossy conical shade,
    and a coiled cable: thin parts and specular highlights together."""
    b = blender
    _default_lights()
    metal = b.material("lamp_red", (0.75, 0.06, 0.05), roughness=0.15, coat=0.8)
    chrome = b.material("chrome", (0.9, 0.9, 0.92), roughness=0.05, metallic=1.0)
    base = g.lathe([(0.0, -1.0), (0.42, -1.0), (0.44, -0.97), (0.42, -0.92), (0.12, -0.88), (0.0, -0.88)], 64)
    b.add_mesh("base", base, metal, smooth=math.radians(40))
    lean = rng.uniform(-0.1, 0.1)
    elbow = np.array([0.25 + lean, 0.0, 0.15])
    head = np.array([-0.35, 0.05, 0.55 + lean])
    arms = [g.tube(np.linspace([0, 0, -0.9], elbow, 8), 0.02, 10), g.tube(np.linspace(elbow, head, 8), 0.017, 10)]
    joints = [g.uv_sphere(0.04, elbow, 12, 24), g.uv_sphere(0.035, head, 12, 24)]
    b.add_mesh("arms", g.merge(*arms, *joints), chrome, smooth=True)
    shade = g.lathe([(0.0, 0.12), (0.06, 0.12), (0.09, 0.05), (0.32, -0.25), (0.31, -0.26), (0.08, 0.04),
                     (0.0, 0.1)], 64)
    aim = g.rotation((0, 1, 0), -0.6)
    b.add_mesh("shade", g.transform(shade, g.translation(head) @ aim), metal, smooth=math.radians(35))
    t = np.linspace(0, 1, 120)
    coil = np.stack([0.05 + 0.5 * t + 0.04 * np.cos(40 * t), -0.35 + 0.04 * np.sin(40 * t),
                     np.full_like(t, -0.97) + 0.02 * np.sin(40 * t)], 1)
    b.add_mesh("cable", g.tube(coil, 0.008, 6), b.material("cable", (0.05, 0.05, 0.05), roughness=0.5),
               smooth=True)


def build_books(rng: np.random.Generator) -> None:
    """A shelf board with a row of books (striped, text-like spines) and two lying flat: large
    flat areas beside fine printed detail."""
    b = blender
    _default_lights()
    board = g.box((2.0, 0.6, 0.06), (0, 0, -0.75))
    b.add_mesh("board", board, b.material("board", roughness=0.5, shader=_wood()), bevel=0.01)
    x = -0.9
    palette = [(0.55, 0.08, 0.08), (0.08, 0.2, 0.45), (0.1, 0.35, 0.15), (0.6, 0.45, 0.1), (0.3, 0.1, 0.35)]
    for k in range(10):
        width = rng.uniform(0.07, 0.16)
        height = rng.uniform(0.55, 0.85)
        depth = rng.uniform(0.36, 0.48)
        tilt = g.rotation((0, 1, 0), rng.uniform(-0.05, 0.05))
        book = g.transform(g.box((width, depth, height)), g.translation((x + width / 2, 0, -0.72 + height / 2)) @ tilt)
        color = palette[int(rng.integers(len(palette)))]
        b.add_mesh(f"book{k}", book, b.material(f"book{k}", color, roughness=0.6, shader=_stripes), bevel=0.006)
        x += width + 0.005
    for k, z in enumerate((-0.69, -0.63)):
        flat = g.box((0.55, 0.42, 0.06), (0.62, 0.02 + 0.03 * k, z))
        b.add_mesh(f"flat{k}", g.transform(flat, g.rotation((0, 0, 1), rng.uniform(-0.2, 0.2))),
                   b.material(f"flat{k}", palette[(k + 2) % len(palette)], roughness=0.6, shader=_stripes),
                   bevel=0.006)


def build_mic(rng: np.random.Generator) -> None:
    """A studio microphone: a wire-mesh grille of thin rings and meridians over a dark capsule,
    a glossy body and a thin tripod stand."""
    b = blender
    _default_lights()
    wire = b.material("grille", (0.75, 0.75, 0.78), roughness=0.25, metallic=1.0)
    r, top = 0.3, 0.55
    rings = [g.tube(_circle(r * math.cos(phi), 64, top + r * math.sin(phi)), 0.006, 6, caps=False)
             for phi in np.linspace(-1.2, 1.35, 14)]
    meridians = []
    for k in range(24):
        a = 2 * math.pi * k / 24
        phi = np.linspace(-1.2, 1.45, 24)
        path = np.stack([r * np.cos(phi) * math.cos(a), r * np.cos(phi) * math.sin(a), top + r * np.sin(phi)], 1)
        meridians.append(g.tube(path, 0.005, 6))
    b.add_mesh("grille", g.merge(*rings, *meridians), wire, smooth=True)
    b.add_mesh("capsule", g.uv_sphere(0.26, (0, 0, top), 24, 48),
               b.material("capsule", (0.04, 0.04, 0.05), roughness=0.7), smooth=True)
    body = g.lathe([(0.0, -0.35), (0.16, -0.35), (0.2, -0.2), (0.24, 0.2), (0.26, 0.3), (0.0, 0.3)], 64)
    b.add_mesh("body", body, b.material("body", (0.12, 0.12, 0.14), roughness=0.1, metallic=0.8, coat=1.0),
               smooth=math.radians(40))
    legs = [g.tube(np.linspace([0, 0, -0.35], [0, 0, -0.75], 4), 0.02, 10)]
    for k in range(3):
        a = 2 * math.pi * k / 3 + rng.uniform(-0.2, 0.2)
        legs.append(g.tube(np.linspace([0, 0, -0.75], [0.6 * math.cos(a), 0.6 * math.sin(a), -1.05], 6), 0.014, 8))
    b.add_mesh("stand", g.merge(*legs), b.material("stand_metal", (0.2, 0.2, 0.22), roughness=0.3, metallic=1.0),
               smooth=True)


SCENES: dict[str, SceneSpec] = {s.name: s for s in [
    SceneSpec("plant", "thin structures: stems a pixel wide, many thin leaves", build_plant),
    SceneSpec("crate", "high-frequency procedural texture (bricks, checker, interference, speckle)", build_crate),
    SceneSpec("materials", "glossy and specular spheres reflecting lights and environment", build_materials),
    SceneSpec("bricks", "fine repeated geometry: hundreds of studs on plates and bricks", build_bricks),
    SceneSpec("chair", "thin legs, stretchers and spindles; wood texture; a soft cushion", build_chair),
    SceneSpec("tableware", "compound object with large smooth surfaces (plate, mug, fruit)", build_tableware),
    SceneSpec("wheel", "thin crossed spokes at every angle around a glossy rim and a dark tyre", build_wheel),
    SceneSpec("lamp", "thin arms and a coiled cable beside a glossy shade and chrome joints", build_lamp),
    SceneSpec("books", "flat board and covers beside fine striped, text-like spines", build_books),
    SceneSpec("mic", "a wire-mesh grille over a dark capsule; glossy body; thin tripod legs", build_mic),
]}

#: Which scenes each part of the work may look at. The bundled model learns from `train` scenes;
#: every choice (model size, flags, thresholds, budgets, the global scale knob) is made on
#: `validation`; `test` scenes are looked at once, for the report, and never to choose anything.
SPLITS: dict[str, tuple[str, ...]] = {
    "train": ("plant", "crate", "materials", "bricks"),
    "validation": ("chair", "tableware"),
    "test": ("wheel", "lamp", "books", "mic"),
}
