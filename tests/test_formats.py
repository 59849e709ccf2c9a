"""The splat formats beside the reference PLY: .splat, .spz (v1-v4), SuperSplat's compressed PLY.

Each format is checked against bytes laid out by hand from its specification (so no codec is
tested only against itself), by round trips within the format's quantisation step, and by
corrupt, truncated and non-finite input, which must raise PlyError naming the file."""

from __future__ import annotations

import gzip
import math
import struct
import types
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.corruption import EDITS, corrupt, read_or_refuse

from gvae_core import GaussianCloud, PlyError, read_ply, read_splat_file, write_ply
from gvae_core.cli import main
from gvae_core.conventions import LOG_SCALE_RANGE, SH_C0, rgb_to_dc
from gvae_core.formats import (detect_format, read_compressed_ply, read_splat, read_spz, write_compressed_ply,
                               write_splat, write_splat_file, write_spz)
from gvae_core.formats.spz import read_spz_header
from gvae_core.ply import InfinitiesReadWarning
from gvae_core.quaternions import normalize

K_OF_DEGREE = {0: 0, 1: 3, 2: 8, 3: 15}
try:
    import zstandard as _zstd
except ImportError:  # an optional runtime: only .spz version 4 needs it
    _zstd = None
requires_zstd = pytest.mark.skipif(_zstd is None, reason="zstandard is not installed (.spz version 4 needs it)")


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def logit(p):
    return math.log(p / (1 - p))


def make_cloud(n=300, degree=3, seed=0, *, dc_range=1.7, sh_range=0.9):
    """A cloud inside every format's range (colours the .splat can show, SH within +-1)."""
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.normal(size=s).astype(np.float32)  # noqa: E731
    return GaussianCloud(means=f(n, 3) * 3, scales=np.clip(f(n, 3) - 4, -9.5, 5), quats=f(n, 4),
                         opacities=np.clip(f(n) * 2, -6, 6),
                         sh_dc=rng.uniform(-dc_range, dc_range, (n, 3)).astype(np.float32),
                         sh_rest=rng.uniform(-sh_range, sh_range, (n, K_OF_DEGREE[degree], 3)).astype(np.float32))


def quat_error(a, b) -> np.ndarray:
    """Per-row largest component difference of the unit quaternions, q and -q being the same rotation."""
    a, b = normalize(np.asarray(a, np.float64)), normalize(np.asarray(b, np.float64))
    return np.minimum(np.abs(a - b).max(1), np.abs(a + b).max(1))


def xyz_error(a, b) -> np.ndarray:
    """Per-row largest difference of x, y, z of the unit quaternions made w >= 0: what .spz versions
    1-2 store (w is derived, so its error grows without bound as w nears 0)."""
    a, b = (normalize(np.asarray(q, np.float64)) for q in (a, b))
    a, b = (np.where(q[:, :1] < 0, -q, q) for q in (a, b))
    return np.abs(a[:, 1:] - b[:, 1:]).max(1)


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


def assert_no_leftovers(folder):
    assert [p.name for p in folder.iterdir()] == [], "a failed write left files behind"


# ============================================================================ hand-laid bytes

def test_splat_bytes_by_hand(tmp_path):
    # position (1, -2, 0.5); scales 0.5, 0.25, 2; colour (1, 0, 0.5) -> 255, 0, 127.5 -> 128;
    # opacity 0.5 -> 127.5 -> 128; identity quaternion: 128 * 1 + 128 = 256, clamped to 255.
    expected = struct.pack("<3f3f4B4B", 1, -2, 0.5, 0.5, 0.25, 2, 255, 0, 128, 128, 255, 128, 128, 128)
    cloud = GaussianCloud(means=[[1, -2, 0.5]], scales=np.log([[0.5, 0.25, 2.0]]), quats=[[3.0, 0, 0, 0]],
                          opacities=[0.0], sh_dc=rgb_to_dc(np.array([[1.0, 0.0, 0.5]])))
    path = write_splat(cloud, tmp_path / "one.splat")
    assert path.read_bytes() == expected
    # and reading bytes laid out by hand
    raw = struct.pack("<3f3f4B4B", 4, 5, 6, 1, 0.5, 0.125, 51, 204, 0, 0, 128, 0, 255, 192)
    (tmp_path / "two.splat").write_bytes(raw)
    back = read_splat_file(tmp_path / "two.splat")
    np.testing.assert_array_equal(back.means, [[4, 5, 6]])
    np.testing.assert_allclose(back.scales, np.log([[1, 0.5, 0.125]]), rtol=1e-6)
    np.testing.assert_allclose(back.sh_dc, [[(0.2 - 0.5) / SH_C0, (0.8 - 0.5) / SH_C0, -0.5 / SH_C0]], rtol=1e-6)
    np.testing.assert_allclose(back.quats, [[0, -1, 127 / 128, 0.5]])
    # opacity code 0 is a quarter step above 0: finite, invisible
    assert back.opacities[0] == pytest.approx(logit(0.25 / 255), rel=1e-6)
    assert back.sh_degree == 0


