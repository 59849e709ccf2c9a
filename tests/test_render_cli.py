"""`gvae render`: PNGs from a PLY, with orbit or transforms cameras, and clear errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import with_dilation_3d, with_filter_3d
from gvae_core.cli import main
from gvae_core.ply import write_ply
from gvae_core.rendering import RenderSettings, render


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


def test_render_with_training_cameras_or_resolution(tmp_path, capsys):
    """A PLY without stored sizes: --train-cameras / --train-resolution give it the size of its
    training cameras that --trained calls for, which the auto mode then uses."""
    cloud = _cloud(seed=2)
    ply = write_ply(cloud, tmp_path / "c.ply")
    cam = Camera.look_at((2.0, 0.5, 1.0), (0, 0, 0), width=32, height=32, fov_x=math.radians(50))
    train = Camera.look_at((1.0, 1.5, 0.5), (0, 0, 0), width=16, height=16, fov_x=math.radians(50))
    for name, c in (("transforms_test.json", cam), ("transforms_train.json", train)):
        meta = {"camera_angle_x": math.radians(50), "w": c.width, "h": c.height,
                "frames": [{"file_path": "./x/r_0", "transform_matrix": c.to_blender_c2w().tolist()}]}
        (tmp_path / name).write_text(json.dumps(meta))
    auto = RenderSettings(antialias="auto")
    cases = {  # extra arguments -> the cloud the PNG must show in the auto mode, and the key it has
        "cams": (["--train-cameras", str(tmp_path / "transforms_train.json")], with_dilation_3d(cloud, [train])),
        "cams_res": (["--train-cameras", str(tmp_path / "transforms_train.json"), "--train-resolution", "8"],
                     with_dilation_3d(cloud, [train], resolution=8)),
        "res": (["--train-resolution", "16"], with_dilation_3d(cloud, [cam], resolution=16)),
        "mip": (["--train-resolution", "16", "--trained", "mip"], with_filter_3d(cloud, [cam], resolution=16)),
    }
    for tag, (extra, want_cloud) in cases.items():
        assert main(["render", str(ply), "--out", str(tmp_path / tag), "--transforms",
                     str(tmp_path / "transforms_test.json"), "--antialias", "auto", *extra]) == 0
        (key,) = set(want_cloud.extra)
        assert f"{key} from 1 training camera" in capsys.readouterr().out
        (png,) = (tmp_path / tag).glob("*.png")
        got = np.asarray(Image.open(png)).astype(np.float64) / 255
        want = render(want_cloud, cam, settings=auto).image.clamp(0, 1).numpy()
        assert np.abs(got - want).max() <= 1 / 255 + 1e-6, tag
    # the filter matters here: the classic render differs
    classic = render(cloud, cam).image.clamp(0, 1).numpy()
    assert np.abs(got - classic).max() > 3 / 255
    assert main(["render", str(ply), "--out", str(tmp_path / "o"), "--train-resolution", "0"]) == 2
    assert "--train-resolution" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", str(ply), "--out", str(tmp_path / "o"), "--antialias", "msaa"])


def test_a_render_too_large_for_memory_is_refused_before_any_work(tmp_path, capsys):
    ply = write_ply(_cloud(), tmp_path / "c.ply")
    out = tmp_path / "huge"
    assert main(["render", str(ply), "--out", str(out), "--orbit", "2", "--height", "1000000"]) == 2
    err = capsys.readouterr().err
    assert "rendering 40 Gaussians at 1000000x1000000 px needs about" in err and "GiB is available" in err
    fits = int(err.split("--height ")[1].split(")")[0])
    assert 1000 < fits < 1000000
    assert not out.exists()  # nothing written
