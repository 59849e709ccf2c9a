"""The `gvae` command line: subcommands, help, info, demo; the example cloud."""

import argparse
import json
import subprocess
import sys
import warnings
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
    picture = Image.open(tmp_path / "out" / "demo.png")  # the README's: the first view, panels over crops
    assert picture.size == (4 * max(2 * H, crop), 2 * H + crop) and picture.mode == "P"


#: Run in a fresh interpreter: each `gvae` call given, then fail when torch or Numba got imported.
_LIGHT = """
import sys
from gvae_core.cli import main
for argv in {calls!r}:
    try:
        main(argv)
    except SystemExit as exc:
        assert exc.code in (0, None), (argv, exc.code)
    heavy = [m for m in ("torch", "numba") if m in sys.modules]
    assert not heavy, f"gvae {{' '.join(argv)}} imported {{heavy}}"
"""


def test_commands_that_read_or_convert_files_import_neither_torch_nor_numba(tmp_path):
    from gvae_core.formats import write_compressed_ply  # noqa: PLC0415

    ply = write_ply(example_cloud(300), tmp_path / "c.ply")
    compressed = write_compressed_ply(example_cloud(300), tmp_path / "c.compressed.ply")
    calls = [["--help"], ["info", str(ply)], ["info", str(compressed)], ["list-scenes"]]
    calls += [["convert", str(ply), str(tmp_path / f"out{ext}")] for ext in (".compressed.ply", ".spz", ".sog",
                                                                             ".splat", ".glb")]
    calls += [["convert", str(tmp_path / "out.sog"), str(tmp_path / "back.ply")]]
    for name in subcommands():
        calls.append([name, "--help"])
    proc = subprocess.run([sys.executable, "-c", _LIGHT.format(calls=calls)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert len(read_ply(tmp_path / "back.ply")) == 300


def test_each_subcommand_is_registered_by_the_module_commands_names():
    """`gvae COMMAND` imports only `COMMANDS[COMMAND]`: that module must register it."""
    from gvae_core.cli import COMMAND_MODULES, COMMANDS  # noqa: PLC0415

    assert sorted(COMMANDS) == subcommands()
    assert set(COMMANDS.values()) == set(COMMAND_MODULES)
    for name, module in COMMANDS.items():
        actions = [a for a in build_parser(name)._actions if isinstance(a, argparse._SubParsersAction)]
        assert name in actions[0].choices, (name, module)


def test_report_profiles_are_the_experiment_protocols():
    from gvae_core.cli.report import PROFILES  # noqa: PLC0415
    from gvae_core.experiment import PROTOCOLS  # noqa: PLC0415

    assert PROFILES == tuple(PROTOCOLS)


def test_every_option_states_its_default():
    """Every optional argument of every subcommand says in its --help what it is when not given
    (flags are off when not given, and one of a required group is always given)."""
    missing = []
    for name in subcommands():
        sub = next(a for a in build_parser(name)._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[name]
        one_required = {a for g in parser._mutually_exclusive_groups if g.required for a in g._group_actions}
        for action in parser._actions:
            if not action.option_strings or action.required or action in one_required or isinstance(
                    action, (argparse._HelpAction, argparse._StoreTrueAction, argparse._StoreFalseAction)):
                continue
            if "default" not in (action.help or ""):
                missing.append(f"gvae {name} {action.option_strings[-1]}")
    assert not missing, "--help does not state the default of:\n" + "\n".join(missing)


def test_train_flags_are_made_from_the_configuration(capsys, monkeypatch):
    """Every TrainConfig field has a flag whose help is the field's and states its default and each
    profile's value where it differs; the flags given become the configuration."""
    import dataclasses  # noqa: PLC0415

    from gvae_core.cli.fields import flag_of  # noqa: PLC0415
    from gvae_core.cli.train import config_of  # noqa: PLC0415
    from gvae_core.train import PROFILES, TrainConfig  # noqa: PLC0415

    monkeypatch.setenv("COLUMNS", "100000")  # (no line breaks inside a help text)
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for f in dataclasses.fields(TrainConfig):
        assert flag_of(f) in text and " ".join(f.metadata["help"].split()) in text, f.name
    for name in PROFILES:
        c = TrainConfig.profile(name)
        for numbers in (c.resolutions, c.iterations):
            assert " ".join(map(str, numbers)) in text, (name, numbers)
    assert "(default: 300 300 1000; tiny: 200 150 150; legacy: 600 400 400; full: 7000 7000 7000 30000)" in text
    assert "(default: auto; full: random)" in text
    parse = build_parser("train").parse_args
    args = parse(["train", "x", "--out", "o", "--image-height", "240", "--gaussians-per-pixel", "0", "--iterations",
                  "50", "--patience", "900", "--no-carry-optimizer"])
    config = config_of(args)
    assert config.resolutions == (120, 180, 240) and config.iterations == (50, 50, 50) and not config.converge
    assert config.gaussians_per_pixel is None and config.patience == 900 and not config.carry_optimizer
    assert config_of(parse(["train", "x", "--profile", "tiny"])) == TrainConfig.profile("tiny")
    counted = config_of(parse(["train", "x", "--iterations", "150", "150", "1000", "--converge"]))
    assert counted.iterations == (150, 150, 1000) and counted.converge  # (the last count then the planned one)


def test_train_refine_and_compact_warn_nothing_from_the_project(tmp_path, capsys):
    """`gvae train`, `refine` (without and with the images) and `compact`, tiny, on the bundled
    example's images, with every warning raised in the project's own code an error."""
    scene = Path(__file__).resolve().parents[1] / "examples" / "trained"
    run = tmp_path / "run"
    with warnings.catch_warnings():
        warnings.filterwarnings("error", module=r"gvae_core(\.|$)")
        assert main(["train", str(scene), "--out", str(run), "--resolutions", "16", "24", "--iterations", "40",
                     "--init-count", "500", "--threads", "1"]) == 0
        stage = run / "stage_1.ply"
        assert main(["refine", str(stage), str(tmp_path / "r.ply"), "--lineage", str(run / "lineage.npz")]) == 0
        assert main(["refine", str(stage), str(tmp_path / "ri.ply"), "--images", str(scene), "--fit-steps", "4"]) == 0
        assert main(["compact", str(stage), str(tmp_path / "c.ply"), "--keep", "0.5", "--distill", "5"]) == 0
    out = capsys.readouterr()
    assert "Warning" not in out.err, out.err


def test_a_warning_is_one_line_without_the_source(tmp_path):
    """As a user runs it: Python shows the warning (no test harness records it)."""
    ply = write_ply(example_cloud(50), tmp_path / "c.ply")  # SH degree 3: a .splat keeps none of it
    code = ("import sys, warnings\n"
            "from gvae_core.cli import main\n"
            "shown = warnings.formatwarning\n"
            f"code = main(['convert', {str(ply)!r}, {str(tmp_path / 'c.splat')!r}])\n"
            "warnings.warn('after the call')\n"
            "sys.exit(code if warnings.formatwarning is shown else 3)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    first, *rest = proc.stderr.splitlines()
    assert first.startswith("warning: ") and ".splat holds no view-dependent colour" in first
    assert "UserWarning" not in first and ".py:" not in first
    assert rest and "UserWarning: after the call" in rest[0]  # Python's own format again after the call


def test_warnings_under_main_can_still_be_recorded(tmp_path):
    ply = write_ply(example_cloud(50), tmp_path / "c.ply")
    with pytest.warns(UserWarning, match="holds no view-dependent colour"):
        assert main(["convert", str(ply), str(tmp_path / "c.splat")]) == 0


def test_running_out_of_memory_midway_is_an_error_line(tmp_path, capsys, monkeypatch):
    from gvae_core.cli import info  # noqa: PLC0415

    def exhausted(args):
        raise MemoryError("Unable to allocate 9.31 GiB for an array")

    monkeypatch.setattr(info, "run", exhausted)
    assert main(["info", str(tmp_path / "any.ply")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("gvae info: error: out of memory (Unable to allocate 9.31 GiB") and "Traceback" not in err
