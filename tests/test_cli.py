"""The `gvae` command line: subcommands, help, info, demo; the example cloud."""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from gvae_core import read_ply, write_ply
from gvae_core.antialias import with_dilation_3d
from gvae_core.cli import build_parser, demo, main
from gvae_core.examples import example_cloud
from gvae_core.detail import DetailModel, save_detail
from gvae_core.rendering import render


def subcommands() -> list[str]:
    """The subcommand names the parser knows (a module may name its command differently)."""
    actions = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return sorted(actions[0].choices)


def test_every_subcommand_has_help(capsys):
    names = subcommands()
    assert {"info", "demo"} <= set(names)
    for name in names:
        with pytest.raises(SystemExit) as exit_:
            main([name, "--help"])
        assert exit_.value.code == 0, name
        assert f"usage: gvae {name}" in capsys.readouterr().out


def test_console_script_and_module_are_the_same_cli():
    script = Path(sys.executable).with_name("gvae")
    assert script.exists(), "the `gvae` console script is not installed (pip install -e .)"
    by_module = subprocess.run([sys.executable, "-m", "gvae_core", "--help"], capture_output=True,
                               text=True, timeout=120)
    by_script = subprocess.run([str(script), "--help"], capture_output=True, text=True, timeout=120)
    assert by_module.returncode == by_script.returncode == 0
    assert by_module.stdout == by_script.stdout
    for name in subcommands():
        assert name in by_module.stdout


def test_example_cloud_is_deterministic_and_sound():
    a, b = example_cloud(), example_cloud()
    assert len(a) == 4096 and a.sh_degree == 3
    for name, value in a.arrays().items():
        np.testing.assert_array_equal(value, getattr(b, name))
        assert value.dtype == np.float32
    assert a.validate().ok
    assert not np.array_equal(example_cloud(seed=1).means, a.means)
    # A torus: every centre is `tube` from the ring of radius 1 in the z = 0 plane.
    ring = np.hypot(a.means[:, 0], a.means[:, 1])
    np.testing.assert_allclose(np.hypot(ring - 1.0, a.means[:, 2]), 0.35, atol=1e-5)


def test_info(tmp_path, capsys):
    cloud = example_cloud(300).replace(extra={"gvae_id": np.arange(300, dtype=np.int64)})
    cloud.quats[7] = 0
    path = write_ply(cloud, tmp_path / "c.ply")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Gaussians: 300" in out and "SH degree: 3" in out
    lo, hi = cloud.means.min(0), cloud.means.max(0)
    assert f"bounding box: min ({lo[0]:.4g}, {lo[1]:.4g}, {lo[2]:.4g}), max ({hi[0]:.4g}," in out
    assert "opacity (sigmoid)" in out and "largest scale" in out
    assert "gvae_id (int64)" in out
    assert "zero quaternions: 1 row(s) [7]" in out and "PROBLEMS" in out


def test_info_on_bad_input_is_one_clear_line(tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "missing required vertex properties" in err[0]
    assert main(["info", str(tmp_path / "nope.ply")]) == 2
    cloud_path = write_ply(example_cloud(20), tmp_path / "nan.ply")
    data = bytearray(cloud_path.read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start:start + 4] = np.float32(np.nan).tobytes()  # x of the first Gaussian
    cloud_path.write_bytes(bytes(data))
    assert main(["info", str(cloud_path)]) == 2
    assert "rows [0]" in capsys.readouterr().err
    assert main(["info", "--sanitize", str(cloud_path)]) == 0
    out = capsys.readouterr().out
    assert "Gaussians: 19" in out and "  read: " in out and "dropped 1 of 20 Gaussians" in out


def test_demo_without_a_trained_example_writes_then_reuses_the_example(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(demo, "trained_example", lambda: None)  # the refine path is tested with it
    monkeypatch.chdir(tmp_path)
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    path = tmp_path / "examples" / "example.ply"
    assert "wrote the example cloud" in out and str(path) in out and "Gaussians: 4096" in out
    assert len(read_ply(path)) == 4096
    stamp = path.stat().st_mtime_ns
    assert main(["demo"]) == 0
    assert "using the existing example" in capsys.readouterr().out
    assert path.stat().st_mtime_ns == stamp


def test_demo_refines_the_trained_example_without_and_with_its_images(tmp_path, capsys, monkeypatch):
    """The demo's main path on a small stand-in for the bundled example: a trained cloud, its training
    images and ground-truth test views at twice their resolution (the synthetic capture of
    tests/test_superres.py), an untrained detail model (which changes nothing: its outputs start at
    zero); the fit to the images does change the picture at 2x and keeps the one at 1x."""
    from tests.test_superres import H, _capture, _write_capture  # noqa: PLC0415

    truth, trained, views = _capture(n_views=4, n=200)
    folder = _write_capture(views, tmp_path / "example")
    cams = [c.scaled(2 * H) for c in views.cameras[:3]]
    sharp = with_dilation_3d(truth, cams)
    (folder / "test").mkdir()
    frames = []
    for i, cam in enumerate(cams):
        img = render(sharp, cam, background=(1.0, 1.0, 1.0)).image.clamp(0, 1).numpy()
        Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(folder / "test" / f"r_{i}.png")
        frames.append({"file_path": f"./test/r_{i}", "transform_matrix": cam.to_blender_c2w().tolist()})
    (folder / "transforms_test.json").write_text(json.dumps({"camera_angle_x": cams[0].fov_x, "frames": frames}))
    write_ply(trained, folder / "scene.ply")
    save_detail(DetailModel(), tmp_path / "model")
    monkeypatch.setenv("GVAE_MODEL_DIR", str(tmp_path / "model"))
    monkeypatch.setattr(demo, "trained_example", lambda: folder)
    assert main(["demo", "--results", str(tmp_path / "out"), "--fit-steps", "8"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ")]
    assert rows[0] == "| view | unrefined | detail model (no images) | change | with the images | change |"
    assert len(rows) == 1 + 3 + 1  # head, 3 views, mean
    before, detail, fitted = (float(rows[-1].split(" | ")[k].split()[0]) for k in (1, 2, 4))
    assert 0 < before < 60 and detail == before and fitted != before
    assert "both refined clouds draw as the unrefined one: PSNR between them 100.0 dB" in out
    assert len(read_ply(tmp_path / "out" / "refined.ply")) == 200
    assert len(read_ply(tmp_path / "out" / "refined_with_images.ply")) >= 200
    sheet = Image.open(tmp_path / "out" / "comparison.png")
    crop = demo.ZOOM * int(demo.CROP * 2 * H)
    assert sheet.size == (4 * 2 * H + 4 * crop, 3 * max(2 * H, crop))  # a row per view: 4 panels, 4 crops
