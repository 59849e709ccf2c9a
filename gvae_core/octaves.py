"""Resolution-aware changes: what a refinement changes per octave of sampling rate, stored with the
cloud and applied by the renderer in proportion to how far above its training sampling rate each
Gaussian is drawn.

A Gaussian was fitted at the highest sampling rate nu (pixels per world unit) at which its training
cameras saw it: the rate its anti-aliasing size stands for (`gvae_core.antialias`: nu =
sqrt(0.3) / `gvae_dilation_3D`, or sqrt(0.2) / `filter_3D`). Drawn by a camera of focal length f at
depth z, it is sampled at r = f / z; it is then

    t = clamp(log2(r / nu), 0, limit)    (t below 1e-4 counts as 0: the float32 rounding of the size)

octaves above what it was trained for, and every refined parameter p is drawn as p + t dp, with dp
the change per octave (extra properties `gvae_octave_<field>[_<column>]`, float32) and `limit`
(`gvae_octave_limit`) how many octaves the refinement covers. So at or below the training sampling
rate a refined cloud draws exactly as its input (the picture it was trained for is kept by
construction), at twice that rate it draws with one octave of change, and a Gaussian seen closer
than in training gets more of it than one seen from afar. Only the `matched` and `mip` renders
know nu; the `classic` render (and any other tool) draws the cloud as it was before refinement.
`bake` writes the changes into the parameters for one chosen factor of the training resolution:
a plain PLY for other tools. Fields that can change: log-scales, opacity logit, DC colour,
positions, quaternions (raw, normalised on use) and the higher SH bands; and the anti-aliasing size
itself (`SIZE`: the change per octave of its logarithm, `gvae_octave_size`, never above 0), so that
a Gaussian refined from images is drawn at 2^t times its training rate with the anti-aliasing of
that rate (its size times 2^-t, `REFINED_SIZE_CHANGE`) rather than of the one it was trained at.
The training rate nu stays the one the stored size says. numpy or torch.
"""

from __future__ import annotations

import math

import numpy as np

from .antialias import CLASSIC_DILATION, DILATION_KEY, FILTER_3D_VARIANCE, FILTER_KEY, max_sampling_rate
from .camera import Camera
from .cloud import GaussianCloud
from .conventions import NEAR_PLANE, is_torch
from .parallel import in_threads

__all__ = ["FIELDS", "SIZE", "REFINED_SIZE_CHANGE", "LIMIT_KEY", "field_keys", "has_octaves", "stored_keys",
           "octave_fields", "training_rate", "training_height", "octaves_seen", "with_octaves", "without_octaves",
           "drawn_fields", "bake"]

#: Fields a refinement may change, and the stem of their extra properties (one per column).
FIELDS = {"scales": "scale", "opacities": "opacity", "sh_dc": "dc", "means": "position", "quats": "rot",
          "sh_rest": "rest"}
#: The anti-aliasing size (`filter_3D` or `gvae_dilation_3D`, whichever the cloud has) as a field a
#: refinement may change: its change per octave is of its natural logarithm, one value a Gaussian.
SIZE = "size"
_SIZE_KEY = "gvae_octave_size"
#: The size's change per octave for a Gaussian refined to the rate it is drawn at: halved per octave.
REFINED_SIZE_CHANGE = -math.log(2.0)
#: Extra property: how many octaves above its training rate a Gaussian's change runs to.
LIMIT_KEY = "gvae_octave_limit"
#: Octaves below this count as none: the stored size is float32, so the training view itself can
#: come out a few 1e-8 octaves above its own rate.
DEADBAND = 1e-4
_PREFIX = "gvae_octave_"


def field_keys(field: str, columns: int) -> list[str]:
    """The extra-property names of a field's change per octave (`columns` values per Gaussian):
    `gvae_octave_opacity`, `gvae_octave_scale_0..2`, `gvae_octave_dc_0..2`, ..."""
    if field == SIZE:
        return [_SIZE_KEY]
    if field not in FIELDS:
        raise ValueError(f"octaves: unknown field {field!r}; known: {', '.join(FIELDS)}, {SIZE}")
    stem = _PREFIX + FIELDS[field]
    return [stem] if field == "opacities" else [f"{stem}_{i}" for i in range(columns)]


def _columns(cloud: GaussianCloud, field: str) -> int:
    if field == SIZE:
        return 1
    shape = tuple(getattr(cloud, field).shape)
    return int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1


def has_octaves(cloud: GaussianCloud) -> bool:
    return LIMIT_KEY in cloud.extra


def stored_keys(cloud: GaussianCloud) -> list[str]:
    """The cloud's extra properties that hold changes per octave (and their limit)."""
    return [k for k in cloud.extra if k.startswith(_PREFIX)]