def _spz_v3_payload() -> tuple[bytes, GaussianCloud]:
    """One SH-degree-1 Gaussian, laid out by hand from Niantic's specification."""
    header = b"NGSP" + struct.pack("<IIBBBB", 3, 1, 1, 12, 0, 0)
    positions = bytes([0x00, 0x10, 0x00,     # x = 1.0   -> 4096 = 0x001000
                       0x00, 0xF8, 0xFF,     # y = -0.5  -> -2048 = 0xFFF800
                       0x00, 0x04, 0x00])    # z = 0.25  -> 1024
    alphas = bytes([128])                    # sigmoid(0) * 255 = 127.5 -> 128
    colors = bytes([128, 166, 89])           # 255 * (0.15 f_dc + 0.5) for f_dc 0, 1, -1
    scales = bytes([0, 160, 240])            # 16 * (log-scale + 10) for -10, 0, 5
    # q (w, x, y, z) = (0.5, -0.5, 0.5, -0.5): in x, y, z, w order the largest |component| is x
    # (index 0, the first of the ties), negative, so the others' signs flip: y -> 1, z -> 0, w -> 1;
    # magnitudes int(511 * 0.5 / sqrt(1/2) + 0.5) = 361; 512 + 361 = 873.
    rotations = struct.pack("<I", (0 << 30) | (873 << 20) | (361 << 10) | 873)
    # SH coefficient-major, channel innermost; round(128 c) + 128 to multiples of 8 (degree 1, 5 bits)
    sh = bytes([192, 96, 128,                # 0.5, -0.25, 0
                144, 128, 128,               # 0.1 -> 141 -> 144, 0, 0
                128, 128, 0])                # 0, 0, -1
    cloud = GaussianCloud(means=[[1.0, -0.5, 0.25]], scales=[[-10.0, 0.0, 5.0]], quats=[[0.5, -0.5, 0.5, -0.5]],
                          opacities=[0.0], sh_dc=[[0.0, 1.0, -1.0]],
                          sh_rest=[[[0.5, -0.25, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, -1.0]]])
    return header + positions + alphas + colors + scales + rotations + sh, cloud


def test_spz_v3_bytes_by_hand(tmp_path):
    payload, cloud = _spz_v3_payload()
    written = write_spz(cloud, tmp_path / "ours.spz")
    assert written.read_bytes()[:2] == b"\x1f\x8b"
    assert gzip.decompress(written.read_bytes()) == payload
    (tmp_path / "hand.spz").write_bytes(gzip.compress(payload))
    back = read_splat_file(tmp_path / "hand.spz")
    np.testing.assert_array_equal(back.means, cloud.means)
    np.testing.assert_array_equal(back.scales, cloud.scales)
    np.testing.assert_allclose(back.sh_dc, [[0.5 / 255 / 0.15, (166 / 255 - 0.5) / 0.15, (89 / 255 - 0.5) / 0.15]],
                               rtol=1e-5)
    np.testing.assert_allclose(back.sh_rest, [[[0.5, -0.25, 0], [0.125, 0, 0], [0, 0, -1]]])
    small = math.sqrt(0.5) * 361 / 511
    np.testing.assert_allclose(back.quats, [[-small, math.sqrt(1 - 3 * small ** 2), -small, small]], rtol=1e-5)
    assert quat_error(back.quats, cloud.quats)[0] < 2e-3
    assert back.opacities[0] == pytest.approx(logit(128 / 255), rel=1e-5)
    h = read_spz_header(tmp_path / "hand.spz")
    assert (h.version, h.count, h.sh_degree, h.fractional_bits) == (3, 1, 1, 12)


def test_spz_v2_rotation_bytes_by_hand(tmp_path):
    # (w, x, y, z) = (-0.6, 0, 0.8, 0): w < 0, so -q is stored: 127.5 - 127.5 * (0, 0.8, 0) -> 128, 26, 128
    cloud = GaussianCloud(means=[[0.0, 0, 0]], scales=[[0.0, 0, 0]], quats=[[-0.6, 0.0, 0.8, 0.0]],
                          opacities=[0.0], sh_dc=[[0.0, 0, 0]])
    payload = gzip.decompress(write_spz(cloud, tmp_path / "v2.spz", version=2).read_bytes())
    assert payload[:8] == b"NGSP" + struct.pack("<I", 2)
    assert payload[16 + 9 + 1 + 3 + 3:] == bytes([128, 26, 128])
    back = read_spz(tmp_path / "v2.spz")
    x, y = 128 / 127.5 - 1, 26 / 127.5 - 1
    np.testing.assert_allclose(back.quats, [[math.sqrt(1 - 2 * x * x - y * y), x, y, x]], rtol=1e-5)


