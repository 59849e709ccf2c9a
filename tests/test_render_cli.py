"""`gvae render`: PNGs from a PLY, with orbit or transforms cameras, and clear errors."""

from __future__ import annotations

import json
import math

import numpy as np
from PIL import Image

from gvae_core import Camera, GaussianCloud
from gvae_core.cli import main
from gvae_core.ply import write_ply
from gvae_core.rendering import render


def _cloud(n=40, seed=0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(means=rng.normal(0, 0.4, (n, 3)).astype(np.float32),
                         scales=np.full((n, 3), -2.5, np.float32),
                         quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                         opacities=np.full(n, 2.0, np.float32), sh_dc=rng.normal(0, 1, (n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.2, (n, 3, 3)).astype(np.float32))


def test_render_orbit(tmp_path, capsys):
    ply = write_ply(_cloud(), tmp_path / "c.ply")
    assert main(["render", str(ply), "--out", str(tmp_path / "out"), "--orbit", "3", "--height", "24",
                 "--background", "1,1,1"]) == 0
    files = sorted((tmp_path / "out").glob("*.png"))
    assert len(files) == 3
    img = np.asarray(Image.open(files[0]))
    assert img.shape == (24, 24, 3)
    assert (img == 255).all(-1).any() and (img < 250).any()  # white background and some splats


def test_render_transforms_matches_render(tmp_path):
    cloud = _cloud(seed=1)
    ply = write_ply(cloud, tmp_path / "c.ply")
    cam = Camera.look_at((2.0, 0.5, 1.0), (0, 0, 0), width=32, height=20, fov_x=math.radians(50))
    meta = {"camera_angle_x": math.radians(50), "w": 32, "h": 20,
            "frames": [{"file_path": "./test/r_0", "transform_matrix": cam.to_blender_c2w().tolist()}]}
    (tmp_path / "transforms_test.json").write_text(json.dumps(meta))
    assert main(["render", str(ply), "--out", str(tmp_path / "o"), "--transforms",
                 str(tmp_path / "transforms_test.json")]) == 0
    (png,) = (tmp_path / "o").glob("*.png")
    got = np.asarray(Image.open(png)).astype(np.float64) / 255
    want = render(cloud, cam).image.clamp(0, 1).numpy()
    assert np.abs(got - want).max() <= 1 / 255 + 1e-6


def test_render_cli_errors(tmp_path, capsys):
    assert main(["render", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.ply" in capsys.readouterr().err
    ply = write_ply(_cloud(), tmp_path / "c.ply")
    bad = tmp_path / "t.json"
    bad.write_text("{\"frames\": []}")
    assert main(["render", str(ply), "--out", str(tmp_path / "o"), "--transforms", str(bad)]) == 2
    assert "t.json" in capsys.readouterr().err
    assert main(["render", str(ply), "--out", str(tmp_path / "o"), "--background", "red"]) == 2
    assert not (tmp_path / "o").exists()  # nothing written on bad input
