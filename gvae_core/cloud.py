"""Gaussian clouds: the raw 3DGS parameters of N Gaussians, held as numpy arrays or torch tensors.

Parameters are stored raw, exactly as the reference 3DGS PLY stores them (DESIGN.md):
log-scales, w-x-y-z quaternions that need not be unit, opacity logits, SH coefficients.
They are activated on use. This module works with numpy alone; torch is touched only when
the arrays already are torch tensors or a conversion to torch is asked for.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Sequence

import numpy as np

from . import quaternions
from .conventions import (LOG_SCALE_RANGE, OPACITY_LOGIT_RANGE, SH_DEGREE_OF_REST, SH_REST_COUNTS, activate_opacities,
                          activate_scales, clip, dc_to_rgb, is_torch)

#: Beyond these, values are reported as extreme by `validate()` (they still render).
EXTREME_LOG_SCALE = (-20.0, 12.0)
EXTREME_OPACITY_LOGIT = 30.0
EXTREME_POSITION = 1e6

#: The six per-Gaussian parameters (DESIGN.md, Conventions), in the constructor's order.
PARAMETER_FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


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
    background: the colour (display-referred RGB in [0, 1]) the cloud was trained over, where it is
    known: what it is drawn over unless told otherwise (its see-through parts were fitted to it);
    None: unknown (tools that know no better draw over black).
    """

    means: Any
    scales: Any
    quats: Any
    opacities: Any
    sh_dc: Any
    sh_rest: Any = None
    extra: dict[str, Any] = field(default_factory=dict)
    background: tuple[float, float, float] | None = None

    def __post_init__(self):
        if self.background is not None:
            bg = tuple(float(v) for v in np.asarray(self.background, np.float64).reshape(-1))
            if len(bg) != 3 or not all(math.isfinite(v) for v in bg):
                raise ValueError(f"GaussianCloud.background must be 3 finite numbers, got {self.background!r}")
            self.background = bg
        for name in PARAMETER_FIELDS:
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
        if len(rest) != 3 or rest[0] != n or rest[2] != 3 or rest[1] not in SH_DEGREE_OF_REST:
            raise ValueError(f"GaussianCloud.sh_rest must have shape (N, K, 3) with K in "
                             f"{sorted(SH_DEGREE_OF_REST)}, got {rest}")
        for k, v in self.extra.items():
            if v.shape[:1] != (n,):
                raise ValueError(f"GaussianCloud.extra[{k!r}] must have {n} rows, got shape {tuple(v.shape)}")
        kinds = {is_torch(getattr(self, f)) for f in PARAMETER_FIELDS}
        if len(kinds) > 1:
            raise ValueError("GaussianCloud fields must be all numpy arrays or all torch tensors")

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return SH_DEGREE_OF_REST[int(self.sh_rest.shape[1])]

    @property
    def is_torch(self) -> bool:
        return is_torch(self.means)

    @property
    def device(self):
        """The torch device, or "cpu" for numpy clouds."""
        return self.means.device if self.is_torch else "cpu"

    def arrays(self) -> dict[str, Any]:
        """The six parameter arrays by field name (not `extra`)."""
        return {name: getattr(self, name) for name in PARAMETER_FIELDS}

    def replace(self, **changes) -> GaussianCloud:
        """A copy with some fields replaced (arrays are shared, not copied)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def empty(cls, sh_degree: int = 0) -> GaussianCloud:
        k = SH_REST_COUNTS[sh_degree]
        return cls(means=np.zeros((0, 3), np.float32), scales=np.zeros((0, 3), np.float32),
                   quats=np.zeros((0, 4), np.float32), opacities=np.zeros((0,), np.float32),
                   sh_dc=np.zeros((0, 3), np.float32), sh_rest=np.zeros((0, k, 3), np.float32))

    # ------------------------------------------------------------ activations
    def activated_scales(self):
        """Standard deviations along the Gaussian's local axes: exp(clamped log-scale)."""
        return activate_scales(self.scales)

    def activated_opacities(self):
        """Opacities in [0, 1]: sigmoid(clamped logit)."""
        return activate_opacities(self.opacities)

    def unit_quats(self):
        """Unit w,x,y,z quaternions; a zero (or non-finite) quaternion becomes the identity."""
        return quaternions.normalize(self.quats)

    def rotation_matrices(self):
        """(N,3,3) rotation matrices of the unit quaternions (columns are the local axes)."""
        return quaternions.to_rotmat(self.unit_quats())

    def base_color(self):
        """RGB of the SH DC term: SH_C0 * f_dc + 0.5, clamped at 0 (view-independent colour)."""
        return dc_to_rgb(self.sh_dc)

    # ------------------------------------------------------- subsets, joins
    def select(self, index) -> GaussianCloud:
        """The Gaussians picked by a boolean mask or an integer index array (numpy or torch)."""
        if self.is_torch:
            torch = _torch()
            index = index if is_torch(index) else torch.as_tensor(np.asarray(index))
            index = index.to(self.means.device)
        else:
            index = index.detach().cpu().numpy() if is_torch(index) else np.asarray(index)
            if index.dtype != bool:
                index = index.astype(np.int64, copy=False)
        fields = {name: getattr(self, name)[index] for name in PARAMETER_FIELDS}
        extra = {}
        for k, v in self.extra.items():
            if is_torch(v):
                extra[k] = v[index if is_torch(index) else _torch().as_tensor(index)]
            else:
                extra[k] = v[index.cpu().numpy() if is_torch(index) else index]
        return GaussianCloud(**fields, extra=extra, background=self.background)

    @staticmethod
    def concat(clouds: Sequence[GaussianCloud]) -> GaussianCloud:
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
        fields = {name: cat([getattr(c, name) for c in clouds], 0) for name in PARAMETER_FIELDS}
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
        backgrounds = {c.background for c in clouds}
        return GaussianCloud(**fields, extra=extra, background=backgrounds.pop() if len(backgrounds) == 1 else None)

    def with_sh_degree(self, degree: int) -> GaussianCloud:
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
    def to_torch(self, device=None, dtype=None) -> GaussianCloud:
        """Torch copy (parameters as float32 unless `dtype` is given); `extra` keeps its dtypes."""
        torch = _torch()
        dtype = dtype or torch.float32

        def conv(x, float_dtype):
            t = x if is_torch(x) else torch.from_numpy(np.ascontiguousarray(x))
            if float_dtype is not None:
                t = t.to(dtype=float_dtype)
            return t.to(device) if device is not None else t

        fields = {name: conv(getattr(self, name), dtype) for name in PARAMETER_FIELDS}
        extra = {k: conv(v, None) for k, v in self.extra.items()}
        return GaussianCloud(**fields, extra=extra, background=self.background)

    def numpy(self) -> GaussianCloud:
        """numpy form: float32 parameters, detached from any autograd graph, every array C-contiguous
        (strided views, such as the columns of one packed block, are copied: the whole-cloud work of
        refine is several times slower on them; arrays already in this form are shared)."""

        def conv(x, float32: bool):
            a = x.detach().cpu().numpy() if is_torch(x) else np.asarray(x)
            return np.ascontiguousarray(a.astype(np.float32, copy=False) if float32 else a)

        fields = {name: conv(getattr(self, name), True) for name in PARAMETER_FIELDS}
        extra = {k: conv(v, False) for k, v in self.extra.items()}
        return GaussianCloud(**fields, extra=extra, background=self.background)

    def detach(self) -> GaussianCloud:
        if not self.is_torch:
            return self
        return GaussianCloud(**{n: getattr(self, n).detach() for n in PARAMETER_FIELDS},
                             extra={k: v.detach() if is_torch(v) else v for k, v in self.extra.items()},
                             background=self.background)

    def copy(self) -> GaussianCloud:
        """Deep copy of every array."""
        dup = (lambda x: x.clone()) if self.is_torch else (lambda x: x.copy())
        return GaussianCloud(**{n: dup(getattr(self, n)) for n in PARAMETER_FIELDS},
                             extra={k: (v.clone() if is_torch(v) else v.copy()) for k, v in self.extra.items()},
                             background=self.background)

    # ------------------------------------------------------ geometry
    def normalization(self) -> tuple[np.ndarray, float]:
        """Centre (3,) and scale of the Gaussian centres, robust to a few far floaters: the centre
        of their 1st..99th percentile box and half of its longest side (1 when degenerate). This
        is the scene-normalised frame, (x - centre) / scale, of lineage features and Hessian
        scores, so that one model serves every scene."""
        return normalization_of(self.numpy().means)

    def transformed(self, matrix) -> GaussianCloud:
        """The cloud moved by a 4x4 matrix of rotation, uniform positive scale and translation (a
        Blender object's world matrix, say): positions, quaternions and log-scales change. SH rest
        coefficients are not rotated; a warning says so when they would need it. Raises
        ValueError for a non-uniform or mirroring scale, which Gaussians cannot follow."""
        m = np.array(matrix, np.float64).reshape(4, 4)
        lin = m[:3, :3]
        sv = np.linalg.svd(lin, compute_uv=False)
        if sv.min() <= 1e-12 or sv.max() / sv.min() - 1.0 > 1e-4:
            raise ValueError(f"the transform's scale is not uniform (singular values {np.round(sv, 6).tolist()})")
        if np.linalg.det(lin) < 0:
            raise ValueError("the transform mirrors (negative scale); Gaussians cannot be mirrored by a rotation")
        s = float(np.cbrt(np.linalg.det(lin)))
        rot = lin / s
        c = self.numpy()
        out = c.replace(
            means=(np.asarray(c.means, np.float64) @ lin.T + m[:3, 3]).astype(np.float32),
            quats=quaternions.multiply(quaternions.from_rotmat(rot)[None], np.asarray(c.quats, np.float64))
            .astype(np.float32),
            scales=(np.asarray(c.scales, np.float64) + math.log(s)).astype(np.float32))
        if c.sh_degree > 0 and not np.allclose(rot, np.eye(3), atol=1e-7):
            warnings.warn("SH rest coefficients (view-dependent colour) were not rotated with the cloud",
                          stacklevel=2)
        return out

    def append_children(self, children: GaussianCloud, parents) -> GaussianCloud:
        """This cloud followed by `children` (numpy), child i born from row `parents[i]` of the
        result: a row of this cloud or an earlier child. The one policy for the extra properties
        (which the algorithm does not interpret) of Gaussians that refinement or a control adds: a
        child takes its own value where `children.extra` has the property, else its parent's; where
        the cloud has `gvae_id`, each child gets a fresh id, and its parent's id as `gvae_parent`."""
        n, m = len(self), len(children)
        parents = np.asarray(parents, np.int64).reshape(-1)
        if len(parents) != m or (m and (parents.min() < 0 or (parents >= n + np.arange(m)).any())):
            raise ValueError(f"append_children: {len(parents)} parents for {m} children, each a row before "
                             f"the child's own")
        root = parents.copy()  # the ancestor of every child among this cloud's rows
        while (later := root >= n).any():
            root[later] = parents[root[later] - n]
        extra = {key: children.extra[key] if key in children.extra else np.asarray(value)[root]
                 for key, value in self.extra.items()}
        if "gvae_id" in self.extra and "gvae_id" not in children.extra:
            ids = np.asarray(self.extra["gvae_id"])
            new = (int(ids.max(initial=-1)) + 1 + np.arange(m)).astype(ids.dtype)
            extra["gvae_id"] = new
            if "gvae_parent" in self.extra:
                extra["gvae_parent"] = np.concatenate([ids, new])[parents].astype(self.extra["gvae_parent"].dtype)
        return GaussianCloud.concat([self.numpy(), children.numpy().replace(extra=extra)])

    # ------------------------------------------------------ validation
    def nonfinite_rows(self) -> np.ndarray:
        """Rows (ascending) with a NaN or an infinity in any parameter."""
        c = self.numpy()
        arrays = [getattr(c, name) for name in PARAMETER_FIELDS]
        with np.errstate(over="ignore", invalid="ignore"):  # a finite sum: every value is finite (cheap)
            if all(np.isfinite(a.sum()) for a in arrays):  # the usual case, without per-row bookkeeping
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

    def sanitize(self) -> GaussianCloud:
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
        out.scales = clip(out.scales, *LOG_SCALE_RANGE)
        out.opacities = clip(out.opacities, *OPACITY_LOGIT_RANGE)
        return out


def normalization_of(means) -> tuple[np.ndarray, float]:
    """`GaussianCloud.normalization` of the centres `means` (N,3) (for a subset of a cloud's rows
    without selecting the rest of its fields)."""
    p = np.asarray(means, np.float64).reshape(-1, 3)
    if not np.isfinite(p).all():
        p = p[np.isfinite(p).all(1)]
    if len(p) == 0:
        return np.zeros(3), 1.0
    lo, hi = np.percentile(p, [1, 99], axis=0)
    scale = float(np.max(hi - lo)) / 2.0
    return (lo + hi) / 2.0, (scale if scale > 1e-8 else 1.0)
