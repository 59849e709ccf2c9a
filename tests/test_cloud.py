"""GaussianCloud: construction, activations, subsets, conversions, validation."""

import numpy as np
import pytest

from gvae_core import GaussianCloud, quaternions
from gvae_core.conventions import LOG_SCALE_RANGE, SH_C0


def make_cloud(n=6, degree=2, seed=0, **extra):
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return GaussianCloud(means=rng.normal(size=(n, 3)), scales=rng.normal(-3, 1, (n, 3)),
                         quats=rng.normal(size=(n, 4)), opacities=rng.normal(size=n),
                         sh_dc=rng.normal(size=(n, 3)), sh_rest=rng.normal(size=(n, k, 3)),
                         extra=extra)


def test_construction_and_shapes():
    c = GaussianCloud(means=[[0, 0, 0], [1, 2, 3]], scales=[[0, 0, 0]] * 2, quats=[[1, 0, 0, 0]] * 2,
                      opacities=[0, 1], sh_dc=[[0, 0, 0]] * 2)
    assert len(c) == 2 and c.sh_degree == 0 and c.sh_rest.shape == (2, 0, 3)
    for degree, k in ((0, 0), (1, 3), (2, 8), (3, 15)):
        assert make_cloud(degree=degree).sh_degree == degree
        assert make_cloud(degree=degree).sh_rest.shape[1] == k
    with pytest.raises(ValueError, match="means"):
        GaussianCloud(means=np.zeros((2, 2)), scales=np.zeros((2, 3)), quats=np.zeros((2, 4)),
                      opacities=np.zeros(2), sh_dc=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="sh_rest"):
        make_cloud().replace(sh_rest=np.zeros((6, 5, 3)))
    with pytest.raises(ValueError, match="extra"):
        make_cloud(tag=np.zeros(5))


def test_activations_are_finite_and_correct():
    c = make_cloud(n=4)
    np.testing.assert_allclose(c.activated_scales(), np.exp(c.scales), rtol=1e-12)
    np.testing.assert_allclose(c.activated_opacities(), 1 / (1 + np.exp(-c.opacities)), rtol=1e-12)
    np.testing.assert_allclose(c.base_color(), np.maximum(c.sh_dc * SH_C0 + 0.5, 0))
    extreme = c.replace(scales=np.full((4, 3), 1e4), opacities=np.array([-1e4, 1e4, 0.0, 5.0]))
    with np.errstate(all="raise"):
        s = extreme.activated_scales()
        o = extreme.activated_opacities()
    assert np.isfinite(s).all() and np.all(s == np.exp(LOG_SCALE_RANGE[1]))
    assert o[0] < 1e-20 and o[1] == 1.0 and o[2] == 0.5


def test_select_concat_and_sh_degree():
    a = make_cloud(n=5, degree=1, ids=np.arange(5, dtype=np.int64))
    b = make_cloud(n=3, degree=3, seed=1)
    sub = a.select(np.array([True, False, True, False, True]))
    assert len(sub) == 3 and list(sub.extra["ids"]) == [0, 2, 4]
    np.testing.assert_array_equal(a.select([4, 0]).means, a.means[[4, 0]])
    joined = GaussianCloud.concat([a, b])
    assert len(joined) == 8 and joined.sh_degree == 3
    np.testing.assert_array_equal(joined.sh_rest[:5, :3], a.sh_rest)
    assert np.all(joined.sh_rest[:5, 3:] == 0)
    assert joined.extra["ids"].dtype == np.int64 and list(joined.extra["ids"]) == [0, 1, 2, 3, 4, 0, 0, 0]
    np.testing.assert_array_equal(b.with_sh_degree(1).sh_rest, b.sh_rest[:, :3])
    with pytest.raises(ValueError):
        GaussianCloud.concat([])


def test_torch_round_trip_keeps_values_and_extra_dtypes():
    torch = pytest.importorskip("torch", reason="torch conversion needs torch")
    c = make_cloud(n=7, degree=3, ids=np.arange(7, dtype=np.int64))
    t = c.to_torch()
    assert t.is_torch and t.means.dtype == torch.float32 and t.extra["ids"].dtype == torch.int64
    back = t.numpy()
    for name, value in c.arrays().items():
        np.testing.assert_array_equal(getattr(back, name), value.astype(np.float32))
    np.testing.assert_array_equal(back.extra["ids"], c.extra["ids"])
    assert len(t.select(torch.tensor([0, 3]))) == 2
    with pytest.raises(ValueError, match="numpy and torch"):
        GaussianCloud.concat([c, t])


