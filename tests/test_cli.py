"""The `gvae` command line: subcommands, help, info, demo; the example cloud."""

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from gvae_core import read_ply, write_ply
from gvae_core.cli import build_parser, demo, main
from gvae_core.examples import example_cloud
from gvae_core.detail import DetailModel, save_detail
from tests.test_experiment import _scene


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


def test_demo_refines_the_trained_example_and_compares_at_2x(tmp_path, capsys, monkeypatch):
    """The demo's main path on a small stand-in for the bundled example: a cloud and ground-truth
    test views at twice its resolution (a ball rendered by our renderer), an untrained detail model
    (which changes nothing: its outputs start at zero)."""
    folder = _scene(tmp_path / "example", size=40)
    cloud = example_cloud(400)
    write_ply(cloud.replace(means=cloud.means * 0.4), folder / "scene.ply")
    save_detail(DetailModel(), tmp_path / "model")
    monkeypatch.setenv("GVAE_MODEL_DIR", str(tmp_path / "model"))
    monkeypatch.setattr(demo, "trained_example", lambda: folder)
    assert main(["demo", "--results", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ")]
    assert rows[0] == "| view | unrefined | refined | change | model, unchecked | change |"
    assert len(rows) == 1 + 3 + 1  # head, 3 views, mean
    before, after, unchecked = (float(rows[-1].split(" | ")[k].split()[0]) for k in (1, 2, 4))
    assert 0 < before < 60 and after == before and unchecked == before
    assert "refined cloud draws as the unrefined one: PSNR between the two 100.0 dB" in out
    refined = read_ply(tmp_path / "out" / "refined.ply")
    assert len(refined) == 400
    sheet = Image.open(tmp_path / "out" / "comparison.png")
    crop = demo.ZOOM * int(demo.CROP * 40)
    assert sheet.size == (4 * 40 + 4 * crop, 3 * max(40, crop))  # a row per view: 4 panels, 4 crops
