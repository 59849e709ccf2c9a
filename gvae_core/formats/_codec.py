"""What the splat codecs share: C-style rounding, 8-bit opacity both ways, what a writer refuses.

Every format here stores opacity as an 8-bit code of the activated value, round(255 * sigmoid(logit)).
Codes 0 and 255 would decode to logits of -inf and +inf; they decode a quarter step inside
instead, to the logit of 0.25/255 and 254.75/255 (about -6.93 and +6.93): within half a step of
what the code stands for, finite, invisible (below 1/255) or opaque (above the rasteriser's 0.99
cap) as the file meant, and encoding the decoded value gives the same code back.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..cloud import GaussianCloud
from ..conventions import sigmoid
from ..ply import PlyError

#: Decoded opacity of the end codes 0 and 255, in steps of 1/255 from their end of [0, 1].
END_CODE_INSET = 0.25


def round_half_away(x) -> np.ndarray:
    """C's round(), exactly, in the input's float type: halves away from zero (numpy's rint rounds
    them to even; x - rint(x) is exact, so the halves are found exactly)."""
    x = np.asarray(x)
    if x.dtype.kind != "f":
        x = x.astype(np.float64)
    r = np.rint(x)
    with np.errstate(invalid="ignore"):
        tie = np.abs(x - r) == 0.5
    if tie.any():
        r = np.where(tie, x + np.copysign(0.5, x), r)
    return r


def unorm_codes(values, levels: int) -> np.ndarray:
    """round(values * levels) clamped to 0..levels (halves away from zero), as int64."""
    with np.errstate(invalid="ignore"):
        return np.clip(round_half_away(np.asarray(values, np.float64) * levels), 0, levels).astype(np.int64)


def byte_codes(values) -> np.ndarray:
    """C's toUint8(x): round(x) (halves away from zero) clamped to 0..255, as uint8; float32 stays
    float32 throughout."""
    return np.clip(round_half_away(values), 0, 255).astype(np.uint8)


def opacity_codes(logits) -> np.ndarray:
    """8-bit codes of the activated opacities, round(255 * sigmoid(logit)), computed as Niantic's
    encoder does in float32 (`conventions.sigmoid` of float32 logits)."""
    return byte_codes(sigmoid(np.asarray(logits, np.float32)) * np.float32(255.0))


def _opacity_table() -> np.ndarray:
    p = np.arange(256, dtype=np.float64)
    p[0], p[255] = END_CODE_INSET, 255 - END_CODE_INSET
    p /= 255.0
    return np.log(p / (1.0 - p)).astype(np.float32)


#: Opacity logit of each 8-bit code.
OPACITY_OF_CODE = _opacity_table()


def writable(cloud: GaussianCloud, fmt: str, where: str) -> GaussianCloud:
    """The numpy cloud a writer of `fmt` writes: PlyError naming the rows with NaN or infinite
    parameters, which no format here can hold, and a warning listing the extra properties `fmt`
    cannot hold (at the writer's caller)."""
    c = cloud.numpy()
    bad = c.nonfinite_rows()
    if len(bad):
        head = ", ".join(str(i) for i in bad[:5]) + (", ..." if len(bad) > 5 else "")
        raise PlyError(f"{where}: refusing to write {len(bad)} Gaussian(s) with non-finite parameters, "
                       f"rows [{head}]; use cloud.sanitize() first")
    if c.extra:
        warnings.warn(f"{where}: {fmt} holds no extra properties; not written: " + ", ".join(c.extra), stacklevel=3)
    return c
