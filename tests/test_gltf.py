"""glTF splats (KHR_gaussian_splatting, .glb and .gltf) and the affine moves of `gvae_core.transform`.

Files laid out by hand from the extension's text (JSON and binary chunks packed here, not by the
writer) are read to the values the text defines: float and normalised integer accessors, byteStride,
sparse accessors, data URIs, node transforms, the SPZ companion extension, splat-transform's files
before 2.7.0; what the writer writes is read back here by a plain parse of its JSON and bytes. The
frame change is checked against the renderer's SH colours. splat-transform and Khronos's validator
themselves are in test_splat_transform.py."""

from __future__ import annotations

import base64
import json
import math
import struct
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings

from tests.corruption import EDITS, corrupt, read_or_refuse
from tests.test_formats import assert_no_leftovers, make_cloud, quiet, sigmoid

from gvae_core import GaussianCloud, PlyError, read_splat_file, write_ply
from gvae_core.cli import main
from gvae_core.conventions import SH_C0, srgb_to_linear
from gvae_core.formats import detect_format, write_gltf, write_spz
from gvae_core.formats.gltf import EXTENSION, SPZ_EXTENSION, has_splats, sh_attribute
from gvae_core.ply import InfinitiesReadWarning
from gvae_core.quaternions import normalize, to_rotmat
from gvae_core.rendering.sh import sh_to_rgb
from gvae_core.transform import affine, flip_axes, rotate_sh, sh_rotation

ROT, SCALE, OPAC = (f"{EXTENSION}:{k}" for k in ("ROTATION", "SCALE", "OPACITY"))
DC = sh_attribute(0, 0)
FLOAT, BYTE, UBYTE, SHORT, USHORT = 5126, 5120, 5121, 5122, 5123
# Sign of each SH rest coefficient under x, y -> -x, -y (the PLY <-> glTF frame change), from the
# basis polynomials by hand: degree 1 (y, z, x), 2 (xy, yz, 3z²-1, xz, x²-y²), 3 (y(3x²-y²), xyz,
# y(5z²-1), z(5z²-3), x(5z²-1), z(x²-y²), x(x²-3y²)).
FRAME_SH_SIGNS = np.array([-1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], np.float32)


def covariances(c: GaussianCloud) -> np.ndarray:
    r = to_rotmat(normalize(np.asarray(c.quats, np.float64)))
    return np.einsum("nij,nj,nkj->nik", r, np.exp(2.0 * np.asarray(c.scales, np.float64)), r)


