"""PlayCanvas's SOG: meta.json + WebP images, bundled (.sog zip) or in a folder.

Files laid out by hand from the format's description (images made with Pillow, meta.json and the zip
by hand) are read to the values the formulas give; the writer's images are checked code by code on
hand-picked Gaussians; round trips hold each attribute to its quantisation; the codebook and k-means
kernels are held to their slow references; corrupt, truncated and non-finite input raises PlyError
naming the file. splat-transform itself is in test_splat_transform.py."""

from __future__ import annotations

import io
import json
import math
import warnings
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from PIL import Image

from tests.corruption import EDITS, corrupt, read_or_refuse
from tests.test_formats import make_cloud, quat_error, quiet, sigmoid

from gvae_core import GaussianCloud, PlyError, read_splat_file
from gvae_core.cli import main
from gvae_core.formats import detect_format, read_sog, write_sog, write_splat_file
from gvae_core.formats import _quantize as quantize
from gvae_core.formats.sog import encode_sog, morton_order, palette_size, texture_size
from gvae_core.ply import InfinitiesReadWarning


def webp(rgba) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgba, np.uint8), "RGBA").save(buf, "WEBP", lossless=True, exact=True)
    return buf.getvalue()


def image(pixels, width=4, height=4) -> np.ndarray:
    """A width x height RGBA image whose first pixels are `pixels` (rows of 4 bytes)."""
    out = np.zeros((width * height, 4), np.uint8)
    out[:len(pixels)] = pixels
    return out.reshape(height, width, 4)


def bundle(path, meta: dict, images: dict[str, np.ndarray]):
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("meta.json", json.dumps(meta))
        for name, rgba in images.items():
            z.writestr(name, webp(rgba))
    return path


def folder(path, meta: dict, images: dict[str, np.ndarray]):
    path.mkdir(parents=True, exist_ok=True)
    (path / "meta.json").write_text(json.dumps(meta))
    for name, rgba in images.items():
        (path / name).write_bytes(webp(rgba))
    return path / "meta.json"


def hand_scene():
    """Two SH-degree-1 Gaussians laid out by hand, and the values splat-transform's decode gives."""
    mins, maxs = [-1.0, 0.0, -2.0], [1.0, 2.0, 0.0]
    x_code = [0, 65535]                 # x: v = -1 -> -(e - 1); v = 1 -> e - 1
    y_code = [32768, 1]                 # y: v = 2 * 32768 / 65535
    z_code = [65535, 0]                 # z: v = 0 -> 0; v = -2 -> -(e^2 - 1)
    lo = [[x & 255, y & 255, z & 255, 255] for x, y, z in zip(x_code, y_code, z_code)]
    hi = [[x >> 8, y >> 8, z >> 8, 255] for x, y, z in zip(x_code, y_code, z_code)]
    # quats: largest is x (tag 253) with the others (w, y, z) = codes 255, 0, 128; then a bad tag.
    quats = [[255, 0, 128, 253], [1, 2, 3, 7]]
    scale_book = [-8.0 + i / 16 for i in range(256)]
    dc_book = [(i - 128) / 64 for i in range(256)]
    sh_book = [(i - 128) / 128 for i in range(256)]
    scales = [[0, 128, 255, 255], [16, 16, 16, 255]]
    sh0 = [[128, 0, 255, 0], [64, 192, 129, 255]]       # alpha: opacity codes 0 and 255
    # palette of 2 entries x 3 coefficients: entry m, coefficient j -> pixel (m % 64) * 3 + j of row m // 64
    centroids = np.zeros((1, 192, 4), np.uint8)
    centroids[0, 0:3, :3] = [[128, 160, 96], [0, 255, 128], [130, 126, 128]]  # entry 0: (r, g, b) of j = 0..2
    centroids[0, 3:6, :3] = [[255, 255, 255], [0, 0, 0], [128, 128, 128]]    # entry 1
    labels = [[0, 0, 0, 255], [2, 0, 0, 255]]           # the second Gaussian's label 2 is past the palette
    meta = {"version": 2, "count": 2, "asset": {"generator": "hand"},
            "means": {"mins": mins, "maxs": maxs, "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": scale_book, "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": dc_book, "files": ["sh0.webp"]},
            "shN": {"count": 2, "bands": 1, "codebook": sh_book, "files": ["shN_centroids.webp", "shN_labels.webp"]}}
    images = {"means_l.webp": image(lo), "means_u.webp": image(hi), "quats.webp": image(quats),
              "scales.webp": image(scales), "sh0.webp": image(sh0), "shN_centroids.webp": centroids,
              "shN_labels.webp": image(labels)}

    def inv(v):
        return math.copysign(math.exp(abs(v)) - 1, v)

    means = [[inv(-1 + 2 * c / 65535) for c in x_code], [inv(2 * c / 65535) for c in y_code],
             [inv(-2 + 2 * c / 65535) for c in z_code]]
    a, b, c = ((code / 255 * 2 - 1) / math.sqrt(2) for code in (255, 0, 128))
    logit = lambda p: math.log(p / (1 - p))  # noqa: E731
    want = GaussianCloud(
        means=np.array(means).T, quats=[[a, math.sqrt(max(0, 1 - a * a - b * b - c * c)), b, c], [1, 0, 0, 0]],
        scales=[[scale_book[i] for i in row[:3]] for row in scales],
        sh_dc=[[dc_book[i] for i in row[:3]] for row in sh0],
        opacities=[logit(1e-6), logit(1 - 1e-6)],
        sh_rest=[[[sh_book[128], sh_book[160], sh_book[96]], [sh_book[0], sh_book[255], sh_book[128]],
                  [sh_book[130], sh_book[126], sh_book[128]]], np.zeros((3, 3))])
    return meta, images, want


