"""GaussianCloud: construction, activations, subsets, conversions, validation."""

import numpy as np
import pytest

from gvae_core import GaussianCloud
from gvae_core.cloud import (LOG_SCALE_RANGE, SH_C0, normalize_quats, quat_to_rotmat,
                             rotmat_to_quat)


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


def test_quaternions_and_rotations():
    q = np.array([[0, 0, 0, 0], [2, 0, 0, 0], [np.nan, 1, 0, 0], [1, 2, 3, 4]], np.float64)
    u = normalize_quats(q)
    np.testing.assert_allclose(u[:3], [[1, 0, 0, 0]] * 3)
    np.testing.assert_allclose(u[3], q[3] / np.linalg.norm(q[3]))
    r = quat_to_rotmat(normalize_quats(make_cloud(n=50).quats))
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    back = rotmat_to_quat(r)
    np.testing.assert_allclose(quat_to_rotmat(back), r, atol=1e-12)
    # 90 degrees about z maps x to y.
    rz = quat_to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    np.testing.assert_allclose(rz @ [1, 0, 0], [0, 1, 0], atol=1e-12)


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
    # The guarded normalisation keeps gradients finite at a zero quaternion.
    q = torch.zeros(2, 4, requires_grad=True)
    normalize_quats(q).sum().backward()
    assert torch.isfinite(q.grad).all()


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