class Builder:
    """A glTF document and its binary buffer, packed by hand."""

    def __init__(self):
        self.bin = bytearray()
        self.doc = {"asset": {"version": "2.0"}, "extensionsUsed": [EXTENSION], "bufferViews": [], "accessors": [],
                    "buffers": [], "meshes": [], "nodes": [], "scenes": [{"nodes": []}], "scene": 0}

    def view(self, data: bytes, stride=None) -> int:
        self.bin += b"\0" * (-len(self.bin) % 4)
        view = {"buffer": 0, "byteOffset": len(self.bin), "byteLength": len(data)}
        if stride:
            view["byteStride"] = stride
        self.bin += data
        self.doc["bufferViews"].append(view)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, values, kind: str, ctype=FLOAT, normalized=False, **extra) -> int:
        dtype = {FLOAT: "<f4", BYTE: "i1", UBYTE: "u1", SHORT: "<i2", USHORT: "<u2"}[ctype]
        a = np.asarray(values, dtype)
        acc = {"bufferView": self.view(a.tobytes()), "componentType": ctype, "count": len(a), "type": kind, **extra}
        if normalized:
            acc["normalized"] = True
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1

    def splats(self, attributes: dict, node: dict | None = None, ext: dict | None = None, mode=0) -> int:
        prim = {"attributes": attributes, "mode": mode,
                "extensions": {EXTENSION: ext or {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}
        self.doc["meshes"].append({"primitives": [prim]})
        self.doc["nodes"].append({"mesh": len(self.doc["meshes"]) - 1, **(node or {})})
        self.doc["scenes"][0]["nodes"].append(len(self.doc["nodes"]) - 1)
        return len(self.doc["nodes"]) - 1

    def float_splats(self, c: GaussianCloud, **how) -> int:
        """A primitive holding `c` as float attributes, written in glTF's frame as they are (no flip)."""
        attrs = {"POSITION": self.accessor(c.means, "VEC3"), ROT: self.accessor(c.quats[:, [1, 2, 3, 0]], "VEC4"),
                 SCALE: self.accessor(np.exp(c.scales.astype(np.float64)), "VEC3"),
                 OPAC: self.accessor(sigmoid(c.opacities), "SCALAR"), DC: self.accessor(c.sh_dc, "VEC3")}
        for band in range(1, c.sh_degree + 1):
            for m in range(2 * band + 1):
                attrs[sh_attribute(band, m)] = self.accessor(c.sh_rest[:, band * band - 1 + m], "VEC3")
        return self.splats(attrs, **how)

    def glb(self, path):
        self.doc["buffers"] = [{"byteLength": len(self.bin)}]
        text = json.dumps(self.doc).encode()
        text += b" " * (-len(text) % 4)
        data = bytes(self.bin) + b"\0" * (-len(self.bin) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(data), 0x004E4942) + data
        path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
        return path

    def gltf(self, path, *, data_uri=False):
        uri = ("data:application/octet-stream;base64," + base64.b64encode(bytes(self.bin)).decode()) if data_uri \
            else "my%20data.bin"
        if not data_uri:
            (path.parent / "my data.bin").write_bytes(bytes(self.bin))
        self.doc["buffers"] = [{"byteLength": len(self.bin), "uri": uri}]
        path.write_text(json.dumps(self.doc))
        return path


def raw_attributes(path) -> tuple[dict, dict]:
    """(glTF JSON, {attribute: array}) of a file the writer made: its tightly packed views, plainly."""
    data = path.read_bytes()
    if data[:4] == b"glTF":
        n_json = struct.unpack_from("<I", data, 12)[0]
        doc = json.loads(data[20:20 + n_json])
        binary = data[20 + n_json + 8:]
    else:
        doc = json.loads(data)
        binary = (path.parent / doc["buffers"][0]["uri"]).read_bytes()
    out = {}
    for name, i in doc["meshes"][0]["primitives"][0]["attributes"].items():
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        dtype = {FLOAT: "<f4", UBYTE: "u1"}[acc["componentType"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        out[name] = np.frombuffer(binary, dtype, acc["count"] * width, view["byteOffset"]).reshape(acc["count"], width)
    return doc, out


# ============================================================================ files by hand

def test_float_file_by_hand_in_gltf_frame(tmp_path):
    """Two Gaussians laid out by hand: read in the PLY's frame (x, y negated; quaternion x, y negated;
    SH odd in x, y negated), linear SCALE and OPACITY back to log-scale and logit."""
    b = Builder()
    b.splats({"POSITION": b.accessor([[1, 2, 3], [-4, 5, 0.5]], "VEC3"),
              ROT: b.accessor([[0.5, 0.5, 0.5, 0.5], [0, 0, 0, 1]], "VEC4"),
              SCALE: b.accessor([[1, math.e, 0.5], [0.01, 0.02, 0.03]], "VEC3"),
              OPAC: b.accessor([0.25, 1.0], "SCALAR"), DC: b.accessor([[0.1, 0.2, 0.3], [-1, 0, 1]], "VEC3"),
              **{sh_attribute(1, m): b.accessor([[m, m + 0.5, -m], [1, 2, 3]], "VEC3") for m in (2, 1, 0)}})
    path = b.glb(tmp_path / "hand.glb")
    assert detect_format(path) == "gltf"
    with pytest.warns(InfinitiesReadWarning, match="1 opacity logit"):
        c = read_splat_file(path)
    np.testing.assert_array_equal(c.means, [[-1, -2, 3], [4, -5, 0.5]])
    np.testing.assert_array_equal(c.quats, [[0.5, -0.5, -0.5, 0.5], [1, 0, 0, 0]])
    np.testing.assert_allclose(c.scales, np.log([[1, math.e, 0.5], [0.01, 0.02, 0.03]]), rtol=1e-6)
    np.testing.assert_allclose(c.opacities, [math.log(1 / 3), 50], rtol=1e-6)
    np.testing.assert_array_equal(c.sh_dc, np.float32([[0.1, 0.2, 0.3], [-1, 0, 1]]))
    assert c.sh_degree == 1
    np.testing.assert_array_equal(c.sh_rest[0], [[-0, -0.5, 0], [1, 1.5, -1], [-2, -2.5, 2]])
    np.testing.assert_array_equal(c.sh_rest[1], [[-1, -2, -3], [1, 2, 3], [-1, -2, -3]])


def test_normalised_integers_stride_sparse_and_missing_views(tmp_path):
    """Every component type the extension allows, read as glTF defines normalised integers; an
    interleaved view; a sparse accessor over zeros (no buffer view)."""
    b = Builder()
    rot = np.array([[127, 0, 0, 0], [0, -128, 0, 0], [0, 0, 64, 127]], np.int8)
    scale = np.array([[255, 128, 0], [1, 2, 3], [10, 20, 30]], np.uint16) * 257  # ushort: c / 65535
    interleaved = np.zeros(3, [("pos", "<f4", 3), ("opacity", "u1"), ("pad", "u1", 3)])
    interleaved["pos"] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    interleaved["opacity"] = [0, 51, 255]
    view = b.view(interleaved.tobytes(), stride=16)
    b.doc["accessors"] += [{"bufferView": view, "componentType": FLOAT, "count": 3, "type": "VEC3"},
                           {"bufferView": view, "byteOffset": 12, "componentType": UBYTE, "normalized": True,
                            "count": 3, "type": "SCALAR"}]
    pos, opac = len(b.doc["accessors"]) - 2, len(b.doc["accessors"]) - 1
    sparse = {"count": 2, "indices": {"bufferView": b.view(np.array([0, 2], "<u2").tobytes()), "componentType": USHORT},
              "values": {"bufferView": b.view(np.array([[1, 2, 3], [4, 5, 6]], "<f4").tobytes())}}
    b.doc["accessors"].append({"componentType": FLOAT, "count": 3, "type": "VEC3", "sparse": sparse})
    dc = len(b.doc["accessors"]) - 1
    b.splats({"POSITION": pos, ROT: b.accessor(rot, "VEC4", BYTE, normalized=True),
              SCALE: b.accessor(scale, "VEC3", USHORT, normalized=True), OPAC: opac, DC: dc})
    with pytest.warns(InfinitiesReadWarning, match="2 opacity logit"):
        c = read_splat_file(b.glb(tmp_path / "ints.glb"))
    np.testing.assert_array_equal(c.means, [[-1, -2, 3], [-4, -5, 6], [-7, -8, 9]])
    xyzw = np.maximum(rot / np.float32(127), -1).astype(np.float32)
    np.testing.assert_array_equal(c.quats, np.stack([xyzw[:, 3], -xyzw[:, 0], -xyzw[:, 1], xyzw[:, 2]], 1))
    np.testing.assert_allclose(np.exp(c.scales.astype(np.float64)), scale / 65535, rtol=1e-6, atol=1e-13)  # 0: flat
    np.testing.assert_allclose(sigmoid(c.opacities), [0, 0.2, 1], atol=1e-6)
    np.testing.assert_array_equal(c.sh_dc, [[1, 2, 3], [0, 0, 0], [4, 5, 6]])


@pytest.mark.parametrize("data_uri", [False, True])
def test_gltf_with_bin_file_or_data_uri(tmp_path, data_uri):
    cloud = make_cloud(n=7, degree=2, seed=3)
    b = Builder()
    b.float_splats(cloud)
    back = quiet(read_splat_file, b.gltf(tmp_path / "scene.gltf", data_uri=data_uri))
    assert detect_format(tmp_path / "scene.gltf") == "gltf"
    np.testing.assert_array_equal(back.means, cloud.means * [-1, -1, 1])
    np.testing.assert_array_equal(back.sh_rest, cloud.sh_rest * FRAME_SH_SIGNS[None, :8, None])


def test_node_transforms_move_centres_covariances_and_sh(tmp_path):
    """Splats under a parent with TRS (uniform scale) and a child with a matrix (non-uniform scale and
    a mirror): the centres, covariances and SH colours read are the ones the node transforms give."""
    cloud = make_cloud(n=40, degree=3, seed=5)
    angle = 0.7
    qr = [math.sin(angle / 2) / math.sqrt(3)] * 3 + [math.cos(angle / 2)]
    r = to_rotmat(np.array([qr[3], *qr[:3]]))
    parent = np.eye(4)
    parent[:3, :3], parent[:3, 3] = 2.0 * r, [1, -2, 3]
    child = np.diag([1.0, 0.5, -3.0, 1.0])
    child[:3, 3] = [0.5, 0, 0]
    b = Builder()
    b.float_splats(cloud, node={"translation": [1, -2, 3], "rotation": qr, "scale": [2, 2, 2]})
    first = len(b.doc["nodes"]) - 1
    b.float_splats(cloud)  # placed again below as the parent's child
    b.doc["scenes"][0]["nodes"].pop()
    b.doc["nodes"][-1]["matrix"] = child.T.reshape(-1).tolist()  # column-major
    b.doc["nodes"][first]["children"] = [len(b.doc["nodes"]) - 1]
    back = quiet(read_splat_file, b.glb(tmp_path / "nodes.glb"))
    assert len(back) == 80
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    for rows, m in ((slice(0, 40), flip @ parent), (slice(40, 80), flip @ parent @ child)):
        got = back.select(np.arange(80)[rows])
        want_means = cloud.means.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
        np.testing.assert_allclose(got.means, want_means, rtol=1e-5, atol=1e-5)
        want_cov = m[:3, :3] @ covariances(cloud) @ m[:3, :3].T
        np.testing.assert_allclose(covariances(got), want_cov, rtol=1e-4, atol=1e-9)
        check_sh_moved(cloud, got, m[:3, :3])


def check_sh_moved(before: GaussianCloud, after: GaussianCloud, linear: np.ndarray):
    """The colour `after` shows along Q d is the one `before` showed along d (Q: the rotation part)."""
    u, _, vt = np.linalg.svd(linear)
    q = u @ vt
    dirs = np.random.default_rng(0).normal(size=(len(before), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    colour = lambda c, d: sh_to_rgb(torch.tensor(c.sh_dc), torch.tensor(c.sh_rest),  # noqa: E731
                                    torch.tensor(d, dtype=torch.float32), c.sh_degree).numpy()
    np.testing.assert_allclose(colour(after, dirs @ q.T), colour(before, dirs), atol=2e-5)


def test_spz_companion_extension(tmp_path):
    """An .spz payload in a buffer view: SPZ's right-up-back frame unpacked to glTF's, then the PLY's."""
    cloud = make_cloud(n=30, degree=3, seed=2)
    spz = write_spz(cloud, tmp_path / "payload.spz")
    b = Builder()
    count = b.accessor(np.zeros((30, 3)), "VEC3")
    view = b.view(spz.read_bytes())
    b.splats({"POSITION": count}, ext={"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                       "extensions": {SPZ_EXTENSION: {"bufferView": view}}})
    b.doc["extensionsUsed"].append(SPZ_EXTENSION)
    back = read_splat_file(b.glb(tmp_path / "spz.glb"))
    want = flip_axes(read_splat_file(spz), (1, -1, -1))
    for field, value in want.arrays().items():
        np.testing.assert_array_equal(getattr(back, field), value, err_msg=field)
    np.testing.assert_array_equal(back.means, read_splat_file(spz).means * [1, -1, -1])
    b.doc["accessors"][count]["count"] = 29
    with pytest.raises(PlyError, match="POSITION's accessor counts 29 points; its SPZ data holds 30"):
        read_splat_file(b.glb(tmp_path / "bad.glb"))


@pytest.mark.parametrize("generator, frame", [("splat-transform 2.3.1", [-1, -1, 1]),
                                              ("splat-transform 1.10.1", [1, 1, 1])])
def test_splat_transform_before_2_7_wrote_log_scales(tmp_path, generator, frame):
    cloud = make_cloud(n=5, degree=0)
    b = Builder()
    b.doc["asset"]["generator"] = generator
    b.splats({"POSITION": b.accessor(cloud.means, "VEC3"), ROT: b.accessor(cloud.quats[:, [1, 2, 3, 0]], "VEC4"),
              SCALE: b.accessor(cloud.scales, "VEC3"), OPAC: b.accessor(sigmoid(cloud.opacities), "SCALAR"),
              DC: b.accessor(cloud.sh_dc, "VEC3")})
    with pytest.warns(UserWarning, match=f"written by {generator} .before 2.7.0.: SCALE read as log-scales"):
        back = read_splat_file(b.glb(tmp_path / "old.glb"))
    np.testing.assert_array_equal(back.scales, cloud.scales)
    np.testing.assert_array_equal(back.means, cloud.means * frame)
    b.doc["asset"]["generator"] = "some draft writer"
    with pytest.warns(UserWarning, match="negative SCALE values: read as log-scales"):
        np.testing.assert_array_equal(read_splat_file(b.glb(tmp_path / "draft.glb")).scales, cloud.scales)


def test_what_else_the_file_holds_is_named_and_left_alone(tmp_path, capsys):
    cloud = make_cloud(n=6, degree=1)
    b = Builder()
    b.float_splats(cloud)
    tri = b.accessor([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "VEC3")
    b.doc["meshes"].append({"primitives": [{"attributes": {"POSITION": tri}, "material": 0}]})
    b.doc["nodes"].append({"mesh": 1})
    b.doc["scenes"][0]["nodes"].append(1)
    b.doc["materials"] = [{"name": "m"}]
    b.doc["cameras"] = [{"type": "perspective", "perspective": {"yfov": 1, "znear": 0.1}}]
    b.doc["meshes"][0]["primitives"][0]["attributes"]["_TEMPERATURE"] = tri + 0  # (any accessor: not read)
    path = b.glb(tmp_path / "mixed.glb")
    assert has_splats(path)
    with pytest.warns(UserWarning) as record:
        back = read_splat_file(path)
    said = " | ".join(str(w.message) for w in record)
    assert "holds more than splats, left unread: 1 mesh primitive(s) (TRIANGLES 1), 1 material, 1 camera" in said
    assert "attribute(s) not read: _TEMPERATURE" in said and len(back) == 6
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"{path} (glTF 2.0 (KHR_gaussian_splatting))" in out and "read: " in out and "1 material" in out
    # a glTF without splats is not a splat file: say so, and where it goes
    b.doc["meshes"][0]["primitives"][0]["extensions"] = {}
    with pytest.raises(PlyError, match="a glTF file without Gaussian splats .* it holds 2 mesh primitive.s. "
                       r"\(POINTS 1, TRIANGLES 1\), 1 material, 1 camera; import it with a glTF importer"):
        read_splat_file(b.glb(tmp_path / "plain.glb"))
    assert not has_splats(tmp_path / "plain.glb") and not has_splats(b.gltf(tmp_path / "plain.gltf"))


def test_bad_files_raise_ply_error_naming_the_file(tmp_path):
    cloud = make_cloud(n=4, degree=1)

    def case(edit, message, name="bad.glb"):
        b = Builder()
        b.float_splats(cloud)
        edit(b)
        path = b.glb(tmp_path / name)
        with pytest.raises(PlyError, match=message) as exc:
            quiet(read_splat_file, path)
        assert str(path) in str(exc.value)

    prim = lambda b: b.doc["meshes"][0]["primitives"][0]  # noqa: E731
    case(lambda b: prim(b)["attributes"].pop(ROT), "lacks the attribute.s. KHR_gaussian_splatting:ROTATION")
    case(lambda b: prim(b)["attributes"].pop(sh_attribute(1, 2)), "SH degree 1 is incomplete .*SH_DEGREE_1_COEF_2")
    case(lambda b: prim(b).update(mode=4), "mode 4, not POINTS")
    case(lambda b: prim(b)["extensions"].update(KHR_draco_mesh_compression={}), "KHR_draco_mesh_compression, which")
    case(lambda b: b.doc["bufferViews"][0].update(extensions={"EXT_meshopt_compression": {}}),
         "compressed with EXT_meshopt_compression")
    case(lambda b: b.doc["accessors"][0].update(count=5), "needs bytes 0..60 of a 48-byte buffer view")
    case(lambda b: b.doc["accessors"][1].update(type="VEC3"), "ROTATION.* is VEC3 .* expected VEC4")
    case(lambda b: b.doc["nodes"][0].update(children=[0]), "its own ancestor")
    case(lambda b: b.doc["buffers"].append({}) or b.doc["bufferViews"][0].update(buffer=3), r"refers to buffers\[3\]")
    case(lambda b: b.doc["asset"].update(version="1.0"), "glTF version '1.0'")
    # an OPACITY outside [0, 1] is refused, or its rows dropped when asked
    b = Builder()
    b.float_splats(cloud)
    acc = b.doc["accessors"][3]
    start = b.doc["bufferViews"][acc["bufferView"]]["byteOffset"]
    b.bin[start:start + 8] = struct.pack("<2f", 1.5, -0.1)
    path = b.glb(tmp_path / "opacity.glb")
    with pytest.raises(PlyError, match=r"2 OPACITY value\(s\) outside \[0, 1\] .* rows \[0, 1\]"):
        read_splat_file(path)
    with pytest.warns(UserWarning, match="dropped 2 of 4"):
        assert len(read_splat_file(path, sanitize=True)) == 2
    (tmp_path / "e.gltf").write_text("{")
    with pytest.raises(PlyError, match="e.gltf: the glTF JSON is not valid"):
        read_splat_file(tmp_path / "e.gltf")
    b.gltf(tmp_path / "gone.gltf")
    (tmp_path / "my data.bin").unlink()
    with pytest.raises(PlyError, match=r"gone.gltf: cannot read buffers\[0\] from .*my data.bin"):
        read_splat_file(tmp_path / "gone.gltf")


@pytest.fixture(scope="module")
def seed_glb(tmp_path_factory) -> bytes:
    return quiet(write_gltf, make_cloud(n=200, degree=1, seed=7), tmp_path_factory.mktemp("glb") / "s.glb").read_bytes()


def test_truncated_glb_raises_ply_error(tmp_path, seed_glb):
    path = tmp_path / "t.glb"
    for cut in (0, 3, 12, 19, 40, len(seed_glb) // 2, len(seed_glb) - 1):
        path.write_bytes(seed_glb[:cut])
        with pytest.raises(PlyError) as exc:
            read_splat_file(path)
        assert str(path) in str(exc.value), cut


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=EDITS)
def test_property_corruption_only_raises_ply_error(tmp_path, seed_glb, ops):
    path = tmp_path / "c.glb"
    json_end = 20 + struct.unpack_from("<I", seed_glb, 12)[0]
    path.write_bytes(corrupt(seed_glb, ops, head_len=json_end + 16))  # half the edits in the header and JSON
    read_or_refuse(read_splat_file, path)


# ============================================================================== the writer

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("name", ["out.glb", "out.gltf"])
def test_ply_to_gltf_to_ply(tmp_path, degree, name):
    """Positions, SH and normalised rotations come back exactly; log-scales and logits within the
    float32 rounding of exp / sigmoid; the file is PLY -> glTF frame, as the extension defines it."""
    cloud = make_cloud(n=300, degree=degree, seed=degree)
    cloud.quats[0] = 0  # zero quaternion: the identity
    path = write_gltf(cloud, tmp_path / name)
    back = read_splat_file(path)
    np.testing.assert_array_equal(back.means, cloud.means)
    np.testing.assert_array_equal(back.sh_dc, cloud.sh_dc)
    np.testing.assert_array_equal(back.sh_rest, cloud.sh_rest)
    np.testing.assert_array_equal(back.quats, normalize(cloud.quats.astype(np.float64)).astype(np.float32))
    assert (np.abs(back.scales - cloud.scales) <= 2.0 ** -24 + np.spacing(np.abs(cloud.scales))).all()
    # (the opacity rounded to float32, then its logit: a quarter of the logit's own rounding more)
    bound = 2.0 ** -25 + 0.25 * np.spacing(np.abs(back.opacities)).astype(np.float64)
    assert (np.abs(sigmoid(back.opacities) - sigmoid(cloud.opacities)) <= bound).all()
    doc, raw = raw_attributes(path)
    assert doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION]["colorSpace"] == "srgb_rec709_display"
    np.testing.assert_array_equal(raw["POSITION"], cloud.means * [-1, -1, 1])
    q = normalize(cloud.quats.astype(np.float64))
    np.testing.assert_array_equal(raw[ROT], (q[:, [1, 2, 3, 0]] * [-1, -1, 1, 1]).astype(np.float32))
    np.testing.assert_array_equal(raw[SCALE], np.exp(cloud.scales.astype(np.float64)).astype(np.float32))
    np.testing.assert_array_equal(raw[OPAC][:, 0], sigmoid(cloud.opacities).astype(np.float32))
    for band in range(1, degree + 1):
        for m in range(2 * band + 1):
            k = band * band - 1 + m
            np.testing.assert_array_equal(raw[sh_attribute(band, m)], cloud.sh_rest[:, k] * FRAME_SH_SIGNS[k])
    want = np.rint(255 * srgb_to_linear(np.clip(cloud.sh_dc * SH_C0 + 0.5, 0, 1)))  # (float32 there: one code off)
    assert np.abs(raw["COLOR_0"][:, :3] - want).max() <= 1
    np.testing.assert_array_equal(raw["COLOR_0"][:, 3], np.rint(255 * raw[OPAC][:, 0]))
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]["max"] == \
        [float(v) for v in raw["POSITION"].max(0)]
    # the frame change keeps the picture: the colour the file shows along F d is the PLY's along d
    rest = [raw[sh_attribute(b, m)] for b in range(1, degree + 1) for m in range(2 * b + 1)]
    in_file = cloud.replace(means=raw["POSITION"], sh_dc=raw[DC],
                            sh_rest=np.stack(rest, 1) if rest else cloud.sh_rest)
    check_sh_moved(cloud, in_file, np.diag([-1.0, -1.0, 1.0]))


def test_writer_refuses_and_leaves_nothing_and_reports_extras(tmp_path):
    cloud = make_cloud(n=5, degree=1)
    cloud.scales[2, 0] = np.nan
    out = tmp_path / "out"
    out.mkdir()
    for name in ("x.glb", "x.gltf"):
        with pytest.raises(PlyError, match=r"non-finite parameters, rows \[2\]"):
            write_gltf(cloud, out / name)
    with pytest.raises(PlyError, match="no Gaussians to write"):
        write_gltf(cloud.select(np.zeros(5, bool)), out / "e.glb")
    assert_no_leftovers(out)
    good = make_cloud(n=5, degree=1)
    good.extra["filter_3D"] = np.ones(5, np.float32)
    good.scales[0, 0] = 100.0
    with pytest.warns(UserWarning) as record:
        write_gltf(good, tmp_path / "x.glb")
    said = " | ".join(str(w.message) for w in record)
    assert "holds no extra properties; not written: filter_3D" in said
    assert "1 log-scale(s) above 88.72 written as the largest float32" in said
    assert read_splat_file(tmp_path / "x.glb").scales[0, 0] == np.float32(math.log(np.finfo(np.float32).max))


def test_cli_convert_and_info(tmp_path, capsys):
    cloud = make_cloud(n=50, degree=3)
    src = write_ply(cloud, tmp_path / "in.ply")
    assert main(["convert", str(src), str(tmp_path / "a.glb")]) == 0
    assert f"-> {tmp_path / 'a.glb'} (glTF 2.0 (KHR_gaussian_splatting)): 50 Gaussians" in capsys.readouterr().out
    assert main(["convert", str(tmp_path / "a.glb"), str(tmp_path / "b.gltf"), "--sh-degree", "1"]) == 0
    capsys.readouterr()
    assert (tmp_path / "b.bin").exists() and read_splat_file(tmp_path / "b.gltf").sh_degree == 1
    assert main(["convert", str(tmp_path / "b.gltf"), str(tmp_path / "c.ply")]) == 0
    capsys.readouterr()
    np.testing.assert_array_equal(read_splat_file(tmp_path / "c.ply").means, cloud.means)
    assert main(["info", str(tmp_path / "a.glb")]) == 0
    assert "Gaussians: 50" in capsys.readouterr().out


# ======================================================================== gvae_core.transform

def test_sh_rotation_against_the_renderer():
    """A random rotation, and a mirror: the colour seen along Q d afterwards is the one seen along d."""
    rng = np.random.default_rng(1)
    cloud = make_cloud(n=50, degree=3, seed=4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    for m in (q * np.sign(np.linalg.det(q)), -q * np.sign(np.linalg.det(q))):
        check_sh_moved(cloud, cloud.replace(sh_rest=rotate_sh(cloud.sh_rest, m)), m)
    t = sh_rotation(np.diag([-1.0, -1.0, 1.0]), 3)
    np.testing.assert_array_equal(t, np.diag(FRAME_SH_SIGNS))  # exact: no rounding in a change of axes


def test_flip_is_exact_and_its_own_inverse_and_affine_agrees():
    cloud = make_cloud(n=100, degree=3, seed=9)
    for signs in ((-1, -1, 1), (1, -1, -1), (-1, 1, -1)):
        once = flip_axes(cloud, signs)
        for field, value in flip_axes(once, signs).arrays().items():
            np.testing.assert_array_equal(value, getattr(cloud, field), err_msg=field)
        general = affine(cloud, np.diag([*signs, 1.0]))
        np.testing.assert_allclose(covariances(general), covariances(once), rtol=1e-5, atol=1e-8)
        np.testing.assert_allclose(general.sh_rest, once.sh_rest, atol=1e-6)
    with pytest.raises(ValueError, match="product"):
        flip_axes(cloud, (-1, 1, 1))
    # the uniform-scale path (quaternions) and the general one (eigen-decomposition) agree
    m = np.eye(4)
    m[:3, :3] = 1.5 * to_rotmat(normalize(np.array([0.3, -0.2, 0.9, 0.1])))
    stretched = np.diag([1.0, 1.0, 1.0 + 1e-7, 1.0]) @ m
    a, b = affine(cloud, m), affine(cloud, stretched)
    np.testing.assert_allclose(covariances(a), covariances(b), rtol=1e-5, atol=1e-8)
    with pytest.raises(ValueError, match="singular"):
        affine(cloud, np.diag([1.0, 0.0, 1.0, 1.0]))


def test_degenerate_gaussians_survive_every_path(tmp_path):
    """Zero and huge scales, a zero quaternion, extreme opacities, a far point: finite both ways."""
    cloud = make_cloud(n=8, degree=2)
    cloud.scales[0] = -30
    cloud.scales[1] = [20, -20, 5]
    cloud.quats[2] = 0
    cloud.opacities[3:5] = [60, -60]
    cloud.means[5] = [1e7, -1e7, 3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = read_splat_file(write_gltf(cloud, tmp_path / "d.glb"))
        moved = affine(back, np.diag([2.0, 1.0, 0.5, 1.0]))
    for c in (back, moved):
        assert all(np.isfinite(a).all() for a in c.arrays().values())
    assert back.opacities[3] == 50 and back.opacities[4] < -30


def test_cli_refine_and_compact_take_and_give_gltf(tmp_path, capsys, monkeypatch):
    """`gvae refine` (the refinement stubbed: test_refine covers it) and `gvae compact` read a .glb and
    write .glb / .gltf through read_splat_file / write_splat_file."""
    cloud = make_cloud(n=120, degree=1, seed=6)
    src = write_gltf(cloud, tmp_path / "in.glb")
    seen = []

    def fake_refine(c, **kwargs):
        seen.append(c)
        return types.SimpleNamespace(cloud=c, summary=lambda: "refined (stub)")

    monkeypatch.setattr("gvae_core.refinement.refine", fake_refine)
    assert main(["refine", str(src), str(tmp_path / "out.gltf"), "--budget", "all"]) == 0
    capsys.readouterr()
    np.testing.assert_array_equal(seen[0].means, read_splat_file(src).means)
    np.testing.assert_array_equal(read_splat_file(tmp_path / "out.gltf").means, cloud.means)
    assert main(["compact", str(src), str(tmp_path / "small.glb"), "--keep", "50%", "--resolution", "24"]) == 0
    assert "120 -> 60" in capsys.readouterr().out and len(read_splat_file(tmp_path / "small.glb")) == 60


@pytest.mark.parametrize("version", ["1.10.1", "2.3.1", "2.7.1"])
def test_files_of_older_splat_transform_versions(version):
    """Files splat-transform itself wrote (tests/data/splat_transform): log-scales before 2.7.0, the
    PLY's frame before 2.0; every Gaussian back as the PLY has it (its quaternions as it stored them)."""
    folder = Path(__file__).parent / "data" / "splat_transform"
    source = read_splat_file(folder / "source.ply")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        back = read_splat_file(folder / f"splat-transform-{version}.glb")
    said = " | ".join(str(w.message) for w in caught)
    assert ("before 2.7.0" in said) == (version < "2.7") and ("PLY's frame" in said) == version.startswith("1.")
    for field in ("means", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(back, field), getattr(source, field), err_msg=field)
    assert (np.abs(back.scales - source.scales) <= 2.0 ** -24 + np.spacing(np.abs(source.scales))).all()
    defined = np.linalg.norm(source.quats, axis=1) > 0
    np.testing.assert_allclose(covariances(back.select(defined)), covariances(source.select(defined)), rtol=1e-6,
                               atol=1e-12)
    assert np.abs(sigmoid(back.opacities) - sigmoid(source.opacities))[2:].max() < 1e-7 and back.opacities[1] == 50