def test_sog_bytes_by_hand(tmp_path):
    meta, images, want = hand_scene()
    sog = bundle(tmp_path / "hand.sog", meta, images)
    meta_json = folder(tmp_path / "scene", meta, images)
    for path in (sog, meta_json, meta_json.parent):
        assert detect_format(path) == "sog"
        back = read_splat_file(path)
        assert back.sh_degree == 1
        for name, value in want.arrays().items():
            np.testing.assert_allclose(getattr(back, name), value, rtol=1e-6, atol=1e-7, err_msg=f"{path} {name}")


def test_sog_version_1_by_hand(tmp_path):
    """The legacy layout (no "version"): per-channel lerps between mins and maxs, the opacity a logit."""
    lo = [[0, 0, 0, 255], [255, 255, 255, 255]]
    hi = [[0, 0, 0, 255], [255, 255, 255, 255]]
    meta = {"means": {"shape": [2, 3], "mins": [0, 0, 0], "maxs": [1, 1, 1], "files": ["ml.webp", "mu.webp"]},
            "scales": {"mins": [-5, -4, -3], "maxs": [-1, 0, 1], "files": ["s.webp"]},
            "quats": {"files": ["q.webp"]},
            "sh0": {"mins": [-1, -1, -1, -4], "maxs": [1, 1, 1, 4], "files": ["c.webp"]},
            "shN": {"mins": -0.5, "maxs": 0.5, "files": ["pal.webp", "lab.webp"]}}
    palette = np.zeros((1, 192, 4), np.uint8)
    palette[0, 3:6, :3] = 255  # entry 1 = all 0.5
    images = {"ml.webp": image(lo), "mu.webp": image(hi), "q.webp": image([[128, 128, 128, 252]] * 2),
              "s.webp": image([[0, 255, 51, 255], [255, 0, 0, 255]]),
              "c.webp": image([[255, 0, 51, 0], [0, 0, 0, 255]]),
              "pal.webp": palette, "lab.webp": image([[1, 0, 0, 255], [0, 0, 0, 255]])}
    back = read_splat_file(bundle(tmp_path / "v1.sog", meta, images))
    np.testing.assert_allclose(back.means, [[0, 0, 0], [math.e - 1] * 3], rtol=1e-6)
    np.testing.assert_allclose(back.scales, [[-5, 0, -3 + 4 * 0.2], [-1, -4, -3]], rtol=1e-6)
    np.testing.assert_allclose(back.sh_dc, [[1, -1, -1 + 0.4], [-1, -1, -1]], rtol=1e-6)
    np.testing.assert_allclose(back.opacities, [-4, 4])
    assert back.sh_degree == 1
    np.testing.assert_allclose(back.sh_rest[0], 0.5)
    np.testing.assert_allclose(back.sh_rest[1], -0.5)
    np.testing.assert_allclose(back.quats[:, 0], 1.0, atol=3e-3)


