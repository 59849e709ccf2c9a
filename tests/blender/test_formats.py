"""File > Import of .splat, .spz, compressed PLY and SOG files and File > Export to .spz and .sog, in real
Blender through the installed extension zip, without Pillow (Blender has none), as a user has it (see
_scenarios.py: scenario_formats)."""

from __future__ import annotations

import warnings

import numpy as np

from gvae_core.cloud import GaussianCloud
from gvae_core.formats import read_splat_file, write_compressed_ply, write_sog, write_splat, write_spz
from gvae_core.formats.sog import morton_order
from gvae_core.ply import read_ply, write_ply
from tests.blender.conftest import run_scenario
from tests.conftest import requires_bpy
from tests.test_formats import quat_error, quiet
from tests.test_ply import reference_rows, write_with_plyfile

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
                 "compressed": write_compressed_ply(cloud, data / "supersplat.ply"),
                 "sog": write_sog(cloud, data / "playcanvas.sog")}
    sog_folder = write_sog(cloud, tmp_path / "scene" / "meta.json")
    # splat-transform's PLY of fully opaque and transparent Gaussians: every row is kept
    cols = reference_rows(cloud)
    cols["opacity"] = cols["opacity"].copy()
    cols["opacity"][[0, 5, 9]] = [np.inf, -np.inf, np.inf]
    files["infinite"] = write_with_plyfile(data / "opaque.ply", cols)
    bad = {"truncated_spz": tmp_path / "cut.spz", "partial_splat": tmp_path / "cut.splat",
           "truncated_compressed": tmp_path / "cut.ply", "truncated_sog": tmp_path / "cut.sog"}
    bad["truncated_spz"].write_bytes(files["spz"].read_bytes()[:-9])
    bad["partial_splat"].write_bytes(files["splat"].read_bytes()[:-7])
    bad["truncated_compressed"].write_bytes(files["compressed"].read_bytes()[:-100])
    bad["truncated_sog"].write_bytes(files["sog"].read_bytes()[:-2000])
    res = run_scenario("formats", tmp_path, extension_zip, block_torch=True, block_pillow=True,
                       files={k: str(v) for k, v in files.items()}, bad={k: str(v) for k, v in bad.items()},
                       sog_folder=str(sog_folder), export_spz=str(tmp_path / "out.spz"),
                       export_ply=str(tmp_path / "out.ply"), export_sog=str(tmp_path / "out.sog"))

    # Each format makes one object whose vertices and attributes are what gvae_core reads from the file
    # (SOG: Blender's image reader gives the bytes Pillow gives).
    files["sog_folder"] = sog_folder
    assert res["imported"]["sog_folder"]["object"] == "scene"
    for name, path in files.items():
        got = res["imported"][name]
        assert got["vertices"] == len(cloud) and got["new"] == [got["object"]]
        want = quiet(read_splat_file, path)
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

    opaque = np.load(tmp_path / "formats.json.infinite.npz")["opacity"]
    assert opaque[0] == opaque[9] == 50 and opaque[5] == -50
    assert "read 3 opacity logit(s) of +-inf" in res["_output"]

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
    # .sog -> Blender -> .sog (through Blender's WebP writer): the object's values again, within the
    # format's quantisation (rows in Morton order again, codebooks of the decoded values: exact)
    assert res["export_sog"] == ["FINISHED"] and res["images_left"] == [], res["images"]
    exported = np.load(tmp_path / "formats.json.exported_sog_object.npz")
    obj = GaussianCloud(means=exported["position"], opacities=exported["opacity"],
                        scales=np.stack([exported[f"scale_{i}"] for i in range(3)], 1),
                        quats=np.stack([exported[f"rot_{i}"] for i in range(4)], 1),
                        sh_dc=np.stack([exported[f"f_dc_{i}"] for i in range(3)], 1),
                        sh_rest=np.stack([exported[f"f_rest_{i}"] for i in range(24)], 1).reshape(-1, 3, 8)
                        .transpose(0, 2, 1))
    obj = obj.select(morton_order(obj.means))
    again = read_splat_file(tmp_path / "out.sog")  # with Pillow
    np.testing.assert_allclose(again.means, obj.means, rtol=1e-4, atol=1e-4)
    for name in ("scales", "opacities", "sh_dc"):
        np.testing.assert_allclose(getattr(again, name), getattr(obj, name), rtol=1e-6, atol=1e-6, err_msg=name)
    assert quat_error(again.quats, obj.quats).max() < 2 / 255
    assert np.abs(again.sh_rest - obj.sh_rest).mean() < 0.05 and again.sh_degree == 2

    # All the files of data/ at once (the folder's meta.json is elsewhere), and what Blender offers.
    assert res["multi_new"] == len(files) - 1 == 6
    assert set(res["file_handler_extensions"].split(";")) == {".ply", ".splat", ".spz", ".sog", ".json"}
    assert set(res["import_filter"].split(";")) == {"*.ply", "*.splat", "*.spz", "*.sog", "*meta.json"}
    assert res["torch_imported"] is False