@requires_zstd
def test_spz_v4_layout_by_hand(tmp_path):
    payload, cloud = _spz_v3_payload()
    body = payload[16:]
    sizes = {"positions": 9, "alphas": 1, "colors": 3, "scales": 3, "rotations": 4, "sh": 9}
    streams, pos = [], 0
    for size in sizes.values():
        streams.append(body[pos:pos + size])
        pos += size
    frames = [_zstd.ZstdCompressor(level=3).compress(s) for s in streams]
    header = b"NGSP" + struct.pack("<IIBBBBI12x", 4, 1, 1, 12, 0, len(frames), 32)
    toc = b"".join(struct.pack("<QQ", len(fr), len(s)) for fr, s in zip(frames, streams))
    (tmp_path / "hand4.spz").write_bytes(header + toc + b"".join(frames))
    hand = read_splat_file(tmp_path / "hand4.spz")
    v3 = read_splat_file(write_spz(cloud, tmp_path / "v3.spz"))
    for name, value in v3.arrays().items():
        np.testing.assert_array_equal(getattr(hand, name), value, err_msg=name)
    ours = write_spz(cloud, tmp_path / "ours4.spz", version=4).read_bytes()
    assert ours[:48] == header + struct.pack("<QQ", len(_zstd.ZstdCompressor(level=3).compress(streams[0])), 9)
    assert detect_format(tmp_path / "ours4.spz") == "spz"


def _compressed_header(n_chunks, n, k3=0, colors=True) -> bytes:
    props = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
             "max_scale_x", "max_scale_y", "max_scale_z"] + (["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
                                                              if colors else [])
    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {n_chunks}"]
    lines += [f"property float {p}" for p in props]
    lines += [f"element vertex {n}"] + [f"property uint packed_{p}" for p in ("position", "rotation", "scale",
                                                                              "color")]
    if k3:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(k3)]
    return ("\n".join(lines) + "\nend_header\n").encode()


def test_compressed_ply_bytes_by_hand(tmp_path):
    # Reading: one chunk with bounds laid out by hand, one Gaussian, no chunk colours.
    chunk = struct.pack("<12f", 0, 0, 0, 2, 1, 4, -5, -5, -5, -1, -1, -1)
    position = (1024 << 21) | (1023 << 11) | 512           # t = 1024/2047, 1, 512/2047
    scale = (0 << 21) | (0 << 11) | 2047                   # t = 0, 0, 1
    color = (255 << 24) | (0 << 16) | (51 << 8) | 255      # rgb 1, 0, 0.2; alpha code 255
    rotation = (2 << 30) | (512 << 20) | (256 << 10) | 768  # largest is rot_2 (y)
    vertex = struct.pack("<4I", position, rotation, scale, color)
    (tmp_path / "hand.ply").write_bytes(_compressed_header(1, 1, colors=False) + chunk + vertex)
    assert detect_format(tmp_path / "hand.ply") == "compressed_ply"
    back = read_splat_file(tmp_path / "hand.ply")
    np.testing.assert_allclose(back.means, [[2 * 1024 / 2047, 1, 4 * 512 / 2047]], rtol=1e-6)
    np.testing.assert_allclose(back.scales, [[-5, -5, -1]], rtol=1e-6)
    np.testing.assert_allclose(back.sh_dc, rgb_to_dc(np.array([[1.0, 0.0, 0.2]])), rtol=1e-5)
    a, b, c = ((code / 1023 - 0.5) * math.sqrt(2) for code in (512, 256, 768))
    np.testing.assert_allclose(back.quats, [[a, b, math.sqrt(1 - a * a - b * b - c * c), c]], atol=1e-6)
    assert back.opacities[0] == pytest.approx(logit(254.75 / 255), rel=1e-5)

    # Writing one SH-degree-1 Gaussian: its chunk's bounds are its own values, every t is 0.
    cloud = GaussianCloud(means=[[1.0, 2, 3]], scales=[[-1.0, -2, -3]], quats=[[2.0, 0, 0, 0]], opacities=[0.0],
                          sh_dc=[[0.0, 0, 0]], sh_rest=[[[0.0, 1.0, -4.0], [0.0, 0, 0], [0.0, 0, 0]]])
    data = write_compressed_ply(cloud, tmp_path / "one.ply").read_bytes()
    head = data[:data.index(b"end_header\n") + 11]
    body = data[len(head):]
    assert body[:72] == struct.pack("<18f", 1, 2, 3, 1, 2, 3, -1, -2, -3, -1, -2, -3, .5, .5, .5, .5, .5, .5)
    # identity: largest rot_0, others 0 -> floor(0.5 * 1023 + 0.5) = 512; alpha floor(127.5 + 0.5) = 128
    assert body[72:88] == struct.pack("<4I", 0, (512 << 20) | (512 << 10) | 512, 0, 128)
    # channel-major uchar f_rest: red (0, 0, 0), green (1, 0, 0), blue (-4, 0, 0): trunc((v / 8 + 0.5) * 256)
    assert body[88:] == bytes([128, 128, 128, 160, 128, 128, 0, 128, 128])


