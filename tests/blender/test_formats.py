"""File > Import of .splat, .spz, compressed PLY, SOG and glTF files and File > Export to .spz, .sog and
.glb, in real Blender through the installed extension zip, without Pillow (Blender has none), as a user
has it (see _scenarios.py: scenario_formats); an ordinary .glb handed to Blender's own glTF importer."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gvae_core.cloud import GaussianCloud
from gvae_core.formats import read_splat_file, write_compressed_ply, write_gltf, write_sog, write_splat, write_spz
from gvae_core.formats.sog import morton_order
from gvae_core.ply import read_ply, write_ply
from tests.blender.conftest import blender_versions, run_scenario
from tests.conftest import requires_bpy
from tests.test_formats import quat_error, quiet, sigmoid
from tests.test_gltf import Builder
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
                 "sog": write_sog(cloud, data / "playcanvas.sog"), "glb": write_gltf(cloud, data / "khronos.glb")}
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
                       export_ply=str(tmp_path / "out.ply"), export_sog=str(tmp_path / "out.sog"),
                       export_glb=str(tmp_path / "out.glb"), plain_glb=str(plain_glb(tmp_path / "plain.glb")))

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
    assert res["multi_new"] == len(files) - 1 == 7
    assert set(res["file_handler_extensions"].split(";")) == {".ply", ".splat", ".spz", ".sog", ".json", ".glb",
                                                              ".gltf"}
    assert set(res["import_filter"].split(";")) == {"*.ply", "*.splat", "*.spz", "*.sog", "*meta.json", "*.glb",
                                                    "*.gltf"}
    assert res["torch_imported"] is False
    # .glb -> Blender -> .glb: the object's values again (scales and opacities through exp / sigmoid)
    assert res["export_glb"] == ["FINISHED"]
    before, after = read_splat_file(files["glb"]), read_splat_file(tmp_path / "out.glb")
    for name in ("means", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(after, name), getattr(before, name), err_msg=name)
    assert quat_error(after.quats, before.quats).max() <= 1e-7  # (unit already: normalised once more)
    assert np.abs(after.scales - before.scales).max() <= 2e-7 and \
        np.abs(sigmoid(after.opacities) - sigmoid(before.opacities)).max() <= 1e-7
    # an ordinary glTF file (a triangle, no splats) is imported by Blender's glTF importer, as a mesh
    assert res["plain_glb"] == ["FINISHED"] and [t for _, t, _ in res["plain_new"]] == ["MESH"]
    assert res["plain_new"][0][2] == 3 and "no Gaussian splats, imported with Blender's glTF 2.0" in res["_output"]
    if not res["native_available"]:  # Blender before 5.3 draws no splats itself: say so, change nothing
        refused = res["native_refused"]
        assert "has no Gaussian-splat point clouds (5.3 and later)" in refused["error"] and refused["unchanged"]


def plain_glb(path):
    """An ordinary glTF file: one triangle, no splats."""
    b = Builder()
    b.doc["extensionsUsed"] = []
    tri = b.accessor([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "VEC3", min=[0, 0, 0], max=[1, 1, 0])
    b.doc["meshes"].append({"primitives": [{"attributes": {"POSITION": tri}}]})
    b.doc["nodes"].append({"mesh": 0, "name": "triangle"})
    b.doc["scenes"][0]["nodes"].append(0)
    return b.glb(path)


def test_blender_gaussian_splats(extension_zip, tmp_path):
    """Blender 5.3+ draws splats itself: Import makes the point cloud Blender's own PLY importer makes
    from the same file (extras kept as attributes, as Blender does), Export writes such objects (ours and Blender's)
    back: positions and SH exactly, scales and opacities through exp / sigmoid."""
    version = blender_versions()[1]
    if version < (5, 3):
        pytest.skip(f"Blender {'.'.join(map(str, version))} has no Gaussian-splat point clouds (5.3 and later); "
                    "make test-blender-versions runs this with bpy 5.3")
    cloud = make_cloud(seed=3)
    cloud.extra["filter_3D"] = np.linspace(0.01, 0.02, len(cloud)).astype(np.float32)
    ply = write_ply(cloud, tmp_path / "ref.ply")
    plain = cloud.replace(extra={})
    glb = write_gltf(plain, tmp_path / "ref.glb")
    res = run_scenario("native", tmp_path, extension_zip, block_torch=True, block_pillow=True, ply=str(ply),
                       glb=str(glb), export_ply=str(tmp_path / "ours.ply"), export_glb=str(tmp_path / "blenders.glb"))
    assert res["import"] == ["FINISHED"] and res["new"] == ["ref"]
    for key in ("ours", "blender", "from_glb"):
        assert res[key] == {"type": "POINTCLOUD", "data_type": "GAUSSIAN_SPLAT", "points": len(cloud)}, key
    ours, blenders = (np.load(tmp_path / f"native.json.{k}.npz") for k in ("ours", "blender"))
    assert set(blenders.files) == set(ours.files) and "filter_3D" in ours.files  # (Blender keeps extras too)
    for name in blenders.files:
        np.testing.assert_allclose(ours[name], blenders[name], rtol=1e-6, atol=1e-7, err_msg=name)
    np.testing.assert_array_equal(ours["position"], cloud.means)
    np.testing.assert_array_equal(ours["radiance__sh_7"], cloud.sh_rest[:, 7])
    np.testing.assert_array_equal(ours["filter_3D"], cloud.extra["filter_3D"])
    assert res["poll"] == [True, True] and res["export"] == [["FINISHED"], ["FINISHED"]]
    for path, extra in ((tmp_path / "ours.ply", True), (tmp_path / "blenders.glb", False)):
        back = quiet(read_splat_file, path)
        for name in ("means", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name), err_msg=f"{path.name} {name}")
        assert quat_error(back.quats, cloud.quats).max() <= 1e-6
        assert np.abs(back.scales - cloud.scales).max() <= 1e-6
        assert np.abs(sigmoid(back.opacities) - sigmoid(cloud.opacities)).max() <= 1e-6
        assert ("filter_3D" in back.extra) == extra
    from_glb = np.load(tmp_path / "native.json.from_glb.npz")
    np.testing.assert_array_equal(from_glb["position"], cloud.means)