def octave_fields(cloud: GaussianCloud) -> dict:
    """Field -> its change per octave, shaped like the field (numpy or torch, as stored), for the
    fields the cloud carries changes of."""
    out = {}
    for field in (*FIELDS, SIZE):
        keys = field_keys(field, _columns(cloud, field))
        if keys and all(k in cloud.extra for k in keys):
            cols = [cloud.extra[k] for k in keys]
            shape = (len(cloud),) if field == SIZE else tuple(getattr(cloud, field).shape)
            if is_torch(cols[0]):
                import torch  # noqa: PLC0415 - numpy-first module

                out[field] = torch.stack([c.reshape(-1) for c in cols], -1).reshape(shape)
            else:
                out[field] = np.stack([np.asarray(c, np.float32).reshape(-1) for c in cols], -1).reshape(shape)
    return out


def with_octaves(cloud: GaussianCloud, changes: dict, limit: float = 1.0) -> GaussianCloud:
    """`cloud` carrying `changes` (field -> change per octave, shaped like the field; numpy, or
    torch to train through the renderer) up to `limit` octaves above each Gaussian's training
    rate. The cloud must know its training rate (an anti-aliasing size)."""
    if training_rate(cloud) is None:
        raise ValueError(f"octaves: the cloud needs its anti-aliasing size ({DILATION_KEY} or {FILTER_KEY}) to know "
                         "the sampling rate it was trained at")
    if not limit > 0 or not math.isfinite(limit):
        raise ValueError(f"octaves: limit must be a positive number of octaves, got {limit!r}")
    extra = dict(without_octaves(cloud).extra)
    n = len(cloud)
    for field, change in changes.items():
        keys = field_keys(field, _columns(cloud, field))
        flat = change.reshape(n, len(keys))
        for i, k in enumerate(keys):
            extra[k] = flat[:, i] if is_torch(flat) else np.ascontiguousarray(flat[:, i], np.float32)
    extra[LIMIT_KEY] = np.full(n, limit, np.float32)
    return cloud.replace(extra=extra)


def without_octaves(cloud: GaussianCloud) -> GaussianCloud:
    """The cloud without stored changes (drawn as it was before refinement)."""
    return cloud.replace(extra={k: v for k, v in cloud.extra.items() if not k.startswith(_PREFIX)})


def training_rate(cloud: GaussianCloud):
    """(N,) the sampling rate nu each Gaussian was trained at, from its anti-aliasing size (the one
    the `auto` render uses; numpy float64, or torch as stored); None for a cloud without one."""
    for key, variance in ((FILTER_KEY, FILTER_3D_VARIANCE), (DILATION_KEY, CLASSIC_DILATION)):
        if key in cloud.extra:
            size = cloud.extra[key]
            if is_torch(size):
                return math.sqrt(variance) / size.reshape(-1).clamp(min=1e-30)
            return math.sqrt(variance) / np.maximum(np.asarray(size, np.float64).reshape(-1), 1e-30)
    return None


def training_height(cloud: GaussianCloud, cameras) -> tuple[float, float]:
    """The image height at which `cameras` (a capture's, at any size) trained `cloud`, read from its
    anti-aliasing size, and the share of the Gaussians those cameras see that agree with it within
    10%. A Gaussian's training rate is the largest f / z of the cameras that saw it, so against
    the same cameras at height h it is h_train / h times theirs, for every Gaussian alike: a low share
    says the cameras are not the ones the cloud was trained with. (nan, 0) for a cloud without a size
    or a view of nothing."""
    rate = training_rate(cloud)
    if rate is None or not len(cameras):
        return float("nan"), 0.0
    cams = list(cameras)
    theirs = max_sampling_rate(np.asarray(cloud.means, np.float64), cams)
    seen = (theirs > 0) & np.isfinite(rate) & (rate > 0) & (rate < 1e29)
    if not seen.any():
        return float("nan"), 0.0
    ratio = rate[seen] / theirs[seen]
    factor = float(np.median(ratio))
    agree = float(np.mean(np.abs(ratio / factor - 1.0) <= 0.1))
    return cams[0].height * factor, agree


