"""Quaternions (w, x, y, z): the one implementation, for numpy arrays and torch tensors."""

import numpy as np
import pytest
import torch

from gvae_core import quaternions as Q


def _random_unit(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_normalize_guards_zero_and_non_finite_rows():
    q = np.array([[0, 0, 0, 0], [2, 0, 0, 0], [np.nan, 1, 0, 0], [np.inf, 0, 0, 0], [1, 2, 3, 4]], np.float64)
    u = Q.normalize(q)
    np.testing.assert_allclose(u[:4], [[1, 0, 0, 0]] * 4)
    np.testing.assert_allclose(u[4], q[4] / np.linalg.norm(q[4]))
    t = Q.normalize(torch.from_numpy(q))
    np.testing.assert_array_equal(t.numpy(), u)


def test_normalize_gradient_is_finite_at_zero_and_infinite_quaternions():
    q = torch.tensor([[0.0, 0, 0, 0], [np.inf, 0, 0, 0], [np.nan, 0, 0, 0], [1, 2, 3, 4]], requires_grad=True)
    Q.normalize(q).sum().backward()
    assert torch.isfinite(q.grad).all()
    assert (q.grad[:3] == 0).all() and (q.grad[3] != 0).any()


def test_rotation_matrices_round_trip():
    r = Q.to_rotmat(_random_unit(50))
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    back = Q.from_rotmat(r)
    assert (back[:, 0] >= 0).all()
    np.testing.assert_allclose(Q.to_rotmat(back), r, atol=1e-12)
    # 90 degrees about z maps x to y.
    rz = Q.to_rotmat(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    np.testing.assert_allclose(rz @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_array_equal(Q.to_rotmat(torch.from_numpy(_random_unit(5))).numpy(), Q.to_rotmat(_random_unit(5)))


@pytest.mark.parametrize("as_torch", [False, True])
def test_multiply_composes_rotations_and_conjugate_inverts(as_torch):
    a, b = _random_unit(20, 1), _random_unit(20, 2)
    conv = torch.from_numpy if as_torch else np.asarray
    ab = Q.multiply(conv(a), conv(b))
    ab = ab.numpy() if as_torch else ab
    np.testing.assert_allclose(Q.to_rotmat(ab), Q.to_rotmat(a) @ Q.to_rotmat(b), atol=1e-12)
    ident = Q.multiply(conv(a), Q.conjugate(conv(a)))
    ident = ident.numpy() if as_torch else ident
    np.testing.assert_allclose(np.abs(ident), np.broadcast_to([1.0, 0, 0, 0], ident.shape), atol=1e-12)


def test_canonical_has_non_negative_w_and_the_same_rotation():
    q = _random_unit(100, 3) * 3.0
    c = Q.canonical(q)
    assert (c[:, 0] >= 0).all()
    np.testing.assert_allclose(Q.to_rotmat(c), Q.to_rotmat(Q.normalize(q)), atol=1e-12)
    np.testing.assert_array_equal(Q.canonical(torch.from_numpy(q)).numpy(), c)