def test_writer_codes_by_hand():
    """Positions, rotations, opacities and labels of two hand-picked Gaussians, code by code."""
    cloud = GaussianCloud(means=[[0.0, 1.0, -3.0], [math.e - 1, 0.0, 1.0]], scales=[[-1.0, -2, -3], [-1, -1, -1]],
                          quats=[[0.0, -2.0, 0, 0], [0.0, 0.0, 0.0, 0.0]], opacities=[0.0, -100.0],
                          sh_dc=[[0.5, 0, 0], [0, 0, 0]])
    images, meta = encode_sog(cloud, morton=False)
    # x: v = 0 and 1 -> codes 0 and 65535; y: v = ln 2 and 0; z: v = -ln 4 and ln 2.
    assert meta["means"]["mins"] == pytest.approx([0.0, 0.0, -math.log(4)], rel=1e-7)
    assert meta["means"]["maxs"] == pytest.approx([1.0, math.log(2), math.log(2)], rel=1e-7)
    lo, hi = images["means_l.webp"].reshape(-1, 4), images["means_u.webp"].reshape(-1, 4)
    code = lo[:2, :3].astype(int) | (hi[:2, :3].astype(int) << 8)
    np.testing.assert_array_equal(code, [[0, 65535, 0], [65535, 0, 65535]])
    assert images["means_l.webp"].shape == (4, 4, 4)  # at least 4 x 4
    # (0, -2, 0, 0) -> unit (0, -1, 0, 0), largest x (tag 253) made positive; others 0 -> code 127.5 -> 128
    # a zero quaternion is the identity: tag 252
    q = images["quats.webp"].reshape(-1, 4)[:2]
    np.testing.assert_array_equal(q, [[128, 128, 128, 253], [128, 128, 128, 252]])
    sh0 = images["sh0.webp"].reshape(-1, 4)[:2]
    assert sh0[0, 3] == 128 and sh0[1, 3] == 0  # round(255 * 0.5); sigmoid(-100) -> 0
    book = np.array(meta["sh0"]["codebook"], np.float32)
    assert book[sh0[0, 0]] == np.float32(0.5) and book[sh0[1, 0]] == 0.0  # two values: exact
    assert "shN" not in meta and meta["version"] == 2 and meta["count"] == 2


def test_sizes_follow_splat_transform():
    assert [palette_size(n) for n in (1, 100, 1000, 1500, 4000, 20000, 10 ** 6)] == \
        [1, 64, 512, 1024, 2048, 16384, 65536]
    assert texture_size(0) == (4, 4) and texture_size(17) == (8, 4) and texture_size(10 ** 6) == (1000, 1000)


# ============================================================================== round trips

def _check_bounds(cloud: GaussianCloud, back: GaussianCloud, meta: dict):
    """Each attribute within its quantisation (rows in the file's order)."""
    assert len(back) == len(cloud) and back.sh_degree == cloud.sh_degree
    v = np.sign(cloud.means) * np.log1p(np.abs(cloud.means.astype(np.float64)))
    step = (np.array(meta["means"]["maxs"]) - meta["means"]["mins"]) / 65535
    bound = (np.abs(cloud.means) + 1) * np.expm1(step / 2) + 1e-6 * (np.abs(cloud.means) + 1)
    assert (np.abs(back.means - cloud.means) <= bound).all()
    assert v.shape == back.means.shape
    # the three smaller components within half a step, 1 / (255 sqrt 2); the largest, derived from
    # them, within 3 of those (it is at least 1/2, the others' sum at most sqrt(3 (1 - 1/4)))
    assert quat_error(back.quats, cloud.quats).max() <= 3 / 255 * 2 ** -0.5 * 1.05
    for name, key in (("scales", "scales"), ("sh_dc", "sh0")):
        book = np.array(meta[key]["codebook"], np.float32)
        nearest = book[quantize.nearest_in_codebook(getattr(cloud, name), book)]
        np.testing.assert_array_equal(getattr(back, name), nearest, err_msg=name)  # the nearest entry, exactly
    p, q = sigmoid(back.opacities), sigmoid(cloud.opacities)
    assert np.abs(p - q).max() <= 0.5 / 255 + 1e-6


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_within_quantisation(tmp_path, degree):
    cloud = make_cloud(n=700, degree=degree, seed=degree)
    cloud.opacities[:3] = [40.0, -40.0, 0.0]
    path = write_sog(cloud, tmp_path / "c.sog")
    assert zipfile.ZipFile(path).namelist()[0] == "meta.json"
    meta = json.loads(zipfile.ZipFile(path).read("meta.json"))
    back = read_sog(path)
    in_order = cloud.select(morton_order(cloud.means))
    _check_bounds(in_order, back, meta)
    if degree:
        assert meta["shN"]["count"] == palette_size(700) == 512 and meta["shN"]["bands"] == degree
        err = back.sh_rest - in_order.sh_rest
        assert np.sqrt((err ** 2).mean()) < 0.5 * np.sqrt((in_order.sh_rest ** 2).mean())  # a palette, not noise
    # The folder form holds the same scene; morton=False keeps the rows where they were.
    again = read_splat_file(write_sog(cloud, tmp_path / "dir" / "meta.json", morton=False))
    _check_bounds(cloud, again, json.loads((tmp_path / "dir" / "meta.json").read_text()))
    # Writing what was read gives the same values back (same codebooks, same codes).
    twice = read_sog(write_sog(back, tmp_path / "twice.sog", morton=False))
    for name in ("means", "scales", "opacities", "sh_dc"):
        np.testing.assert_allclose(getattr(twice, name), getattr(back, name), rtol=1e-6, atol=1e-6, err_msg=name)
    assert quat_error(twice.quats, back.quats).max() <= 3 / 255 * 2 ** -0.5 * 1.05