def octaves_seen(means, rate, limit, camera: Camera):
    """(N,) t = clamp(log2((f / z) / nu), 0, limit) (0 below DEADBAND) for Gaussians at `means` through `camera`
    (numpy float64, or torch without gradient); 0 behind the near plane and where nu is 0."""
    if is_torch(means):
        import torch  # noqa: PLC0415 - numpy-first module

        with torch.no_grad():
            m = means.detach().to(torch.float64)
            center = torch.as_tensor(camera.center, dtype=torch.float64, device=m.device)
            rot = torch.as_tensor(camera.rotation, dtype=torch.float64, device=m.device)
            z = (m - center) @ rot[2]
            nu = torch.as_tensor(rate, device=m.device).to(torch.float64).reshape(-1)
            ok = torch.isfinite(z) & (z > NEAR_PLANE) & (nu > 0)
            r = max(camera.fx, camera.fy) / torch.where(ok, z, torch.ones_like(z))
            t = torch.log2(torch.where(ok, r / torch.where(ok, nu, torch.ones_like(nu)), torch.ones_like(r)))
            lim = torch.as_tensor(limit, device=m.device).to(torch.float64).reshape(-1)
            t = torch.where(t < DEADBAND, torch.zeros_like(t), t)
            return torch.minimum(t, lim).nan_to_num(0.0)
    m = np.asarray(means).reshape(-1, 3)
    nu = np.asarray(rate).reshape(-1)
    lim = np.broadcast_to(np.asarray(limit).reshape(-1), (len(m),))
    out = np.empty(len(m))

    def part(a: int, b: int) -> None:  # float64 per range of rows, in threads (parallel.in_threads)
        z = (np.asarray(m[a:b], np.float64) - camera.center) @ camera.rotation[2]
        r = np.asarray(nu[a:b], np.float64)
        ok = np.isfinite(z) & (z > NEAR_PLANE) & (r > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(ok, np.log2(np.where(ok, max(camera.fx, camera.fy) / np.where(ok, z, 1.0)
                                              / np.where(ok, r, 1.0), 1.0)), 0.0)
        t = np.where(t < DEADBAND, 0.0, t)
        out[a:b] = np.nan_to_num(np.minimum(t, np.asarray(lim[a:b], np.float64)))

    in_threads(len(m), part)
    return out


def drawn_fields(fields: dict, cloud: GaussianCloud, camera: Camera) -> dict:
    """`fields` (field -> torch tensor of the cloud's values; SIZE: its anti-aliasing size) as drawn
    through `camera`: each refined field plus t times its change per octave, the size times
    e^(t times its change) (gradients reach the stored changes)."""
    changes = octave_fields(cloud)
    rate = training_rate(cloud)
    if not changes or rate is None:
        return fields
    import torch  # noqa: PLC0415 - numpy-first module

    means = fields["means"]
    limit = cloud.extra[LIMIT_KEY]
    if all(not is_torch(x) or x.device.type == "cpu" for x in (means, rate, limit)):
        # on the CPU by numpy in threads (the same float64 arithmetic; torch's element-wise passes cost more)
        t = torch.from_numpy(octaves_seen(*(x.detach().numpy() if is_torch(x) else x for x in (means, rate, limit)),
                                          camera)).to(means.device)
    else:
        t = octaves_seen(means, rate if is_torch(rate) else torch.from_numpy(np.asarray(rate)),
                         limit if is_torch(limit) else torch.from_numpy(np.asarray(limit, np.float32)), camera)
    out = dict(fields)
    for field, change in changes.items():
        if field not in out:
            continue
        value = out[field]
        d = change if is_torch(change) else torch.from_numpy(np.ascontiguousarray(change))
        d = d.to(device=value.device, dtype=value.dtype)
        tt = t.to(value.dtype).reshape((-1,) + (1,) * (value.dim() - 1))
        step = tt * torch.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)
        out[field] = value * torch.exp(step.clamp(max=0.0)) if field == SIZE else value + step
    return out


def bake(cloud: GaussianCloud, factor: float = 2.0) -> GaussianCloud:
    """A plain cloud for other tools, drawn as the refined one is at `factor` times the training
    resolution at the training distance: every Gaussian takes t = clamp(log2(factor), 0, limit)
    octaves of its change; the stored changes are dropped. numpy."""
    if not factor > 0 or not math.isfinite(factor):
        raise ValueError(f"bake: factor must be a positive number, got {factor!r}")
    c = cloud.numpy()
    changes = octave_fields(c)
    out = without_octaves(c)
    if not changes:
        return out
    limit = np.asarray(c.extra[LIMIT_KEY], np.float64)
    t = np.clip(math.log2(factor), 0.0, limit).astype(np.float32)
    new = {}
    size = changes.pop(SIZE, None)
    for field, change in changes.items():
        value = getattr(c, field)
        tt = t.reshape((-1,) + (1,) * (value.ndim - 1))
        new[field] = (value + tt * np.nan_to_num(change)).astype(np.float32)
    if size is not None:  # the baked cloud's anti-aliasing size says the rate it is drawn for
        key = FILTER_KEY if FILTER_KEY in c.extra else DILATION_KEY
        shrink = np.exp(np.minimum(t * np.nan_to_num(size), 0.0))
        new["extra"] = {**out.extra, key: (np.asarray(c.extra[key], np.float32) * shrink).astype(np.float32)}
    return out.replace(**new)