# ============================================================================== round trips

def _check_bounds(fmt, cloud, back):
    n = len(cloud)
    assert len(back) == n
    if fmt == "splat":
        np.testing.assert_array_equal(back.means, cloud.means)
        assert np.abs(back.scales - cloud.scales).max() < 1e-5
        assert quat_error(back.quats, cloud.quats).max() <= 1 / 128 + 1e-3
        assert np.abs(back.sh_dc - cloud.sh_dc).max() <= 0.5 / 255 / SH_C0 + 1e-5
        assert back.sh_degree == 0
        return
    assert back.sh_degree == cloud.sh_degree
    alpha_err = np.abs(sigmoid(back.opacities) - sigmoid(cloud.opacities)).max()
    assert alpha_err <= 0.5 / 255 + 1e-6
    if fmt.startswith("spz"):
        assert np.abs(back.means - cloud.means).max() <= 2.0 ** -13 + 1e-6
        assert np.abs(back.scales - cloud.scales).max() <= 1 / 32 + 1e-5
        assert np.abs(back.sh_dc - cloud.sh_dc).max() <= 0.5 / 255 / 0.15 + 1e-5
        if fmt == "spz2":
            assert xyz_error(back.quats, cloud.quats).max() <= 1 / 127.5  # a step: |xyz| > 1 is renormalised
        else:
            assert quat_error(back.quats, cloud.quats).max() <= 2e-3
        if cloud.sh_degree:
            err = np.abs(back.sh_rest - cloud.sh_rest)
            assert err[:, :3].max() <= 4.5 / 128 + 1e-6          # degree 1: multiples of 8/128
            assert err[:, 3:].max(initial=0) <= 8.5 / 128 + 1e-6  # higher: multiples of 16/128
    else:  # compressed PLY: half a step of each chunk's extent
        for start in range(0, n, 256):
            sl = slice(start, start + 256)
            for got, want, steps in ((back.means, cloud.means, (2047, 1023, 2047)),
                                     (back.scales, cloud.scales, (2047, 1023, 2047))):
                extent = want[sl].max(0) - want[sl].min(0)
                assert (np.abs(got[sl] - want[sl]) <= 0.5 * extent / np.array(steps) + 1e-5).all()
            rgb = cloud.sh_dc[sl] * SH_C0
            bound = 0.5 * (rgb.max(0) - rgb.min(0)) / 255 / SH_C0 + 1e-5
            assert (np.abs(back.sh_dc[sl] - cloud.sh_dc[sl]) <= bound).all()
        assert quat_error(back.quats, cloud.quats).max() <= 2e-3
        assert np.abs(back.sh_rest - cloud.sh_rest).max(initial=0) <= 1 / 32 + 1e-6


WRITERS = {"splat": write_splat, "spz3": write_spz, "spz2": lambda c, p: write_spz(c, p, version=2),
           "spz4": lambda c, p: write_spz(c, p, version=4), "compressed": write_compressed_ply}


@pytest.mark.parametrize("fmt", list(WRITERS))
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_within_quantisation(tmp_path, fmt, degree):
    if fmt == "spz4" and _zstd is None:
        pytest.skip("zstandard is not installed (.spz version 4 needs it)")
    cloud = make_cloud(n=700, degree=degree, seed=degree)
    path = quiet(WRITERS[fmt], cloud, tmp_path / f"c.{'splat' if fmt == 'splat' else 'spz' if 'spz' in fmt else 'ply'}")
    back = read_splat_file(path)
    assert all(a.dtype == np.float32 and np.isfinite(a).all() for a in back.arrays().values())
    _check_bounds(fmt, cloud, back)
    # Encoding what was decoded keeps it: the same values (the same codes), except that quaternions
    # are renormalised (and .splat scales go through log and exp), which stays within the step.
    again = read_splat_file(quiet(WRITERS[fmt], back, tmp_path / ("again" + path.suffix)))
    for name, value in back.arrays().items():
        if name == "quats":
            err = (xyz_error if fmt == "spz2" else quat_error)(getattr(again, name), value)
            assert err.max() <= 8e-3
        elif fmt == "compressed" or (fmt == "splat" and name == "scales"):
            np.testing.assert_allclose(getattr(again, name), value, rtol=1e-5, atol=2e-2, err_msg=name)
        else:
            np.testing.assert_array_equal(getattr(again, name), value, err_msg=name)


@st.composite
def clouds(draw):
    degree = draw(st.integers(0, 3))
    n = draw(st.integers(1, 600))
    return make_cloud(n=n, degree=degree, seed=draw(st.integers(0, 2 ** 32 - 1)),
                      sh_range=draw(st.floats(0.01, 1.0)))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cloud=clouds(), fmt=st.sampled_from(["splat", "spz3", "spz2", "compressed"]))
def test_property_round_trip(tmp_path, cloud, fmt):
    path = quiet(WRITERS[fmt], cloud, tmp_path / f"p.{fmt}")
    _check_bounds(fmt, cloud, read_splat_file(path))