def test_sh_palette_is_exact_when_the_cloud_has_few_sh_vectors(tmp_path):
    """20 distinct SH-1 vectors (180 values: each its own codebook entry) come back exactly."""
    cloud = make_cloud(n=900, degree=1, seed=3)
    rng = np.random.default_rng(0)
    vectors = rng.uniform(-1, 1, (20, 3, 3)).astype(np.float32)
    cloud.sh_rest[:] = vectors[rng.integers(0, 20, 900)]
    back = read_sog(write_sog(cloud, tmp_path / "few.sog", morton=False))
    np.testing.assert_array_equal(back.sh_rest, cloud.sh_rest)


def test_the_same_cloud_gives_the_same_file(tmp_path):
    cloud = make_cloud(n=1500, degree=3, seed=5)
    a = write_sog(cloud, tmp_path / "a.sog").read_bytes()
    b = write_sog(cloud, tmp_path / "b.sog").read_bytes()
    assert a == b
    assert write_sog(cloud, tmp_path / "c.sog", seed=1).read_bytes() != a


def test_empty_and_single_gaussian(tmp_path):
    for n in (0, 1):
        cloud = make_cloud(n=n, degree=2)
        back = read_sog(write_sog(cloud, tmp_path / f"{n}.sog"))
        assert len(back) == n
        if n:
            np.testing.assert_allclose(back.sh_rest, cloud.sh_rest, atol=1e-6)  # its own palette entry


def test_extreme_values(tmp_path):
    """Zero and unnormalised quaternions, huge and tiny scales, a point 3000 units out, opacity 0 and 1."""
    cloud = make_cloud(n=300, degree=1, seed=2)
    cloud.quats[0] = 0
    cloud.quats[1] = [0, 0, 0, 1e-30]
    cloud.quats[2] *= 1e6
    cloud.scales[3] = [-30, 20, 0]
    cloud.means[4] = [3000.0, -3000.0, 0.5]
    cloud.opacities[5:7] = [-50, 50]
    back = read_sog(write_sog(cloud, tmp_path / "x.sog", morton=False))
    assert all(np.isfinite(a).all() for a in back.arrays().values())
    np.testing.assert_allclose(back.quats[0], [1, 0, 0, 0], atol=3e-3)
    np.testing.assert_allclose(back.means[4], cloud.means[4], rtol=2e-4)
    assert back.scales[3, 0] == min(back.scales.min(), -30) and back.scales[3, 1] == 20
    assert sigmoid(back.opacities[5]) < 1e-5 and sigmoid(back.opacities[6]) > 1 - 1e-5


def test_writer_refuses_non_finite_and_leaves_nothing(tmp_path):
    cloud = make_cloud(n=5, degree=1)
    cloud.sh_rest[2, 0, 1] = np.nan
    out = tmp_path / "out"
    out.mkdir()
    for name in ("x.sog", "d/meta.json"):
        with pytest.raises(PlyError, match=r"non-finite parameters, rows \[2\]"):
            write_sog(cloud, out / name)
    assert list(out.iterdir()) == []
    cloud = make_cloud(n=5, degree=0).replace(extra={"gvae_step": np.zeros(5, np.int32)})
    with pytest.warns(UserWarning, match="SOG holds no extra properties; not written: gvae_step"):
        write_sog(cloud, tmp_path / "e.sog")


