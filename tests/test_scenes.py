"""Benchmark scenes: geometry and camera helpers (numpy), the cache and CLI (no Blender needed),
and, with bpy, one scene generated end to end at the tiny profile (loads with
load_nerf_synthetic, the mesh projects onto its silhouettes, renders are reproducible) plus every
other scene built without rendering."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from plyfile import PlyData
from scipy.spatial import cKDTree

from gvae_core import Camera, load_nerf_synthetic, scenes
from gvae_core.cli import main as cli_main
from gvae_core.scenes import cameras
from gvae_core.scenes import geometry as g
from tests.conftest import requires_bpy

FULL_SCENE = "chair"  # thin legs: the hardest silhouette for the projection check


# ----------------------------------------------------------------------------- numpy helpers
def test_lathe_sphere_is_closed_and_outward():
    verts, faces = g.uv_sphere(0.5, (0.1, -0.2, 0.3), rings=12, segments=20)
    assert np.allclose(np.linalg.norm(verts - [0.1, -0.2, 0.3], axis=1), 0.5)
    tris = g.triangulate(faces)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # every edge shared by exactly two triangles: no holes
    v = verts[tris]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    outward = np.einsum("nd,nd->n", normals, v.mean(1) - [0.1, -0.2, 0.3])
    assert (outward > 0).all()
    # Enclosed volume (divergence theorem) close to the sphere's.
    volume = np.einsum("nd,nd->n", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    assert volume == pytest.approx(4 / 3 * math.pi * 0.125, rel=0.1)


def test_tube_follows_path_at_radius():
    t = np.linspace(0, math.pi, 20)
    path = np.stack([np.cos(t), np.sin(t), 0.3 * t], 1)
    verts, faces = g.tube(path, 0.05, segments=7, caps=False)
    ring = verts.reshape(len(path), 7, 3)
    assert np.allclose(np.linalg.norm(ring - path[:, None], axis=2), 0.05)
    tangent = np.gradient(path, axis=0)
    assert np.abs(np.einsum("pkd,pd->pk", ring - path[:, None], tangent)).max() < 1e-9  # rings across the path
    assert len(faces) == 19 * 7


def test_sample_surface_is_area_uniform_and_on_surface():
    verts, faces = g.box((2.0, 1.0, 0.5))
    pts, idx = g.sample_surface(verts, g.triangulate(faces), 60_000, np.random.default_rng(0))
    on_face = np.isclose(np.abs(pts), [1.0, 0.5, 0.25]).any(axis=1)
    assert on_face.all() and (np.abs(pts) <= np.array([1.0, 0.5, 0.25]) + 1e-12).all()
    frac_top = np.isclose(np.abs(pts[:, 2]), 0.25).mean()
    assert frac_top == pytest.approx(2 * 2.0 / (2 * (2.0 + 1.0 + 0.5)), abs=0.01)  # area share of top+bottom


def test_cameras_on_upper_hemisphere_looking_at_origin():
    for c2ws in (cameras.train_views(60, 0), cameras.test_views(20, 0)):
        eyes = c2ws[:, :3, 3]
        assert np.allclose(np.linalg.norm(eyes, axis=1), cameras.RADIUS)
        assert (eyes[:, 2] > 0).all()
        forward = -c2ws[:, :3, 2]  # Blender cameras look along -z
        assert np.allclose(forward, -eyes / np.linalg.norm(eyes, axis=1, keepdims=True))
        assert (c2ws[:, 2, 0] == pytest.approx(0.0, abs=1e-9))  # no roll: image x stays horizontal
        for c2w in c2ws[:3]:
            cam = Camera.from_blender_c2w(c2w, cameras.CAMERA_ANGLE_X, 64, 64)
            uv, z = cam.project([[0, 0, 0], [0, 0, 0.5]])
            assert np.allclose(uv[0], [32, 32]) and uv[1, 1] < 32  # world up is image up
    assert math.asin(cameras.OBJECT_RADIUS / cameras.RADIUS) < cameras.CAMERA_ANGLE_X / 2  # objects fit
    train = cameras.train_views(60, 0)
    azimuth_gaps = np.diff(np.sort(np.arctan2(train[:, 1, 3], train[:, 0, 3])))
    assert azimuth_gaps.max() < 0.5  # spread all around
    assert np.array_equal(train, cameras.train_views(60, 0))
    assert not np.allclose(train, cameras.train_views(60, 1))


# ---------------------------------------------------------------------------- cache and CLI
def test_keys_and_bad_arguments():
    key = scenes.scene_key("plant", "tiny", 0)
    assert key == scenes.scene_key("plant", "tiny", 0)
    assert len({key, scenes.scene_key("plant", "tiny", 1), scenes.scene_key("plant", "default", 0),
                scenes.scene_key("chair", "tiny", 0)}) == 4
    with pytest.raises(ValueError, match="unknown scene 'nope'"):
        scenes.make_scene("nope")
    with pytest.raises(ValueError, match="unknown profile"):
        scenes.make_scene("plant", profile="huge")
    with pytest.raises(ValueError, match="seed"):
        scenes.make_scene("plant", seed=-1)
    assert len(scenes.list_scenes()) >= 6


def test_splits_partition_the_library():
    named = [name for split in scenes.SPLITS.values() for name in split]
    assert sorted(named) == sorted(scenes.list_scenes())  # every scene in exactly one split
    assert len(scenes.SPLITS["test"]) >= 4 and scenes.SPLITS["validation"] and scenes.SPLITS["train"]


def _fake_cached(cache, name="plant", profile="tiny", seed=0):
    key = scenes.scene_key(name, profile, seed)
    folder = cache / "scenes" / f"{name}-{profile}-s{seed}-{key}"
    (folder / "train").mkdir(parents=True)
    (folder / "train" / "r_0.png").write_bytes(b"png")
    (folder / scenes.MARKER).write_text(json.dumps({"key": key}))
    return folder


def _no_subprocess(*args, **kwargs):
    raise AssertionError("a cached scene must not be regenerated")


def test_cache_hit_and_export_without_blender(tmp_path, monkeypatch):
    folder = _fake_cached(tmp_path / "cache")
    monkeypatch.setattr(scenes.subprocess, "run", _no_subprocess)
    monkeypatch.setattr(scenes, "bpy_available", lambda: False)
    assert scenes.make_scene("plant", cache=tmp_path / "cache") == folder
    monkeypatch.setenv("GVAE_CACHE_DIR", str(tmp_path / "cache"))
    assert scenes.make_scene("plant") == folder
    out = scenes.make_scene("plant", tmp_path / "out")
    assert (out / "train" / "r_0.png").read_bytes() == b"png"
    assert scenes.make_scene("plant", tmp_path / "out") == out  # already there
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a generated scene"):
        scenes.make_scene("plant", tmp_path / "foreign")
    assert (tmp_path / "foreign" / "notes.txt").read_text() == "mine"


def test_cli_make_scene_from_cache(tmp_path, monkeypatch, capsys):
    folder = _fake_cached(tmp_path / "cache")
    monkeypatch.setattr(scenes.subprocess, "run", _no_subprocess)
    assert cli_main(["make-scene", "plant", "--cache-dir", str(tmp_path / "cache")]) == 0
    assert str(folder) in capsys.readouterr().out
    assert cli_main(["make-scene", "plant", "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "train" / "r_0.png").exists()


def test_missing_blender_is_a_clear_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(scenes, "bpy_available", lambda: False)
    with pytest.raises(scenes.BlenderNotAvailable, match=r"pip install bpy==5\.0\.1"):
        scenes.make_scene("plant", cache=tmp_path)
    assert cli_main(["make-scene", "plant", "--cache-dir", str(tmp_path)]) == 2
    assert "pip install bpy==5.0.1" in capsys.readouterr().err
    assert not (tmp_path / "scenes").exists() or not any((tmp_path / "scenes").iterdir())


def test_failed_generation_leaves_nothing(tmp_path, monkeypatch):
    def half_written(cmd, **kwargs):
        out = scenes.Path(cmd[4])
        (out / "train").mkdir(parents=True)
        (out / "train" / "r_0.png").write_bytes(b"partial")
        return subprocess.CompletedProcess(cmd, 1, None, "Traceback ...\nboom")

    monkeypatch.setattr(scenes, "bpy_available", lambda: True)
    monkeypatch.setattr(scenes.subprocess, "run", half_written)
    with pytest.raises(RuntimeError, match="boom"):
        scenes.make_scene("plant", cache=tmp_path)
    assert list((tmp_path / "scenes").iterdir()) == []


def test_cli_list_and_bad_name(capsys):
    assert cli_main(["list-scenes"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in scenes.list_scenes())
    assert cli_main(["list-scenes", "--json"]) == 0
    assert set(json.loads(capsys.readouterr().out)) == set(scenes.list_scenes())
    assert cli_main(["make-scene", "nope"]) == 2
    assert "unknown scene 'nope'" in capsys.readouterr().err


# ----------------------------------------------------------------------------- with Blender
def _read_mesh(path):
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    tris = np.stack(list(ply["face"]["vertex_indices"])).astype(np.int64)
    return verts, tris


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    cache = tmp_path_factory.mktemp("scene_cache")
    return scenes.make_scene(FULL_SCENE, profile="tiny", seed=0, cache=cache, threads=2), cache


@requires_bpy
def test_scene_loads_with_nerf_synthetic_loader(tiny_scene):
    root, _ = tiny_scene
    train, test = load_nerf_synthetic(root, "train"), load_nerf_synthetic(root, "test")
    assert (len(train), len(test)) == (8, 4)
    assert train.images.shape == (8, 64, 64, 3) and test.alphas.shape == (4, 64, 64)
    for views in (train, test):
        assert views.images.min() >= 0 and views.images.max() <= 1
        cover = (views.alphas > 0).mean(axis=(1, 2))
        assert (cover > 0.03).all() and (cover < 0.6).all()  # an object, on a transparent background
        assert (views.alphas[:, 0, :] == 0).all()  # nothing touches the top border
    meta = json.loads((root / "transforms_train.json").read_text())
    assert meta["frames"][0]["file_path"] == "./train/r_0"
    half = load_nerf_synthetic(root, "test", resolution=32)
    assert half.images.shape == (4, 32, 32, 3)


@requires_bpy
def test_mesh_projects_onto_rendered_silhouettes(tiny_scene):
    """The ground-truth mesh seen through the loaded cameras lands on pixels that the renders
    cover, and a camera convention mix-up (OpenGL matrix taken as OpenCV) would not."""
    root, _ = tiny_scene
    verts, tris = _read_mesh(root / "mesh.ply")
    assert len(tris) > 500 and tris.max() < len(verts)
    assert np.linalg.norm(verts, axis=1).max() <= cameras.OBJECT_RADIUS + 1e-5  # fits the views, like NeRF-Synthetic
    pts, _ = g.sample_surface(verts, tris, 4000, np.random.default_rng(0))
    for split in ("train", "test"):
        views = load_nerf_synthetic(root, split)
        frames = json.loads((root / f"transforms_{split}.json").read_text())["frames"]
        for cam, alpha, frame in zip(views.cameras, views.alphas, frames):
            for candidate, expect in ((cam, True), (Camera(np.linalg.inv(frame["transform_matrix"]), cam.fx, cam.fy,
                                                            cam.cx, cam.cy, 64, 64), False)):
                uv, z = candidate.project(pts)
                inside = (z > 0) & np.isfinite(uv).all(1)
                inside &= (uv >= 0).all(1) & (uv < 64).all(1)
                px = np.floor(uv[inside]).astype(int)
                hits = (alpha[px[:, 1], px[:, 0]] > 0).mean() if inside.any() else 0.0
                if expect:
                    assert inside.all() and hits > 0.995, (split, hits)
                else:
                    assert inside.mean() * hits < 0.5


@requires_bpy
def test_gt_points_are_on_the_mesh_and_seen_by_test_cameras(tiny_scene):
    root, _ = tiny_scene
    verts, tris = _read_mesh(root / "mesh.ply")
    gt = np.load(root / "gt_points.npy")
    meta = json.loads((root / "scene.json").read_text())
    assert gt.dtype == np.float32 and gt.shape == (meta["gt_points"], 3)
    assert 0.2 * scenes.PROFILES["tiny"].gt_candidates < len(gt) < 0.95 * scenes.PROFILES["tiny"].gt_candidates
    dense, _ = g.sample_surface(verts, tris, 300_000, np.random.default_rng(1))
    assert cKDTree(dense).query(gt)[0].max() < 0.03
    test = load_nerf_synthetic(root, "test")
    covered = np.zeros(len(gt), bool)
    for cam, alpha in zip(test.cameras, test.alphas):
        uv, z = cam.project(gt)
        ok = (z > 0) & (uv >= 0).all(1) & (uv < 64).all(1)
        px = np.floor(uv[ok]).astype(int)
        covered[np.flatnonzero(ok)[alpha[px[:, 1], px[:, 0]] > 0]] = True
    assert covered.mean() > 0.995


@requires_bpy
def test_cached_second_call_and_reproducible_renders(tiny_scene, tmp_path, monkeypatch):
    root, cache = tiny_scene
    with monkeypatch.context() as m:
        m.setattr(scenes.subprocess, "run", _no_subprocess)
        assert scenes.make_scene(FULL_SCENE, profile="tiny", seed=0, cache=cache) == root
        out = scenes.make_scene(FULL_SCENE, tmp_path / "copy", profile="tiny", seed=0, cache=cache)
        assert sorted(p.name for p in out.rglob("*")) == sorted(p.name for p in root.rglob("*"))
    again = scenes.make_scene(FULL_SCENE, profile="tiny", seed=0, cache=tmp_path / "fresh", threads=2)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file() and p.name != scenes.MARKER)
    assert any(f.suffix == ".png" for f in files) and (again / "mesh.ply").exists()
    for rel in files:
        assert (again / rel).read_bytes() == (root / rel).read_bytes(), rel


#: The scenes built without rendering, all in one Blender process (each `generate` starts from an empty
#: scene; bpy's start-up is most of a build's time).
BUILT = [n for n in scenes.list_scenes() if n != FULL_SCENE]


@pytest.fixture(scope="module")
def built_scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("built")
    code = ("import sys; from pathlib import Path; from gvae_core.scenes.build import generate\n"
            "for name in sys.argv[2:]:\n    generate(name, Path(sys.argv[1]) / name, render=False, log=print)")
    subprocess.run([sys.executable, "-c", code, str(root), *BUILT], check=True, capture_output=True)
    return root


@requires_bpy
@pytest.mark.parametrize("name", BUILT)
def test_every_scene_builds_and_fits_the_views(name, built_scenes):
    """Each scene without rendering (cheap): ground truth written, object inside every view."""
    out = built_scenes / name
    verts, tris = _read_mesh(out / "mesh.ply")
    assert len(tris) > 1000 and np.isfinite(verts).all()
    assert np.linalg.norm(verts, axis=1).max() <= cameras.OBJECT_RADIUS + 1e-5
    gt = np.load(out / "gt_points.npy")
    assert len(gt) > 1000
    for split in ("train", "test"):
        frames = json.loads((out / f"transforms_{split}.json").read_text())["frames"]
        for frame in frames:
            cam = Camera.from_blender_c2w(frame["transform_matrix"], cameras.CAMERA_ANGLE_X, 64, 64)
            uv, z = cam.project(verts)
            assert (z > 0).all() and (uv >= 0).all() and (uv < 64).all()
