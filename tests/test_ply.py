"""PLY I/O: layouts, round trips, extras, bad input, atomic writes; cross-checked with plyfile."""

import os
import subprocess
import sys
import warnings

import numpy as np
import plyfile
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.corruption import EDITS, corrupt, read_or_refuse

from gvae_core import GaussianCloud, PlyError, read_ply, write_ply
from gvae_core.ply import InfinitiesReadWarning

K_OF_DEGREE = {0: 0, 1: 3, 2: 8, 3: 15}


def random_cloud(n=20, degree=3, seed=0, **extra):
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    return GaussianCloud(means=f(n, 3), scales=f(n, 3) - 3, quats=f(n, 4), opacities=f(n),
                         sh_dc=f(n, 3), sh_rest=f(n, K_OF_DEGREE[degree], 3), extra=extra)


def assert_same(a, b):
    assert len(a) == len(b) and a.sh_degree == b.sh_degree
    for name, value in a.arrays().items():
        other = getattr(b, name)
        assert other.dtype == np.float32
        np.testing.assert_array_equal(other, value, err_msg=name)


def reference_rows(cloud):
    """The cloud as plyfile vertex rows in the reference layout (slow, written independently)."""
    n, k = len(cloud), cloud.sh_rest.shape[1]
    cols = {"x": cloud.means[:, 0], "y": cloud.means[:, 1], "z": cloud.means[:, 2]}
    for s in "xyz":
        cols[f"n{s}"] = np.zeros(n, np.float32)
    for c in range(3):
        cols[f"f_dc_{c}"] = cloud.sh_dc[:, c]
    for c in range(3):          # channel-major: all red coefficients, then green, then blue
        for j in range(k):
            cols[f"f_rest_{c * k + j}"] = cloud.sh_rest[:, j, c]
    cols["opacity"] = cloud.opacities
    for i in range(3):
        cols[f"scale_{i}"] = cloud.scales[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = cloud.quats[:, i]
    return cols


def write_with_plyfile(path, cols, *, text=False, byte_order="<", order=None, dtype="f4", comments=()):
    names = order or list(cols)
    rows = np.empty(len(next(iter(cols.values()))), [(name, cols[name].dtype if cols[name].dtype.kind in "iub"
                                                       else dtype) for name in names])
    for name in names:
        rows[name] = cols[name]
    el = plyfile.PlyElement.describe(rows, "vertex")
    plyfile.PlyData([el], text=text, byte_order=byte_order, comments=list(comments)).write(str(path))
    return path


# ------------------------------------------------------------------------- layouts

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_byte_identical(tmp_path, degree):
    cloud = random_cloud(degree=degree, seed=degree)
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    write_ply(cloud, a)
    back = read_ply(a)
    assert_same(cloud, back)
    assert back.extra == {}
    write_ply(back, b)
    assert a.read_bytes() == b.read_bytes()
    # plyfile sees the reference layout, property by property.
    v = plyfile.PlyData.read(str(a))["vertex"]
    expected = reference_rows(cloud)
    assert list(v.data.dtype.names) == list(expected)
    for name, col in expected.items():
        np.testing.assert_array_equal(v[name], col, err_msg=name)


@pytest.mark.parametrize("text,byte_order,dtype", [(True, "=", "f4"), (False, ">", "f4"),
                                                    (False, "<", "f8"), (True, "=", "f8")])
def test_reads_ascii_big_endian_double_and_any_order(tmp_path, text, byte_order, dtype):
    cloud = random_cloud(n=13, degree=2, seed=3)
    cols = reference_rows(cloud)
    del cols["nx"], cols["ny"], cols["nz"]  # normals absent
    order = list(cols)[::-1]
    path = write_with_plyfile(tmp_path / "x.ply", cols, text=text, byte_order=byte_order,
                              order=order, dtype=dtype)
    assert_same(cloud, read_ply(path))


def test_extras_keep_their_dtype_and_values(tmp_path):
    n = 9
    big = np.arange(n, dtype=np.int64) * (2 ** 40) - 5  # beyond int32: stored exactly as double
    cloud = random_cloud(n=n, degree=1, gvae_id=np.arange(n, dtype=np.int64) + 10 ** 6, big=big,
                         label=np.arange(n, dtype=np.uint8), weight=np.linspace(0, 1, n),
                         flag=np.arange(n) % 3 == 0, half=np.linspace(0, 2, n).astype(np.float16))
    path = write_ply(cloud, tmp_path / "e.ply")
    back = read_ply(path)
    assert list(back.extra) == list(cloud.extra)
    for key, value in cloud.extra.items():
        assert back.extra[key].dtype == value.dtype, key
        np.testing.assert_array_equal(back.extra[key], value, err_msg=key)
    # Other readers see standard PLY types.
    v = plyfile.PlyData.read(str(path))["vertex"]
    assert v["gvae_id"].dtype == np.int32 and v["big"].dtype == np.float64
    np.testing.assert_array_equal(v["big"].astype(np.int64), big)
    before = path.read_bytes()
    write_ply(back, path)
    assert path.read_bytes() == before
    # Unknown properties from other tools are kept as they are.
    cols = reference_rows(cloud) | {"seg": np.arange(n, dtype=np.int16)}
    other = read_ply(write_with_plyfile(tmp_path / "o.ply", cols))
    assert other.extra["seg"].dtype == np.int16 and list(other.extra["seg"]) == list(range(n))


def test_extras_that_ply_cannot_hold_are_refused(tmp_path):
    path = tmp_path / "r.ply"
    for bad in ({"huge": np.array([2 ** 60, 0], np.int64)}, {"vec": np.zeros((2, 3))},
                {"z": np.zeros(2, np.complex64)}, {"has space": np.zeros(2)}, {"x": np.zeros(2)}):
        with pytest.raises(PlyError, match=str(path)):
            write_ply(random_cloud(n=2, **bad), path)
        assert os.listdir(tmp_path) == []


def test_normals_are_kept_when_present(tmp_path):
    cloud = random_cloud(n=4, degree=0)
    zero = read_ply(write_ply(cloud, tmp_path / "z.ply"))
    assert "nx" not in zero.extra
    normals = {"nx": np.ones(4, np.float32), "ny": np.zeros(4, np.float32), "nz": -np.ones(4, np.float32)}
    back = read_ply(write_ply(cloud.replace(extra=normals), tmp_path / "n.ply"))
    assert set(back.extra) == {"nx", "ny", "nz"}
    np.testing.assert_array_equal(back.extra["nz"], -1)
    v = plyfile.PlyData.read(str(tmp_path / "n.ply"))["vertex"]
    assert v.data.dtype.names[3:6] == ("nx", "ny", "nz")  # in the reference slot, not appended


def test_empty_cloud(tmp_path):
    back = read_ply(write_ply(GaussianCloud.empty(3), tmp_path / "e.ply"))
    assert len(back) == 0 and back.sh_degree == 3


def test_torch_clouds_are_written(tmp_path):
    pytest.importorskip("torch", reason="torch clouds need torch")
    cloud = random_cloud(n=5, gvae_id=np.arange(5, dtype=np.int64))
    back = read_ply(write_ply(cloud.to_torch(), tmp_path / "t.ply"))
    assert_same(cloud, back)
    assert back.extra["gvae_id"].dtype == np.int64


def test_other_elements(tmp_path):
    cloud = random_cloud(n=6, degree=0)
    rows = reference_rows(cloud)
    vert = np.empty(6, [(k, "f4") for k in rows])
    for k, v in rows.items():
        vert[k] = v
    faces = np.array([([0, 1, 2],)], [("vertex_indices", "i4", (3,))])
    cam = np.array([(1.0, 2.0)], [("a", "f4"), ("b", "f4")])
    for text in (False, True):
        path = tmp_path / f"f{text}.ply"
        plyfile.PlyData([plyfile.PlyElement.describe(cam, "camera"), plyfile.PlyElement.describe(vert, "vertex"),
                         plyfile.PlyElement.describe(faces, "face")], text=text).write(str(path))
        with pytest.warns(UserWarning, match="face"):
            assert_same(cloud, read_ply(path))
        plyfile.PlyData([plyfile.PlyElement.describe(faces, "face"),
                         plyfile.PlyElement.describe(vert, "vertex")], text=text).write(str(path))
        with pytest.raises(PlyError, match="list properties before the vertex"):
            read_ply(path)


# ------------------------------------------------------------------------ bad input

@pytest.fixture
def good_file(tmp_path):
    return write_ply(random_cloud(n=10, degree=3), tmp_path / "good.ply")


def header_of(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end].decode(), data[end:]


def test_bad_headers(tmp_path, good_file):
    head, body = header_of(good_file)
    cases = {
        "not a PLY": b"solid cube\n" + body,
        "no 'end_header'": head.replace("end_header", "end_headr").encode() + body,
        "format": head.replace("binary_little_endian 1.0", "binary_middle_endian 1.0").encode() + body,
        "unknown keyword": head.replace("element vertex", "elephant vertex").encode() + body,
        "property TYPE NAME": head.replace("float opacity", "float16 opacity").encode() + body,
        "non-ASCII": head.replace("comment", "comment \xe9").encode("latin-1") + body if "comment" in head
        else head.replace("ply\n", "ply\ncomment \xe9\n").encode("latin-1") + body,
        "one 'vertex' element": head.replace("element vertex", "element vertices").encode() + body,
    }
    for what, data in cases.items():
        path = tmp_path / "bad.ply"
        path.write_bytes(data)
        with pytest.raises(PlyError, match=what) as err:
            read_ply(path)
        assert str(path) in str(err.value)


def test_truncated_and_oversized_counts(tmp_path, good_file):
    data = good_file.read_bytes()
    path = tmp_path / "t.ply"
    path.write_bytes(data[:-7])
    with pytest.raises(PlyError, match="truncated"):
        read_ply(path)
    head, body = header_of(good_file)
    for count in (10 ** 15, 2 ** 62):  # refused from the file size, before allocating anything
        path.write_bytes(head.replace("element vertex 10", f"element vertex {count}").encode() + body)
        with pytest.raises(PlyError, match=f"declares {count} vertices"):
            read_ply(path)
    ascii_path = write_with_plyfile(tmp_path / "a.ply", reference_rows(random_cloud(n=3)), text=True)
    head, body = header_of(ascii_path)
    path.write_bytes(head.replace("element vertex 3", "element vertex 4000000000000").encode() + body)
    with pytest.raises(PlyError, match="truncated"):
        read_ply(path)
    path.write_bytes(head.encode() + body.replace(b"\n", b" x\n", 1))
    with pytest.raises(PlyError, match="ascii"):
        read_ply(path)


def test_missing_properties_are_named(tmp_path):
    cols = reference_rows(random_cloud(n=3, degree=1))
    for drop in ("opacity", "rot_3", "f_dc_1"):
        path = write_with_plyfile(tmp_path / "m.ply", {k: v for k, v in cols.items() if k != drop})
        with pytest.raises(PlyError, match=f"missing required vertex properties: {drop}"):
            read_ply(path)
    path = write_with_plyfile(tmp_path / "r.ply", {k: v for k, v in cols.items() if k != "f_rest_8"})
    with pytest.raises(PlyError, match="8 f_rest_"):
        read_ply(path)
    renamed = {("f_rest_9" if k == "f_rest_3" else k): v for k, v in cols.items()}
    with pytest.raises(PlyError, match="numbered"):
        read_ply(write_with_plyfile(tmp_path / "g.ply", renamed))


def test_non_finite_rows_are_reported_or_dropped(tmp_path):
    cloud = random_cloud(n=12, degree=1)
    cols = reference_rows(cloud)
    cols["x"] = cols["x"].copy()
    cols["x"][[3, 7]] = [np.nan, np.inf]
    cols["f_rest_4"] = cols["f_rest_4"].copy()
    cols["f_rest_4"][9] = -np.inf
    for dtype in ("f4", "f8"):
        path = write_with_plyfile(tmp_path / "nan.ply", cols, dtype=dtype)
        with pytest.raises(PlyError, match=r"3 Gaussian\(s\) with non-finite .* rows \[3, 7, 9\]"):
            read_ply(path)
        with pytest.warns(UserWarning, match="dropped 3 of 12"):
            clean = read_ply(path, sanitize=True)
        assert_same(cloud.select(np.setdiff1d(np.arange(12), [3, 7, 9])), clean)
    # A double too large for float32 is non-finite once canonicalised.
    cols = reference_rows(cloud)
    cols["scale_0"] = cols["scale_0"].astype(np.float64)
    cols["scale_0"][0] = 1e300
    with pytest.raises(PlyError, match=r"rows \[0\]"):
        read_ply(write_with_plyfile(tmp_path / "big.ply", cols, dtype="f8"))


def test_infinite_opacities_and_flat_axes_are_read_as_their_meaning(tmp_path):
    """splat-transform and Niantic's loader write fully opaque / transparent Gaussians as an opacity
    logit of +inf / -inf, and a flat axis is a log-scale of -inf: every such row is kept, clamped to
    the finite value the renderer uses, and counted; other infinities and NaN stay bad input."""
    cloud = random_cloud(n=12, degree=1)
    cols = reference_rows(cloud)
    for name in ("opacity", "scale_1", "scale_2", "x", "f_dc_0"):
        cols[name] = cols[name].copy()
    cols["opacity"][[1, 2, 5]] = [np.inf, -np.inf, np.inf]
    cols["scale_1"][[2, 4]] = -np.inf
    for dtype in ("f4", "f8"):
        path = write_with_plyfile(tmp_path / "inf.ply", cols, dtype=dtype)
        with pytest.warns(InfinitiesReadWarning, match=r"read 3 opacity logit\(s\) of \+-inf as \+-50 .*"
                          r"and 2 log-scale\(s\) of -inf as -30 \(flat axes\)"):
            back = read_ply(path)
        want = cloud.copy()
        want.opacities[[1, 2, 5]] = [50, -50, 50]
        want.scales[[2, 4], 1] = -30
        assert_same(want, back)
        assert back.activated_opacities()[1] == 1.0 and back.activated_opacities()[2] < 1e-21
    # NaN, an infinite position or colour and a log-scale of +inf are not read as anything.
    cols["scale_2"][7] = np.inf
    cols["x"][8] = -np.inf
    cols["f_dc_0"][9] = np.inf
    cols["opacity"][10] = np.nan
    cols["scale_1"][8] = -np.inf  # a flat axis does not save a row that is bad otherwise
    path = write_with_plyfile(tmp_path / "bad.ply", cols)
    with pytest.raises(PlyError, match=r"4 Gaussian\(s\) with non-finite .* rows \[7, 8, 9, 10\]"):
        quiet_read(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        clean = read_ply(path, sanitize=True)
    assert len(clean) == 8 and np.isfinite(clean.opacities).all()
    said = " | ".join(str(w.message) for w in caught)
    assert "dropped 4 of 12" in said and "3 opacity logit(s)" in said


def quiet_read(path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_ply(path, **kwargs)


def test_writes_are_atomic(tmp_path, good_file):
    before = good_file.read_bytes()
    bad = random_cloud(n=10)
    bad.quats[4, 2] = np.nan
    with pytest.raises(PlyError, match=r"refusing to write 1 Gaussian\(s\) .* rows \[4\]"):
        write_ply(bad, good_file)
    assert good_file.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["good.ply"]
    with pytest.raises(OSError):
        write_ply(random_cloud(n=2), tmp_path)  # a directory cannot be replaced by a file
    assert sorted(os.listdir(tmp_path)) == ["good.ply"]


def test_no_torch_needed():
    code = ("import sys, tempfile, os, numpy as np\n"
            "import gvae_core\n"
            "from gvae_core import GaussianCloud, read_ply, write_ply, load_nerf_synthetic, Camera\n"
            "c = GaussianCloud(means=np.zeros((2,3)), scales=np.zeros((2,3)), quats=np.ones((2,4)),"
            " opacities=np.zeros(2), sh_dc=np.zeros((2,3)))\n"
            "p = os.path.join(tempfile.mkdtemp(), 'a.ply')\n"
            "assert len(read_ply(write_ply(c, p))) == 2\n"
            "c.validate(); c.sanitize(); c.select([0]); c.rotation_matrices()\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


# ----------------------------------------------------------------------- properties

finite32 = st.floats(-1e6, 1e6, allow_nan=False, width=32)


@st.composite
def clouds(draw):
    n = draw(st.integers(0, 12))
    degree = draw(st.integers(0, 3))
    k = K_OF_DEGREE[degree]
    seed = draw(st.integers(0, 2 ** 32 - 1))
    rng = np.random.default_rng(seed)
    special = np.array([0.0, -0.0, 1e-38, -3.4e38, 3.4e38, 1.0, -1.0], np.float32)

    def arr(*shape):
        a = (rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape)).astype(np.float32)
        mask = rng.random(shape) < 0.1
        a[mask] = rng.choice(special, size=int(mask.sum()))
        return a

    extra = {}
    if draw(st.booleans()):
        extra["gvae_id"] = rng.integers(-2 ** 53, 2 ** 53, size=n, dtype=np.int64)
    if draw(st.booleans()):
        extra["tag"] = rng.integers(0, 255, size=n).astype(draw(st.sampled_from(["u1", "i2", "u4", "f8"])))
    if n and draw(st.booleans()):
        extra.update(nx=arr(n), ny=arr(n), nz=arr(n))
    return GaussianCloud(means=arr(n, 3), scales=arr(n, 3), quats=arr(n, 4), opacities=arr(n),
                         sh_dc=arr(n, 3), sh_rest=arr(n, k, 3), extra=extra)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cloud=clouds())
def test_property_round_trip(tmp_path, cloud):
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    write_ply(cloud, a)
    back = read_ply(a)
    assert_same(cloud, back)
    assert set(back.extra) == set(cloud.extra)
    for key, value in cloud.extra.items():
        assert back.extra[key].dtype == value.dtype
        np.testing.assert_array_equal(back.extra[key], value)
    write_ply(back, b)
    assert a.read_bytes() == b.read_bytes()


def _seed_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("seeds")
    cloud = random_cloud(n=4, degree=1, gvae_id=np.arange(4, dtype=np.int64))
    binary = write_ply(cloud, d / "b.ply").read_bytes()
    ascii_ = write_with_plyfile(d / "a.ply", reference_rows(cloud), text=True).read_bytes()
    return [binary, ascii_]


@pytest.fixture(scope="module")
def seed_files(tmp_path_factory):
    return _seed_files(tmp_path_factory)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.integers(0, 1), ops=EDITS)
def test_property_corruption_only_raises_ply_error(tmp_path, seed_files, which, ops):
    data = seed_files[which]
    path = tmp_path / "c.ply"
    path.write_bytes(corrupt(data, ops, head_len=data.index(b"end_header") + 11))
    read_or_refuse(read_ply, path)
