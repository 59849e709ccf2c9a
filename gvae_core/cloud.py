"""Gaussian clouds: the raw 3DGS parameters of N Gaussians, held as numpy arrays or torch tensors.

Parameters are stored raw, exactly as the reference 3DGS PLY stores them (DESIGN.md):
log-scales, w-x-y-z quaternions that need not be unit, opacity logits, SH coefficients.
They are activated on use. This module works with numpy alone; torch is touched only when
the arrays already are torch tensors or a conversion to torch is asked for.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

#: Number of SH "rest" coefficients per channel for SH degree 0..3.
SH_REST_COUNTS = {0: 0, 1: 3, 2: 8, 3: 15}
_DEGREE_OF_REST = {k: d for d, k in SH_REST_COUNTS.items()}

#: Range log-scales are clamped to on activation: exp(±30) is finite in float32 and squares safely
#: in float64; the renderer clamps further where it needs to.
LOG_SCALE_RANGE = (-30.0, 30.0)
#: Range opacity logits are clamped to on activation.
OPACITY_LOGIT_RANGE = (-50.0, 50.0)
#: SH band-0 constant: colour = SH_C0 * f_dc + 0.5.
SH_C0 = 0.28209479177387814

#: Beyond these, values are reported as extreme by `validate()` (they still render).
EXTREME_LOG_SCALE = (-20.0, 12.0)
EXTREME_OPACITY_LOGIT = 30.0
EXTREME_POSITION = 1e6

_FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def is_torch(x: Any) -> bool:
    """True for a torch tensor, without importing torch."""
    return type(x).__module__.startswith("torch")


def _torch():
    import torch  # noqa: PLC0415 - deliberately lazy: gvae_core must import without torch

    return torch


def _as_array(x: Any, dtype=np.float32):
    """numpy arrays and torch tensors pass through; anything else becomes a numpy array."""
    if is_torch(x) or isinstance(x, np.ndarray):
        return x
    return np.asarray(x, dtype=dtype)


@dataclass
class ValidationReport:
    """What `GaussianCloud.validate()` found. Row indices are into the validated cloud."""

    n: int
    nonfinite_rows: np.ndarray
    zero_quat_rows: np.ndarray
    extreme_scale_rows: np.ndarray
    extreme_opacity_rows: np.ndarray
    far_rows: np.ndarray

    @property
    def ok(self) -> bool:
        """No row would be dropped or changed by `sanitize()`."""
        return len(self.nonfinite_rows) == 0 and len(self.zero_quat_rows) == 0

    def lines(self) -> list[str]:
        def describe(name: str, rows: np.ndarray) -> str:
            head = ", ".join(str(int(i)) for i in rows[:5])
            more = ", ..." if len(rows) > 5 else ""
            return f"{name}: {len(rows)} row(s) [{head}{more}]" if len(rows) else f"{name}: none"

        return [
            describe("non-finite values", self.nonfinite_rows),
            describe("zero quaternions", self.zero_quat_rows),
            describe(f"log-scale outside {EXTREME_LOG_SCALE}", self.extreme_scale_rows),
            describe(f"|opacity logit| > {EXTREME_OPACITY_LOGIT:g}", self.extreme_opacity_rows),
            describe(f"|position| > {EXTREME_POSITION:g}", self.far_rows),
        ]

    def __str__(self) -> str:
        status = "ok" if self.ok else "PROBLEMS"
        return f"validation of {self.n} Gaussians: {status}\n  " + "\n  ".join(self.lines())


@dataclass
class GaussianCloud:
    """N Gaussians with raw 3DGS parameters.

    means (N,3) world positions; scales (N,3) log-scales; quats (N,4) w,x,y,z (normalised on
    use, zero means identity); opacities (N,) logits; sh_dc (N,3); sh_rest (N,K,3) with K in
    {0,3,8,15}; extra: per-Gaussian arrays for properties the project does not interpret
    (kept with their own dtype so they round-trip through PLY).
    All fields are numpy arrays or all are torch tensors.
    """

    means: Any
    scales: Any
    quats: Any
    opacities: Any
    sh_dc: Any
    sh_rest: Any = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        for name in _FIELDS:
            value = getattr(self, name)
            if value is None and name == "sh_rest":
                n = len(self.means)
                value = (_torch().zeros((n, 0, 3), dtype=self.means.dtype, device=self.means.device)
                         if is_torch(self.means) else np.zeros((n, 0, 3), np.float32))
            setattr(self, name, _as_array(value))
        self.extra = {k: (v if is_torch(v) else np.asarray(v)) for k, v in dict(self.extra).items()}
        n = self.means.shape[0] if self.means.ndim else -1
        expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,),
                    "sh_dc": (n, 3)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"GaussianCloud.{name} must have shape {shape}, "
                                 f"got {tuple(getattr(self, name).shape)}")
        rest = tuple(self.sh_rest.shape)
        if len(rest) != 3 or rest[0] != n or rest[2] != 3 or rest[1] not in _DEGREE_OF_REST:
            raise ValueError(f"GaussianCloud.sh_rest must have shape (N, K, 3) with K in "
                             f"{sorted(_DEGREE_OF_REST)}, got {rest}")
        for k, v in self.extra.items():
            if v.shape[:1] != (n,):
                raise ValueError(f"GaussianCloud.extra[{k!r}] must have {n} rows, got shape {tuple(v.shape)}")
        kinds = {is_torch(getattr(self, f)) for f in _FIELDS}
        if len(kinds) > 1:
            raise ValueError("GaussianCloud fields must be all numpy arrays or all torch tensors")

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return _DEGREE_OF_REST[int(self.sh_rest.shape[1])]

    @property
    def is_torch(self) -> bool:
        return is_torch(self.means)

    @property
    def device(self):
        """The torch device, or "cpu" for numpy clouds."""
        return self.means.device if self.is_torch else "cpu"

    def arrays(self) -> dict[str, Any]:
        """The six parameter arrays by field name (not `extra`)."""
        return {name: getattr(self, name) for name in _FIELDS}

    def replace(self, **changes) -> "GaussianCloud":
        """A copy with some fields replaced (arrays are shared, not copied)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def empty(cls, sh_degree: int = 0) -> "GaussianCloud":
        k = SH_REST_COUNTS[sh_degree]
        return cls(means=np.zeros((0, 3), np.float32), scales=np.zeros((0, 3), np.float32),
                   quats=np.zeros((0, 4), np.float32), opacities=np.zeros((0,), np.float32),
                   sh_dc=np.zeros((0, 3), np.float32), sh_rest=np.zeros((0, k, 3), np.float32))

    # ------------------------------------------------------------ activations
    def _ns(self):
        return _torch() if self.is_torch else np

    def activated_scales(self):
        """Standard deviations along the Gaussian's local axes: exp(clamped log-scale)."""
        return self._ns().exp(_clip(self.scales, *LOG_SCALE_RANGE))

    def activated_opacities(self):
        """Opacities in [0, 1]: sigmoid(clamped logit)."""
        x = _clip(self.opacities, *OPACITY_LOGIT_RANGE)
        if self.is_torch:
            return _torch().sigmoid(x)
        return 1.0 / (1.0 + np.exp(-x))

    def unit_quats(self):
        """Unit w,x,y,z quaternions; a zero (or non-finite) quaternion becomes the identity."""
        return normalize_quats(self.quats)

    def rotation_matrices(self):
        """(N,3,3) rotation matrices of the unit quaternions (columns are the local axes)."""
        return quat_to_rotmat(self.unit_quats())

    def base_color(self):
        """RGB of the SH DC term: SH_C0 * f_dc + 0.5, clamped at 0 (view-independent colour)."""
        c = self.sh_dc * SH_C0 + 0.5
        return c.clamp(min=0.0) if self.is_torch else np.maximum(c, 0.0)

    # ------------------------------------------------------- subsets, joins
    def select(self, index) -> "GaussianCloud":
        """The Gaussians picked by a boolean mask or an integer index array (numpy or torch)."""
        if self.is_torch:
            torch = _torch()
            index = index if is_torch(index) else torch.as_tensor(np.asarray(index))
            index = index.to(self.means.device)
        else:
            index = index.detach().cpu().numpy() if is_torch(index) else np.asarray(index)
            if index.dtype != bool:
                index = index.astype(np.int64, copy=False)
        fields = {name: getattr(self, name)[index] for name in _FIELDS}
        extra = {}
        for k, v in self.extra.items():
            if is_torch(v):
                extra[k] = v[index if is_torch(index) else _torch().as_tensor(index)]
            else:
                extra[k] = v[index.cpu().numpy() if is_torch(index) else index]
        return GaussianCloud(**fields, extra=extra)

    @staticmethod
    def concat(clouds: Sequence["GaussianCloud"]) -> "GaussianCloud":
        """Join clouds of the same kind (numpy or torch). SH degree is raised to the largest one
        (missing coefficients are zero); an `extra` key missing from a cloud is filled with zeros."""
        clouds = list(clouds)
        if not clouds:
            raise ValueError("GaussianCloud.concat needs at least one cloud")
        if len({c.is_torch for c in clouds}) > 1:
            raise ValueError("GaussianCloud.concat: mix of numpy and torch clouds")
        degree = max(c.sh_degree for c in clouds)
        clouds = [c.with_sh_degree(degree) for c in clouds]
        torch_mode = clouds[0].is_torch
        cat = _torch().cat if torch_mode else np.concatenate
        fields = {name: cat([getattr(c, name) for c in clouds], 0) for name in _FIELDS}
        keys: list[str] = []
        for c in clouds:
            keys += [k for k in c.extra if k not in keys]
        extra = {}
        for k in keys:
            template = next(c.extra[k] for c in clouds if k in c.extra)
            parts = []
            for c in clouds:
                if k in c.extra:
                    parts.append(c.extra[k])
                elif is_torch(template):
                    parts.append(_torch().zeros((len(c),) + tuple(template.shape[1:]),
                                                dtype=template.dtype, device=template.device))
                else:
                    parts.append(np.zeros((len(c),) + template.shape[1:], template.dtype))
            extra[k] = (_torch().cat if is_torch(template) else np.concatenate)(parts, 0)
        return GaussianCloud(**fields, extra=extra)

    def with_sh_degree(self, degree: int) -> "GaussianCloud":
        """A copy with SH truncated or zero-padded to `degree`."""
        k = SH_REST_COUNTS[degree]
        rest = self.sh_rest
        have = rest.shape[1]
        if have == k:
            return self
        if have > k:
            return self.replace(sh_rest=rest[:, :k])
        pad_shape = (rest.shape[0], k - have, 3)
        if self.is_torch:
            pad = _torch().zeros(pad_shape, dtype=rest.dtype, device=rest.device)
            return self.replace(sh_rest=_torch().cat([rest, pad], 1))
        return self.replace(sh_rest=np.concatenate([rest, np.zeros(pad_shape, rest.dtype)], 1))

    # -------------------------------------------------------- conversions
    def to_torch(self, device=None, dtype=None) -> "GaussianCloud":
        """Torch copy (parameters as float32 unless `dtype` is given); `extra` keeps its dtypes."""
        torch = _torch()
        dtype = dtype or torch.float32

        def conv(x, float_dtype):
            t = x if is_torch(x) else torch.from_numpy(np.ascontiguousarray(x))
            if float_dtype is not None:
                t = t.to(dtype=float_dtype)
            return t.to(device) if device is not None else t

        fields = {name: conv(getattr(self, name), dtype) for name in _FIELDS}
        extra = {k: conv(v, None) for k, v in self.extra.items()}
        return GaussianCloud(**fields, extra=extra)

    def numpy(self) -> "GaussianCloud":
        """numpy copy (float32 parameters, detached from any autograd graph)."""

        def conv(x, float32: bool):
            a = x.detach().cpu().numpy() if is_torch(x) else np.asarray(x)
            return a.astype(np.float32, copy=False) if float32 else a

        fields = {name: conv(getattr(self, name), True) for name in _FIELDS}
        extra = {k: conv(v, False) for k, v in self.extra.items()}
        return GaussianCloud(**fields, extra=extra)

    def detach(self) -> "GaussianCloud":
        if not self.is_torch:
            return self
        return GaussianCloud(**{n: getattr(self, n).detach() for n in _FIELDS},
                             extra={k: v.detach() if is_torch(v) else v for k, v in self.extra.items()})

    def copy(self) -> "GaussianCloud":
        """Deep copy of every array."""
        dup = (lambda x: x.clone()) if self.is_torch else (lambda x: x.copy())
        return GaussianCloud(**{n: dup(getattr(self, n)) for n in _FIELDS},
                             extra={k: (v.clone() if is_torch(v) else v.copy()) for k, v in self.extra.items()})

    # ------------------------------------------------------ validation
    def nonfinite_rows(self) -> np.ndarray:
        """Rows (ascending) with a NaN or an infinity in any parameter."""
        c = self.numpy()
        arrays = [getattr(c, name) for name in _FIELDS]
        if all(np.isfinite(a).all() for a in arrays):  # the usual case, without per-row bookkeeping
            return np.zeros(0, np.int64)
        finite = np.ones(len(c), bool)
        for a in arrays:
            finite &= np.isfinite(a.reshape(len(c), int(np.prod(a.shape[1:])))).all(axis=1)
        return np.flatnonzero(~finite)

    def validate(self) -> ValidationReport:
        """Rows with non-finite values, zero quaternions and extreme (but finite) values."""
        c = self.numpy()
        bad = c.nonfinite_rows()
        finite = np.ones(len(c), bool)
        finite[bad] = False
        with np.errstate(invalid="ignore", over="ignore"):
            qnorm = np.linalg.norm(c.quats.astype(np.float64), axis=1)
            zero_q = finite & (qnorm < 1e-12)
            ext_scale = finite & ((c.scales < EXTREME_LOG_SCALE[0]) | (c.scales > EXTREME_LOG_SCALE[1])).any(1)
            ext_op = finite & (np.abs(c.opacities) > EXTREME_OPACITY_LOGIT)
            far = finite & (np.abs(c.means) > EXTREME_POSITION).any(1)
        return ValidationReport(
            n=len(c),
            nonfinite_rows=bad,
            zero_quat_rows=np.flatnonzero(zero_q),
            extreme_scale_rows=np.flatnonzero(ext_scale),
            extreme_opacity_rows=np.flatnonzero(ext_op),
            far_rows=np.flatnonzero(far),
        )

    def sanitize(self) -> "GaussianCloud":
        """Drop rows with non-finite values, replace zero quaternions by the identity and clamp
        log-scales and opacity logits to their finite ranges. Returns a new cloud."""
        report = self.validate()
        keep = np.ones(len(self), bool)
        keep[report.nonfinite_rows] = False
        out = self.select(keep) if not keep.all() else self.copy()
        norm = (out.quats.norm(dim=1) if out.is_torch else np.linalg.norm(out.quats, axis=1))
        zero = norm < 1e-12
        if bool(zero.any()):
            out.quats[zero] = out.quats.new_tensor([1.0, 0, 0, 0]) if out.is_torch else np.array(
                [1.0, 0, 0, 0], out.quats.dtype)
        out.scales = _clip(out.scales, *LOG_SCALE_RANGE)
        out.opacities = _clip(out.opacities, *OPACITY_LOGIT_RANGE)
        return out


