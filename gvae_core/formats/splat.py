"""The web viewers' `.splat` (antimatter15's WebGL viewer and the tools that followed it).

No header: a flat array of 32-byte little-endian records, one per Gaussian, so a file's size is a
multiple of 32 and the count is size / 32:

    offset  bytes  field
    0       12     x, y, z             float32 position
    12      12     sx, sy, sz          float32 scales, activated: exp(log-scale)
    24      4      r, g, b, a          uint8: 255 * (SH_C0 * f_dc + 0.5) and 255 * sigmoid(opacity)
    28      4      qw, qx, qy, qz      uint8: 128 * q / |q| + 128 (rot_0..3 order)

There are no SH rest coefficients (degree 0). Decoding (what the viewers do):
- position exact; log-scale = log(s): a scale of 0 (an underflowed exp) is a flat axis, log-scale -inf,
  read as LOG_SCALE_RANGE[0] with a warning (`ply.drop_nonfinite`); a negative scale or one that is
  not finite makes a non-finite row;
- f_dc = (c / 255 - 0.5) / SH_C0: within half a step, 0.5 / 255 / SH_C0 ~ 0.007, for colours in [0, 1]
  (those outside were clipped);
- opacity: the logit of a / 255, the end codes a quarter step inside (see `_codec`): sigmoid within
  0.5 / 255;
- quaternion (b - 128) / 128, not normalised (the cloud normalises on use; 128,128,128,128 is the
  zero quaternion, the identity): each component of the unit quaternion within 1/256, 1/128 at +1.
Encoding rounds to nearest (the original converter truncated), clamps log-scales as `exp` on use
does, and keeps the row order (the converter sorted by size times opacity; viewers sort anyway).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..atomic import atomic_write
from ..cloud import GaussianCloud
from ..conventions import activate_scales, dc_to_rgb, rgb_to_dc
from ..ply import PlyError, drop_nonfinite
from ._codec import OPACITY_OF_CODE, opacity_codes, unorm_codes, writable

__all__ = ["RECORD", "read_splat", "write_splat", "looks_like_splat"]

#: One Gaussian of a .splat file.
RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])

_DC_OF_CODE = rgb_to_dc(np.arange(256) / 255.0).astype(np.float32)
_ROT_OF_CODE = ((np.arange(256) - 128) / 128.0).astype(np.float32)


def looks_like_splat(head: bytes, size: int) -> bool:
    """Whether a file without a signature, of `size` bytes starting with `head`, reads as .splat:
    a whole number of records whose first ones have finite positions and positive finite scales."""
    if size == 0 or size % RECORD.itemsize:
        return False
    rows = np.frombuffer(head[:len(head) - len(head) % RECORD.itemsize], RECORD)[:64]
    with np.errstate(invalid="ignore"):
        return bool(len(rows) and np.isfinite(rows["position"]).all()
                    and (np.isfinite(rows["scale"]) & (rows["scale"] > 0)).all())


def read_splat(path, *, sanitize: bool = False) -> GaussianCloud:
    """Read a .splat file into a numpy GaussianCloud (SH degree 0).

    Zero scales are flat axes (read as the smallest log-scale, with a warning); rows with other
    non-finite values (or negative scales) raise PlyError naming them, unless `sanitize` is true:
    then they are dropped with a warning."""
    path = Path(path)
    where = str(path)
    size = path.stat().st_size
    if size == 0:
        raise PlyError(f"{where}: empty file: a .splat holds at least one {RECORD.itemsize}-byte record")
    if size % RECORD.itemsize:
        raise PlyError(f"{where}: not a .splat file or truncated: {size} bytes is not a whole number "
                       f"of {RECORD.itemsize}-byte records")
    rec = np.fromfile(path, RECORD)
    if len(rec) * RECORD.itemsize != size:
        raise PlyError(f"{where}: truncated while reading (did the file change?)")
    n = len(rec)
    means = np.ascontiguousarray(rec["position"])
    s = rec["scale"]
    with np.errstate(divide="ignore", invalid="ignore"):
        scales = np.log(s)
    rgba = rec["rgba"]
    cloud = GaussianCloud(means=means, scales=scales, quats=_ROT_OF_CODE[rec["rot"]],
                          opacities=OPACITY_OF_CODE[rgba[:, 3]], sh_dc=_DC_OF_CODE[rgba[:, :3]],
                          sh_rest=np.zeros((n, 0, 3), np.float32))
    finite = np.ones(n, bool)
    if not (np.isfinite(means.sum()) and np.isfinite(scales.sum())):
        finite = np.isfinite(means).all(1) & np.isfinite(scales).all(1)
    return drop_nonfinite(cloud, finite, where, sanitize, stacklevel=3)


def write_splat(cloud: GaussianCloud, path) -> Path:
    """Write `cloud` as a .splat file (atomic). SH rest coefficients and extra properties are not
    stored (a warning says so when there are any); non-finite rows are refused (PlyError)."""
    path = Path(path)
    where = str(path)
    c = writable(cloud, ".splat", where)
    if c.sh_degree:
        warnings.warn(f"{where}: .splat holds no view-dependent colour; the SH degree {c.sh_degree} "
                      "coefficients are not written", stacklevel=2)
    rec = np.empty(len(c), RECORD)
    rec["position"] = c.means
    rec["scale"] = activate_scales(c.scales)
    rec["rgba"][:, :3] = unorm_codes(dc_to_rgb(c.sh_dc), 255)
    rec["rgba"][:, 3] = opacity_codes(c.opacities)
    rec["rot"] = unorm_codes((c.unit_quats().astype(np.float64) + 1.0) / 2.0, 256).clip(0, 255)
    return atomic_write(path, lambda f: f.write(rec.tobytes()))