def test_numpy_form_is_contiguous_and_shares_what_already_is():
    """Columns of one packed block (what the Blender add-on reads) become contiguous arrays."""
    n = 50
    block = np.random.default_rng(0).normal(size=(n, 16)).astype(np.float32)
    packed = GaussianCloud(means=np.ascontiguousarray(block[:, :3]), scales=block[:, 3:6], quats=block[:, 6:10],
                           opacities=block[:, 10], sh_dc=block[:, 11:14], sh_rest=np.zeros((n, 0, 3), np.float32),
                           extra={"gvae_id": np.arange(2 * n)[::2]})
    assert not packed.scales.flags["C_CONTIGUOUS"]
    c = packed.numpy()
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert getattr(c, name).flags["C_CONTIGUOUS"]
        np.testing.assert_array_equal(getattr(c, name), getattr(packed, name))
    assert c.extra["gvae_id"].flags["C_CONTIGUOUS"] and c.extra["gvae_id"].tolist() == list(range(0, 2 * n, 2))
    assert c.means is packed.means  # already in form: shared, not copied


def test_validate_and_sanitize():
    c = make_cloud(n=8)
    c.means[2, 1] = np.nan
    c.sh_rest[5, 0, 0] = np.inf
    c.quats[3] = 0
    c.scales[4, 0] = 40.0
    c.opacities[6] = -80.0
    report = c.validate()
    assert list(report.nonfinite_rows) == [2, 5]
    assert list(report.zero_quat_rows) == [3]
    assert list(report.extreme_scale_rows) == [4]
    assert list(report.extreme_opacity_rows) == [6]
    assert not report.ok and "non-finite values: 2 row(s) [2, 5]" in str(report)
    clean = c.sanitize()
    assert len(clean) == 6 and clean.validate().ok
    np.testing.assert_array_equal(clean.quats[2], [1, 0, 0, 0])  # old row 3
    assert clean.scales.max() <= LOG_SCALE_RANGE[1]
    assert c.means[2, 1] != c.means[2, 1]  # the original is untouched


def _points(pts) -> GaussianCloud:
    n = len(pts)
    return GaussianCloud(means=np.asarray(pts, np.float32), scales=np.zeros((n, 3)),
                         quats=np.tile([1.0, 0, 0, 0], (n, 1)), opacities=np.zeros(n), sh_dc=np.zeros((n, 3)))


def test_normalization_ignores_floaters():
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, size=(2000, 3)) + [3.0, 0.0, 0.0]
    pts[:5] = 1e4  # a few floaters
    center, scale = _points(pts).normalization()
    np.testing.assert_allclose(center, [3.0, 0.0, 0.0], atol=0.05)
    assert 0.9 < scale < 1.0
    assert _points(np.zeros((4, 3))).normalization()[1] == 1.0
    assert _points(np.zeros((0, 3))).normalization()[1] == 1.0


def test_transformed_moves_positions_rotations_and_scales():
    c = make_cloud(n=20, degree=0)
    angle = 0.7
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]])
    m = np.eye(4)
    m[:3, :3] = 2.5 * rot
    m[:3, 3] = [1.0, -2.0, 0.5]
    moved = c.transformed(m)
    np.testing.assert_allclose(moved.means, c.means @ (2.5 * rot).T + m[:3, 3], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(moved.scales, c.scales + np.log(2.5), rtol=1e-5, atol=1e-5)
    got = quaternions.to_rotmat(quaternions.normalize(moved.quats.astype(np.float64)))
    want = rot @ quaternions.to_rotmat(quaternions.normalize(c.quats))
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_array_equal(moved.sh_dc, c.sh_dc.astype(np.float32))
    with pytest.warns(UserWarning, match="SH rest"):
        make_cloud(n=3, degree=1).transformed(m)
    for bad in (np.diag([1.0, 2.0, 1.0, 1.0]), np.diag([-1.0, 1.0, 1.0, 1.0])):
        with pytest.raises(ValueError, match="uniform|mirror"):
            c.transformed(bad)


def test_append_children_extras_policy():
    base = make_cloud(n=4, degree=1, gvae_id=np.array([10, 11, 12, 13], np.int64),
                      gvae_parent=np.array([-1, 10, 10, 12], np.int64), tag=np.array([1.0, 2.0, 3.0, 4.0], np.float32))
    kids = make_cloud(n=3, degree=1, seed=2).numpy()
    out = base.append_children(kids, [1, 3, 4])  # the third child is born from the first child
    assert len(out) == 7 and out.sh_degree == 1
    np.testing.assert_array_equal(out.means[4:], kids.means)
    np.testing.assert_array_equal(out.extra["tag"], [1, 2, 3, 4, 2, 4, 2])      # inherited from the ancestor
    np.testing.assert_array_equal(out.extra["gvae_id"], [10, 11, 12, 13, 14, 15, 16])  # fresh ids
    np.testing.assert_array_equal(out.extra["gvae_parent"], [-1, 10, 10, 12, 11, 13, 14])  # the parent's id
    assert out.extra["gvae_id"].dtype == np.int64
    own = kids.replace(extra={"tag": np.array([7.0, 8.0, 9.0], np.float32)})
    np.testing.assert_array_equal(base.append_children(own, [0, 0, 0]).extra["tag"][4:], [7, 8, 9])
    plain = make_cloud(n=2, degree=1)
    assert set(plain.append_children(kids, [0, 1, 0]).extra) == set()
    for bad in ([0, 1], [0, 1, 6], [0, -1, 0]):
        with pytest.raises(ValueError, match="parents"):
            base.append_children(kids, bad)