# ---------------------------------------------------------------- helpers

def _clip(x, lo: float, hi: float):
    return x.clamp(lo, hi) if is_torch(x) else np.clip(x, lo, hi)


def normalize_quats(q):
    """Unit quaternions (w,x,y,z); rows with zero or non-finite norm become the identity.
    Gradients stay finite: the norm is guarded before dividing."""
    if is_torch(q):
        torch = _torch()
        norm = q.norm(dim=-1, keepdim=True)
        good = torch.isfinite(norm) & (norm > 1e-12)
        safe = torch.where(good, norm, torch.ones_like(norm))
        ident = torch.zeros_like(q)
        ident[..., 0] = 1.0
        return torch.where(good, q / safe, ident)
    q = np.asarray(q)
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(q, axis=-1, keepdims=True)
    good = np.isfinite(norm) & (norm > 1e-12)
    out = np.where(good, q / np.where(good, norm, 1.0), 0.0).astype(q.dtype, copy=False)
    out[..., 0] = np.where(good[..., 0], out[..., 0], 1.0)
    return out


def quat_to_rotmat(q):
    """(…,4) unit w,x,y,z quaternions to (…,3,3) rotation matrices."""
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    if is_torch(q):
        return _torch().stack(rows, -1).reshape(q.shape[:-1] + (3, 3))
    return np.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(m):
    """(…,3,3) rotation matrices to (…,4) unit w,x,y,z quaternions with w >= 0 (numpy only)."""
    m = np.asarray(m, np.float64)
    flat = m.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    tr = flat[:, 0, 0] + flat[:, 1, 1] + flat[:, 2, 2]
    # Choose the numerically largest of w, x, y, z as the pivot (Shepperd's method).
    cand = np.stack([tr, flat[:, 0, 0], flat[:, 1, 1], flat[:, 2, 2]], 1)
    pivot = cand.argmax(1)
    for p in range(4):
        sel = pivot == p
        if not sel.any():
            continue
        a = flat[sel]
        if p == 0:
            s = np.sqrt(np.maximum(1 + a[:, 0, 0] + a[:, 1, 1] + a[:, 2, 2], 1e-300)) * 2
            q = [0.25 * s, (a[:, 2, 1] - a[:, 1, 2]) / s, (a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 1, 0] - a[:, 0, 1]) / s]
        elif p == 1:
            s = np.sqrt(np.maximum(1 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2], 1e-300)) * 2
            q = [(a[:, 2, 1] - a[:, 1, 2]) / s, 0.25 * s, (a[:, 0, 1] + a[:, 1, 0]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s]
        elif p == 2:
            s = np.sqrt(np.maximum(1 - a[:, 0, 0] + a[:, 1, 1] - a[:, 2, 2], 1e-300)) * 2
            q = [(a[:, 0, 2] - a[:, 2, 0]) / s, (a[:, 0, 1] + a[:, 1, 0]) / s, 0.25 * s, (a[:, 1, 2] + a[:, 2, 1]) / s]
        else:
            s = np.sqrt(np.maximum(1 - a[:, 0, 0] - a[:, 1, 1] + a[:, 2, 2], 1e-300)) * 2
            q = [(a[:, 1, 0] - a[:, 0, 1]) / s, (a[:, 0, 2] + a[:, 2, 0]) / s, (a[:, 1, 2] + a[:, 2, 1]) / s, 0.25 * s]
        out[sel] = np.stack(q, 1)
    out *= np.where(out[:, :1] < 0, -1.0, 1.0)
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape(m.shape[:-2] + (4,))

