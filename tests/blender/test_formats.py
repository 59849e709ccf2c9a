"""File > Import of .splat, .spz and compressed PLY files and File > Export to .spz, in real Blender
through the installed extension zip (see _scenarios.py: scenario_formats)."""

from __future__ import annotations

import warnings

import numpy as np

from gvae_core.cloud import GaussianCloud
from gvae_core.formats import read_splat_file, write_compressed_ply, write_splat, write_spz
from gvae_core.ply import read_ply, write_ply
from tests.blender.conftest import run_scenario
from tests.conftest import requires_bpy

pytestmark = requires_bpy


def make_cloud(n: int = 300, seed: int = 0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    return GaussianCloud(means=f(n, 3), scales=f(n, 3) - 3, quats=f(n, 4), opacities=f(n),
                         sh_dc=np.clip(f(n, 3), -1.5, 1.5), sh_rest=f(n, 8, 3) * 0.2)


def test_import_every_format_and_export_spz(extension_zip, tmp_path):
    cloud = make_cloud()
    data = tmp_path / "data"
    data.mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        files = {"ply": write_ply(cloud, data / "ref.ply"), "splat": write_splat(cloud, data / "web.splat"),
                 "spz": write_spz(cloud, data / "niantic.spz"),
                 "compressed": write_compressed_ply(cloud, data / "supersplat.ply")}
    bad = {"truncated_spz": tmp_path / "cut.spz", "partial_splat": tmp_path / "cut.splat",
           "truncated_compressed": tmp_path / "cut.ply"}
    bad["truncated_spz"].write_bytes(files["spz"].read_bytes()[:-9])
    bad["partial_splat"].write_bytes(files["splat"].read_bytes()[:-7])
    bad["truncated_compressed"].write_bytes(files["compressed"].read_bytes()[:-100])
    res = run_scenario("formats", tmp_path, extension_zip, block_torch=True,
                       files={k: str(v) for k, v in files.items()}, bad={k: str(v) for k, v in bad.items()},
                       export_spz=str(tmp_path / "out.spz"), export_ply=str(tmp_path / "out.ply"))

    # Each format makes one object whose vertices and attributes are what gvae_core reads from the file.
    for name, path in files.items():
        got = res["imported"][name]
        assert got["vertices"] == len(cloud) and got["new"] == [got["object"]]
        want = read_splat_file(path)
        attrs = np.load(tmp_path / f"formats.json.{name}.npz")
        np.testing.assert_array_equal(attrs["position"], want.means)
        np.testing.assert_array_equal(attrs["opacity"], want.opacities)
        for i in range(3):
            np.testing.assert_array_equal(attrs[f"scale_{i}"], want.scales[:, i])
            np.testing.assert_array_equal(attrs[f"f_dc_{i}"], want.sh_dc[:, i])
        for i in range(4):
            np.testing.assert_array_equal(attrs[f"rot_{i}"], want.quats[:, i])
        k = want.sh_rest.shape[1]
        assert sum(1 for a in attrs.files if a.startswith("f_rest_")) == 3 * k
        if k:
            np.testing.assert_array_equal(attrs["f_rest_1"], want.sh_rest[:, 1, 0])  # channel-major names

    # .spz -> Blender -> .spz keeps every value the file held (rotations renormalised, within the step)
    assert res["export_spz_poll"] and res["export_spz"] == ["FINISHED"] and res["export_ply"] == ["FINISHED"]
    before, after = read_splat_file(files["spz"]), read_splat_file(tmp_path / "out.spz")
    assert (tmp_path / "out.spz").read_bytes()[:2] == b"\x1f\x8b"
    for name in ("means", "scales", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name), err_msg=name)
    assert np.abs(np.abs((after.quats * before.quats).sum(1)) - 1).max() < 1e-5
    np.testing.assert_array_equal(read_ply(tmp_path / "out.ply").means, before.means)

    # Bad files of each format: a clear error naming the file, and the scene unchanged.
    for name, path in bad.items():
        failure = res["bad"][name]
        assert failure["error"] and str(path) in failure["error"] and failure["unchanged"], (name, failure)
    assert res["multi_new"] == len(files)
    assert set(res["file_handler_extensions"].split(";")) == {".ply", ".splat", ".spz"}
    assert set(res["import_filter"].split(";")) == {"*.ply", "*.splat", "*.spz"}
    assert res["torch_imported"] is False