def test_write_splat_file_and_cli_write_sog(tmp_path, capsys):
    cloud = make_cloud(n=200, degree=2)
    write_splat_file(cloud, tmp_path / "a.sog")
    write_splat_file(cloud, tmp_path / "b" / "meta.json")
    assert detect_format(tmp_path / "a.sog") == detect_format(tmp_path / "b") == "sog"
    ply = write_splat_file(cloud, tmp_path / "c.ply")
    assert main(["convert", str(ply), str(tmp_path / "d.sog"), "--sh-degree", "1"]) == 0
    assert "(SOG (PlayCanvas, SuperSplat)): 200 Gaussians, SH degree 1 (of 2)" in capsys.readouterr().out
    assert read_splat_file(tmp_path / "d.sog").sh_degree == 1
    assert main(["info", str(tmp_path / "b" / "meta.json")]) == 0
    out = capsys.readouterr().out
    assert "SOG (PlayCanvas, SuperSplat)" in out and "Gaussians: 200" in out and "SH degree: 2" in out


# ============================================================================ the kernels

def test_lloyd_matches_its_reference():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(150, 6)).astype(np.float32)
    points[100:110] = points[0]  # duplicates make empty clusters, which move to the farthest points
    start = points[rng.choice(150, 20, replace=False)]
    fast_c, fast_l = quantize.lloyd(points, start, 6)
    ref_c, ref_l = quantize.kmeans_reference(points, start, 6)
    np.testing.assert_array_equal(fast_l, ref_l)
    np.testing.assert_allclose(fast_c, ref_c, atol=1e-5)


def test_codebook_1d_matches_its_reference_and_is_exact_on_few_values():
    rng = np.random.default_rng(2)
    values = np.concatenate([rng.normal(size=700), rng.normal(20, 0.1, 5)])  # a sparse tail keeps its entries
    book, labels = quantize.codebook_1d(values, 16)
    assert np.all(np.diff(book) >= 0) and len(book) == 16
    np.testing.assert_array_equal(labels, quantize.codebook_labels_reference(values, book))
    assert np.abs(book[labels] - values)[-5:].max() < 0.5
    few = rng.choice(rng.normal(size=200), 5000)
    book, labels = quantize.codebook_1d(few)
    np.testing.assert_array_equal(book[labels], few.astype(np.float32))


def test_two_level_kmeans_is_close_to_flat(monkeypatch):
    """The two-level search (for large palettes) loses little against plain Lloyd on structured data."""
    rng = np.random.default_rng(3)
    centres = rng.normal(size=(300, 9))
    points = (centres[rng.integers(0, 300, 6000)] + 0.05 * rng.normal(size=(6000, 9))).astype(np.float32)

    def sse(k_limit):
        monkeypatch.setattr(quantize, "FLAT_LIMIT", k_limit)
        c, labels = quantize.kmeans(points, 256, seed=0)
        assert len(c) == 256 and labels.max() < 256
        return float(((points - c[labels]) ** 2).sum())

    flat, two = sse(1 << 40), sse(1000)
    assert two < 1.25 * flat


# ====================================================================== non-finite and bad input

def test_non_finite_codebooks(tmp_path):
    """JSON null (how splat-transform's older writers stored NaN codebooks) is a non-finite value; a
    log-scale of -Infinity is a flat axis."""
    meta, images, _ = hand_scene()
    meta["sh0"]["codebook"][64] = None          # the second Gaussian's red colour
    path = bundle(tmp_path / "null.sog", meta, images)
    with pytest.raises(PlyError, match=r"1 Gaussian\(s\) with non-finite .* rows \[1\]") as exc:
        read_sog(path)
    assert str(path) in str(exc.value)
    with pytest.warns(UserWarning, match="dropped 1 of 2"):
        assert len(read_sog(path, sanitize=True)) == 1
    meta["sh0"]["codebook"][64] = 0.0
    meta["scales"]["codebook"][0] = -math.inf   # json writes -Infinity
    path = bundle(tmp_path / "flat.sog", meta, images)
    with pytest.warns(InfinitiesReadWarning, match=r"1 log-scale\(s\) of -inf as -30"):
        assert read_sog(path).scales[0, 0] == -30


