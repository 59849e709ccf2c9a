"""Quaternions in w, x, y, z order (the 3DGS PLY's `rot_0..3`), for numpy arrays and torch tensors.

Stored quaternions need not be unit; `normalize` makes them unit, and a zero or non-finite one
means the identity (DESIGN.md). Every function takes (..., 4) arrays or tensors and returns the
same kind; torch is never imported here.
"""

from __future__ import annotations

import numpy as np

from .conventions import is_torch


def _stack(parts, axis: int = -1):
    if is_torch(parts[0]):
        import torch  # noqa: PLC0415 - only reached with torch tensors, so torch is loaded already

        return torch.stack(parts, axis)
    return np.stack(parts, axis)


def normalize(q):
    """Unit quaternions; rows with a zero or non-finite norm become the identity. With torch the
    gradient stays finite everywhere: such rows are replaced before any arithmetic."""
    if is_torch(q):
        norm = q.detach().norm(dim=-1, keepdim=True)
        good = norm.isfinite() & (norm > 1e-12)
        safe = q.where(good, q.new_ones(()))
        ident = q.new_zeros(q.shape)
        ident[..., 0] = 1.0
        return (safe / safe.norm(dim=-1, keepdim=True)).where(good, ident)
    q = np.asarray(q)
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(q, axis=-1, keepdims=True)
    good = np.isfinite(norm) & (norm > 1e-12)
    out = np.where(good, q / np.where(good, norm, 1.0), 0.0).astype(q.dtype, copy=False)
    out[..., 0] = np.where(good[..., 0], out[..., 0], 1.0)
    return out


def canonical(q):
    """Unit quaternions with w >= 0 (q and -q are the same rotation)."""
    q = normalize(q)
    flip = q[..., :1] < 0
    return q.where(~flip, -q) if is_torch(q) else np.where(flip, -q, q)


def multiply(a, b):
    """Hamilton product a * b (rotation b, then a), broadcasting over leading axes."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return _stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                   aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def conjugate(q):
    """The inverse rotation of a unit quaternion."""
    sign = np.array([1.0, -1.0, -1.0, -1.0])
    return q * (q.new_tensor(sign) if is_torch(q) else sign.astype(q.dtype))


def to_rotmat(q):
    """(..., 4) unit quaternions to (..., 3, 3) rotation matrices (columns are the local axes)."""
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return _stack(rows).reshape(q.shape[:-1] + (3, 3))


def from_rotmat(m) -> np.ndarray:
    """(..., 3, 3) rotation matrices to (..., 4) unit quaternions with w >= 0 (numpy, float64).
    Shepperd's method: column p of the symmetric matrix K = 4 q q^T follows from the matrix
    entries, and the column of its largest diagonal entry gives q without cancellation."""
    m = np.asarray(m, np.float64)
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = m.reshape(-1, 9).T
    k = np.array([[1 + a00 + a11 + a22, a21 - a12, a02 - a20, a10 - a01],
                  [a21 - a12, 1 + a00 - a11 - a22, a01 + a10, a02 + a20],
                  [a02 - a20, a01 + a10, 1 - a00 + a11 - a22, a12 + a21],
                  [a10 - a01, a02 + a20, a12 + a21, 1 - a00 - a11 + a22]]).transpose(2, 0, 1)
    rows = np.arange(len(k))
    pivot = np.stack([a00 + a11 + a22, a00, a11, a22], 1).argmax(1)
    s = np.sqrt(np.maximum(k[rows, pivot, pivot], 1e-300)) * 2
    out = k[rows, pivot] / s[:, None]
    out[rows, pivot] = 0.25 * s
    out *= np.where(out[:, :1] < 0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(m.shape[:-2] + (4,))