def test_reference_ply_round_trip_stays_byte_identical(tmp_path):
    cloud = make_cloud(n=50, degree=2)
    a = write_ply(cloud, tmp_path / "a.ply")
    b = write_ply(read_splat_file(a), tmp_path / "b.ply")
    assert a.read_bytes() == b.read_bytes()


def test_write_splat_file_dispatches_on_the_name(tmp_path):
    cloud = make_cloud(n=10, degree=1)
    for name, fmt in (("a.spz", "spz"), ("a.splat", "splat"), ("a.compressed.ply", "compressed_ply"),
                      ("a.ply", "ply"), ("A.SOG", "sog"), ("scene/meta.json", "sog")):
        assert detect_format(quiet(write_splat_file, cloud, tmp_path / name)) == fmt
    assert read_spz_header(write_splat_file(cloud, tmp_path / "v2.spz", spz_version=2)).version == 2


def test_write_splat_file_refuses_names_it_cannot_write(tmp_path):
    """A name without a known ending is refused before any file is touched (no silent PLY)."""
    cloud = make_cloud(n=10, degree=1)
    (tmp_path / "keep.xyz").write_bytes(b"old")
    for name in ("x.sogg", "keep.xyz", "noext", "lod-meta.json", "x.ply.bak"):
        with pytest.raises(PlyError, match=r"cannot tell which splat format.*\.compressed\.ply, \.ply, \.spz, "
                           r"\.splat, \.sog, meta\.json") as exc:
            write_splat_file(cloud, tmp_path / name)
        assert str(tmp_path / name) in str(exc.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.xyz"]
    assert (tmp_path / "keep.xyz").read_bytes() == b"old"


# ========================================================================= numerical robustness

def test_splat_non_finite_zero_and_negative_values(tmp_path):
    rows = [struct.pack("<3f3f4B4B", 0, 0, 0, 1, 1, 1, 9, 9, 9, 9, 200, 128, 128, 128),
            struct.pack("<3f3f4B4B", float("nan"), 0, 0, 1, 1, 1, 9, 9, 9, 9, 200, 128, 128, 128),
            struct.pack("<3f3f4B4B", 0, 0, 0, 0.0, 1, 1, 9, 9, 9, 9, 128, 128, 128, 128),   # zero scale, zero quat
            struct.pack("<3f3f4B4B", 0, 0, 0, -1.0, 1, 1, 9, 9, 9, 9, 200, 128, 128, 128)]  # negative scale
    path = tmp_path / "bad.splat"
    path.write_bytes(b"".join(rows))
    with pytest.raises(PlyError, match=r"2 Gaussian\(s\) with non-finite.*rows \[1, 3\]") as exc:
        quiet(read_splat_file, path)
    assert str(path) in str(exc.value)
    with pytest.warns(UserWarning, match="dropped 2 of 4"), pytest.warns(InfinitiesReadWarning, match="flat axes"):
        ok = read_splat_file(path, sanitize=True)
    assert len(ok) == 2 and ok.scales[1, 0] == LOG_SCALE_RANGE[0]
    np.testing.assert_array_equal(ok.quats[1], [0, 0, 0, 0])  # the zero quaternion is kept, identity on use
    np.testing.assert_array_equal(ok.validate().zero_quat_rows, [1])


def test_every_reader_reads_meaningful_infinities(tmp_path):
    """The same rule as read_ply (test_ply): a zero .splat scale and a compressed PLY chunk whose
    smallest log-scale is -inf are flat axes, kept with a warning; the rows stay."""
    cloud = make_cloud(n=300, degree=0)
    data = bytearray(quiet(write_splat, cloud, tmp_path / "z.splat").read_bytes())
    data[12:16] = struct.pack("<f", 0.0)  # the first Gaussian's x scale
    (tmp_path / "z.splat").write_bytes(bytes(data))
    with pytest.warns(InfinitiesReadWarning, match=r"1 log-scale\(s\) of -inf as -30"):
        back = read_splat_file(tmp_path / "z.splat")
    assert len(back) == 300 and back.scales[0, 0] == LOG_SCALE_RANGE[0]
    cloud.scales[:256, 1] = np.linspace(-5, -1, 256)
    data = bytearray(write_compressed_ply(cloud, tmp_path / "c.ply").read_bytes())
    start = data.index(b"end_header\n") + 11
    data[start + 4 * 7:start + 4 * 8] = struct.pack("<f", -np.inf)  # chunk 0's min_scale_y
    (tmp_path / "c.ply").write_bytes(bytes(data))
    with pytest.warns(InfinitiesReadWarning, match=r"log-scale\(s\) of -inf"):
        back = read_splat_file(tmp_path / "c.ply")
    assert len(back) == 300 and back.scales[0, 1] == LOG_SCALE_RANGE[0] and np.isfinite(back.scales).all()


def test_compressed_ply_non_finite_chunk_bounds(tmp_path):
    cloud = make_cloud(n=300, degree=0)
    data = bytearray(write_compressed_ply(cloud, tmp_path / "c.ply").read_bytes())
    start = data.index(b"end_header\n") + 11
    data[start + 4 * 18:start + 4 * 19] = struct.pack("<f", float("inf"))  # chunk 1's min_x
    (tmp_path / "c.ply").write_bytes(bytes(data))
    # (the one Gaussian at the top of the chunk's x range, t = 1, reads as max_x: finite)
    with pytest.raises(PlyError, match=r"43 Gaussian\(s\) with non-finite.*rows \[256, 257"):
        read_compressed_ply(tmp_path / "c.ply")
    with pytest.warns(UserWarning, match="dropped 43 of 300"):
        assert len(read_splat_file(tmp_path / "c.ply", sanitize=True)) == 257


@pytest.mark.parametrize("writer", [write_splat, write_spz, write_compressed_ply])
def test_writers_refuse_non_finite_and_leave_nothing(tmp_path, writer):
    cloud = make_cloud(n=5, degree=1)
    cloud.scales[3, 1] = np.inf
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(PlyError, match=r"non-finite parameters, rows \[3\]"):
        quiet(writer, cloud, out / "x.bin")
    assert_no_leftovers(out)


def test_spz_extreme_values(tmp_path):
    cloud = make_cloud(n=4, degree=0)
    cloud.scales[0] = [100.0, -100.0, 0.0]   # clamped to what 8 bits hold
    cloud.quats[1] = 0.0                      # zero quaternion -> identity
    cloud.means[2] = [3000.0, -5000.0, 1.0]   # beyond 2048: fewer fractional bits
    back = read_spz(write_spz(cloud, tmp_path / "x.spz"))
    np.testing.assert_array_equal(back.scales[0], [255 / 16 - 10, -10.0, 0.0])
    np.testing.assert_allclose(back.quats[1], [1, 0, 0, 0], atol=2e-3)
    assert read_spz_header(tmp_path / "x.spz").fractional_bits == 10
    assert np.abs(back.means - cloud.means).max() <= 2.0 ** -11
    cloud.means[3, 0] = 2.0 ** 24
    with pytest.raises(PlyError, match="beyond what .spz holds"):
        write_spz(cloud, tmp_path / "far.spz")
    assert not (tmp_path / "far.spz").exists()


def test_spz_extras_are_reported_not_written(tmp_path):
    cloud = make_cloud(n=3, degree=0).replace(extra={"gvae_step": np.arange(3, dtype=np.int32)})
    with pytest.warns(UserWarning, match=r"\.spz holds no extra properties; not written: gvae_step"):
        write_spz(cloud, tmp_path / "e.spz")
    assert read_spz(tmp_path / "e.spz").extra == {}


# ================================================================ .spz container details

def _legacy(payload_after_header: bytes, *, version=3, n=1, degree=0, flags=0) -> bytes:
    return b"NGSP" + struct.pack("<IIBBBB", version, n, degree, 12, flags, 0) + payload_after_header


def test_spz_degree_4_is_read_as_degree_3(tmp_path):
    sh = bytes(range(72))
    path = tmp_path / "d4.spz"
    path.write_bytes(gzip.compress(_legacy(bytes(9) + bytes([128]) + bytes(3) + bytes(3) + bytes(4) + sh, degree=4)))
    with pytest.warns(UserWarning, match="SH degree 4 read as degree 3"):
        back = read_spz(path)
    assert back.sh_degree == 3
    np.testing.assert_array_equal(back.sh_rest.reshape(-1), (np.arange(45) - 128) / 128)


def test_spz_extension_records_are_skipped_wherever_they_are(tmp_path):
    data = bytes(9) + bytes([128]) + bytes(3) + bytes(3) + bytes(4)
    record = struct.pack("<II", 0xADBE0002, 12) + struct.pack("<3f", 0.1, 0.2, 3.0)
    for i, body in enumerate((data + record, record + data)):
        path = tmp_path / f"ext{i}.spz"
        path.write_bytes(gzip.compress(_legacy(body, flags=2)))
        np.testing.assert_array_equal(read_spz(path).means, [[0, 0, 0]])
    path.write_bytes(gzip.compress(_legacy(data + b"\x01\x02\x03", flags=2)))
    with pytest.raises(PlyError, match="not well-formed extension records"):
        read_spz(path)
    path.write_bytes(gzip.compress(_legacy(data + b"\x01")))
    with pytest.raises(PlyError, match="more than the 1 Gaussians"):
        read_spz(path)


def test_spz_gzip_but_not_spz_and_unknown_versions(tmp_path):
    path = tmp_path / "x.spz"
    path.write_bytes(gzip.compress(b"hello world, not a splat"))
    with pytest.raises(PlyError, match="gzip data but not an .spz file"):
        read_splat_file(path)
    path.write_bytes(gzip.compress(_legacy(bytes(20), version=9)))
    with pytest.raises(PlyError, match="unsupported .spz version 9"):
        read_splat_file(path)
    path.write_bytes(b"NGSP" + struct.pack("<IIBBBBI12x", 3, 1, 0, 12, 0, 5, 32))
    with pytest.raises(PlyError, match="unsupported .spz version 3 in a NGSP container"):
        read_splat_file(path)


# ============================================================= detection, corrupt and truncated

def test_detection_is_by_content_not_extension(tmp_path):
    cloud = make_cloud(n=20, degree=1)
    write_spz(cloud, tmp_path / "really_spz.ply")
    assert detect_format(tmp_path / "really_spz.ply") == "spz"
    write_compressed_ply(cloud, tmp_path / "packed.ply")
    assert detect_format(tmp_path / "packed.ply") == "compressed_ply"
    with pytest.raises(PlyError, match="compressed .SuperSplat. PLY.*read_splat_file"):
        quiet(read_ply, tmp_path / "packed.ply")
    quiet(write_splat, cloud, tmp_path / "records.bin")
    assert detect_format(tmp_path / "records.bin") == "splat"
    assert len(read_splat_file(tmp_path / "records.bin")) == 20
    (tmp_path / "noise.bin").write_bytes(np.full(64, 0xFF, np.uint8).tobytes())  # NaN floats: not Gaussians
    with pytest.raises(PlyError, match="not a splat file this reader knows") as exc:
        read_splat_file(tmp_path / "noise.bin")
    assert str(tmp_path / "noise.bin") in str(exc.value)
    write_ply(cloud, tmp_path / "plain.splat")  # a PLY whatever its name
    assert detect_format(tmp_path / "plain.splat") == "ply"


def _seed_files(folder) -> dict[str, bytes]:
    cloud = make_cloud(n=300, degree=1, seed=7)
    seeds = {"splat": quiet(write_splat, cloud, folder / "s.splat").read_bytes(),
             "spz": write_spz(cloud, folder / "s.spz").read_bytes(),
             "spz2": write_spz(cloud, folder / "s2.spz", version=2).read_bytes(),
             "compressed": write_compressed_ply(cloud, folder / "s.ply").read_bytes()}
    if _zstd is not None:
        seeds["spz4"] = write_spz(cloud, folder / "s4.spz", version=4).read_bytes()
    return seeds


@pytest.fixture(scope="module")
def seed_files(tmp_path_factory):
    return _seed_files(tmp_path_factory.mktemp("seeds"))


SUFFIX = {"splat": ".splat", "spz": ".spz", "spz2": ".spz", "spz4": ".spz", "compressed": ".ply"}


@pytest.mark.parametrize("fmt", list(SUFFIX))
def test_truncated_files_raise_ply_error(tmp_path, seed_files, fmt):
    if fmt not in seed_files:
        pytest.skip("zstandard is not installed (.spz version 4 needs it)")
    data = seed_files[fmt]
    path = tmp_path / ("t" + SUFFIX[fmt])
    # (a .splat has no header: one cut at a record boundary reads as a smaller file, so cuts here are not)
    for cut in (0, 3, 10, 17, 40, len(data) // 2 + 5, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(PlyError) as exc:
            read_splat_file(path)
        assert str(path) in str(exc.value), (cut, str(exc.value))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fmt=st.sampled_from(sorted(SUFFIX)), ops=EDITS)
def test_property_corruption_only_raises_ply_error(tmp_path, seed_files, fmt, ops):
    if fmt not in seed_files:
        return
    data = seed_files[fmt]
    path = tmp_path / ("c" + SUFFIX[fmt])
    path.write_bytes(corrupt(data, ops, head_len=min(64, len(data))))
    read_or_refuse(read_splat_file, path)


def test_read_splat_alone_rejects_a_partial_record(tmp_path):
    (tmp_path / "p.splat").write_bytes(bytes(33))
    with pytest.raises(PlyError, match="not a whole number of 32-byte records"):
        read_splat(tmp_path / "p.splat")


# ===================================================================================== the CLI

def test_cli_info_names_the_format(tmp_path, capsys):
    cloud = make_cloud(n=40, degree=2)
    for name, writer, label in (("a.spz", write_spz, "Niantic .spz"), ("b.splat", write_splat, ".splat (web"),
                                ("c.ply", write_compressed_ply, "compressed PLY (SuperSplat)")):
        path = quiet(writer, cloud, tmp_path / name)
        assert main(["info", str(path)]) == 0
        out = capsys.readouterr().out
        assert f"{path} ({label}" in out and "Gaussians: 40" in out
        assert f"SH degree: {0 if name.endswith('splat') else 2}" in out
    (tmp_path / "cut.spz").write_bytes((tmp_path / "a.spz").read_bytes()[:30])
    assert main(["info", str(tmp_path / "cut.spz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "cut.spz") in err[0] and "truncated" in err[0]


def test_cli_refine_reads_every_format(tmp_path, capsys, monkeypatch):
    """`gvae refine` reads its input with read_splat_file (the refinement itself is stubbed: test_refine
    covers it); the SH degree and values reach it as the file holds them."""
    seen = []

    def fake_refine(cloud, **kwargs):
        seen.append(cloud)
        return types.SimpleNamespace(cloud=cloud, summary=lambda: "refined (stub)")

    monkeypatch.setattr("gvae_core.refinement.refine", fake_refine)
    cloud = make_cloud(n=30, degree=1)
    for name, writer in (("in.spz", write_spz), ("in.splat", write_splat), ("in.ply", write_compressed_ply)):
        src = quiet(writer, cloud, tmp_path / name)
        assert main(["refine", str(src), str(tmp_path / "out.ply"), "--budget", "all"]) == 0
        assert f"read {src}" in capsys.readouterr().out
        back = read_splat_file(src)
        for field, value in back.arrays().items():
            np.testing.assert_array_equal(getattr(seen[-1], field), value, err_msg=field)
        np.testing.assert_array_equal(read_ply(tmp_path / "out.ply").means, back.means)
    # an OUT name no format is written under is refused before the input is read or refined
    calls = len(seen)
    assert main(["refine", str(src), str(tmp_path / "out.xyz"), "--budget", "all"]) == 2
    assert "cannot tell which splat format" in capsys.readouterr().err and len(seen) == calls


def test_cli_convert_between_formats(tmp_path, capsys):
    cloud = make_cloud(n=60, degree=3)
    src = write_ply(cloud, tmp_path / "in.ply")
    for name, label in (("a.spz", "Niantic .spz"), ("b.splat", ".splat (web viewers)"),
                        ("c.compressed.ply", "compressed PLY (SuperSplat)"), ("d.ply", "3DGS PLY")):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # .splat drops the SH and says so
            assert main(["convert", str(src), str(tmp_path / name)]) == 0
        out = capsys.readouterr().out
        assert f"-> {tmp_path / name} ({label}" in out and "60 Gaussians" in out
        back = read_splat_file(tmp_path / name)
        assert len(back) == 60 and back.sh_degree == (0 if name.endswith("splat") else 3)
    assert (tmp_path / "d.ply").read_bytes() == src.read_bytes()
    assert main(["convert", str(tmp_path / "a.spz"), str(tmp_path / "e.spz"), "--spz-version", "2",
                 "--sh-degree", "1"]) == 0
    assert "SH degree 1 (of 3)" in capsys.readouterr().out
    assert read_spz_header(tmp_path / "e.spz").version == 2 and read_spz(tmp_path / "e.spz").sh_degree == 1
    # Errors: one line naming the file; an OUT name no format has is refused before IN is read.
    for argv, message in ((["missing.ply", str(tmp_path / "x.txt")], "cannot tell which splat format"),
                          ([str(src), str(tmp_path / "x.ply"), "--spz-version", "4"], "applies to .spz output"),
                          ([str(tmp_path / "nothing.ply"), str(tmp_path / "x.spz")], "nothing.ply")):
        assert main(["convert", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    assert not (tmp_path / "x.txt").exists() and not (tmp_path / "x.ply").exists()


def test_spz_version_1_float16_positions(tmp_path):
    positions = np.array([[1.5, -2.0, 0.25], [np.inf, 0, 0]], "<f2").tobytes()
    body = positions + bytes([128, 128]) + bytes(6) + bytes(6) + bytes([128, 128, 128] * 2)
    path = tmp_path / "v1.spz"
    path.write_bytes(gzip.compress(_legacy(body, version=1, n=2)))
    with pytest.raises(PlyError, match=r"1 Gaussian\(s\) with non-finite.*rows \[1\]"):
        read_spz(path)
    with pytest.warns(UserWarning, match="dropped 1 of 2"):
        back = read_spz(path, sanitize=True)
    np.testing.assert_array_equal(back.means, [[1.5, -2.0, 0.25]])
    np.testing.assert_allclose(back.quats, [[1, 128 / 127.5 - 1, 128 / 127.5 - 1, 128 / 127.5 - 1]], atol=1e-4)


def test_spz_rounds_halves_away_from_zero_as_niantic(tmp_path):
    """C's round(): a position exactly half a step from two codes goes away from zero (numpy would
    round it to even), in the arrays and in the scalar that picks the fractional bits."""
    step = 2.0 ** -12
    cloud = GaussianCloud(means=[[0.5 * step, -0.5 * step, 1.5 * step]], scales=[[-10.0 + 1 / 32, 0, 0]],
                          quats=[[1.0, 0, 0, 0]], opacities=[0.0], sh_dc=[[0.0, 0, 0]])
    back = read_spz(write_spz(cloud, tmp_path / "h.spz"))
    np.testing.assert_array_equal(back.means, [[step, -step, 2 * step]])
    assert back.scales[0, 0] == -10.0 + 1 / 16  # 16 * (1/32) = 0.5 -> 1