def _bad_meta(meta: dict, images: dict) -> dict:
    """name -> (meta, images) of broken scenes, each with the message it must give."""
    def edit(fn):
        m, im = json.loads(json.dumps(meta)), dict(images)
        fn(m, im)
        return m, im

    return {
        "no count": (edit(lambda m, im: m.pop("count")), "meta.json has no count"),
        "bad mins": (edit(lambda m, im: m["means"].update(mins=[0, 1])), "means.mins must be 3 numbers"),
        "version 3": (edit(lambda m, im: m.update(version=3)), "SOG version 3"),
        "missing image": (edit(lambda m, im: im.pop("quats.webp")), "no quats.webp"),
        "small image": (edit(lambda m, im: m.update(count=17)), "fewer than the 17 Gaussians"),
        "outside": (edit(lambda m, im: m["quats"].update(files=["../quats.webp"])), "outside the scene"),
        "palette width": (edit(lambda m, im: m["shN"].update(bands=3)), "a palette of 3-band SH is 960"),
        "palette count": (edit(lambda m, im: m["shN"].update(count=65)), "holds 64 palette entries"),
        "not webp": (edit(lambda m, im: im.update({"sh0.webp": None})), "sh0.webp is not a readable WebP image"),
    }


def test_bad_scenes_name_the_file_and_the_problem(tmp_path):
    meta, images, _ = hand_scene()
    for i, (name, ((m, im), message)) in enumerate(_bad_meta(meta, images).items()):
        path = tmp_path / f"bad{i}.sog"
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("meta.json", json.dumps(m))
            for member, rgba in im.items():
                z.writestr(member, b"RIFF junk" if rgba is None else webp(rgba))
        with pytest.raises(PlyError, match=message) as exc:
            read_splat_file(path)
        assert str(path) in str(exc.value), name
    (tmp_path / "lod-meta.json").write_text("{}")
    with pytest.raises(PlyError, match="streamed SOG"):
        read_splat_file(tmp_path / "lod-meta.json")
    with zipfile.ZipFile(tmp_path / "other.sog", "w") as z:
        z.writestr("readme.txt", "hello")
    with pytest.raises(PlyError, match="bundle has no meta.json"):
        read_splat_file(tmp_path / "other.sog")
    (tmp_path / "j.json").write_text('{"version": 2, "count"')
    with pytest.raises(PlyError, match="not valid JSON"):
        read_splat_file(tmp_path / "j.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PlyError, match="folder without a SOG scene's meta.json"):
        read_splat_file(tmp_path / "empty")


def test_detection_tells_json_from_splat_records(tmp_path):
    """A meta.json whose size is a whole number of 32-byte records is SOG; a .splat whose first byte
    happens to be '{' is a .splat."""
    meta, images, _ = hand_scene()
    path = folder(tmp_path / "scene", meta, images)
    text = path.read_text()
    path.write_text(text + " " * (-len(text) % 32))
    assert path.stat().st_size % 32 == 0 and detect_format(path) == "sog"
    cloud = make_cloud(n=4, degree=0)
    cloud.means[0, 0] = np.frombuffer(b"{\x00\x80\x3f", "<f4")[0]  # 1.0000147, its low byte '{'
    data = quiet(write_splat_file, cloud, tmp_path / "a.splat").read_bytes()
    assert data[:1] == b"{"
    (tmp_path / "a.bin").write_bytes(data)
    assert detect_format(tmp_path / "a.splat") == detect_format(tmp_path / "a.bin") == "splat"


@pytest.fixture(scope="module")
def seed_sog(tmp_path_factory) -> bytes:
    return write_sog(make_cloud(n=300, degree=1, seed=7), tmp_path_factory.mktemp("sog") / "s.sog").read_bytes()


def test_truncated_bundles_raise_ply_error(tmp_path, seed_sog):
    path = tmp_path / "t.sog"
    for cut in (0, 3, 10, 100, len(seed_sog) // 2, len(seed_sog) - 30, len(seed_sog) - 1):
        path.write_bytes(seed_sog[:cut])
        with pytest.raises(PlyError) as exc:
            quiet(read_splat_file, path)
        assert str(path) in str(exc.value), cut


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=EDITS)
def test_property_corruption_only_raises_ply_error(tmp_path, seed_sog, ops):
    path = tmp_path / "c.sog"
    path.write_bytes(corrupt(seed_sog, ops, head_len=200))
    read_or_refuse(read_splat_file, path)


def test_info_says_what_was_read_as_its_meaning(tmp_path, capsys):
    meta, images, _ = hand_scene()
    meta["scales"]["codebook"][0] = -math.inf
    path = bundle(tmp_path / "flat.sog", meta, images)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # info reports it in its text, not as a warning
        assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "read: " in out and "1 log-scale(s) of -inf as -30 (flat axes)" in out and "Gaussians: 2" in out
