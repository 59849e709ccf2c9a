"""Posed images (`Views`) and how they are read and resampled; captures are read by `gvae_core.capture`.

Images are straight (not premultiplied) RGB in [0, 1] with a separate alpha (1 for photos);
downsampling averages areas exactly (box filter with fractional overlaps) in premultiplied space,
so transparent pixels do not bleed their colour into the result.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .camera import Camera

__all__ = ["DatasetError", "Views", "read_rgba", "resize_rgba", "premultiplied", "resize_area", "resize_area_reference",
           "every_nth", "name_order"]

class DatasetError(ValueError):
    """A dataset folder that cannot be read: the message names the file and what is wrong."""


@dataclass
class Views:
    """Posed images: cameras[i] took images[i] (N,H,W,3 straight RGB) with alphas[i] (N,H,W)."""

    cameras: list[Camera]
    images: np.ndarray
    alphas: np.ndarray | None = None
    names: list[str] | None = None

    def __post_init__(self):
        self.cameras = list(self.cameras)
        self.images = np.asarray(self.images, np.float32)
        self.alphas = (np.ones(self.images.shape[:3], np.float32) if self.alphas is None
                       else np.asarray(self.alphas, np.float32))
        if self.names is None:
            self.names = [f"view_{i:03d}" for i in range(len(self.cameras))]
        if self.images.ndim != 4 or self.images.shape[-1] != 3 or self.alphas.shape != self.images.shape[:3] \
                or len(self.cameras) != len(self.images) or len(self.names) != len(self.cameras):
            raise ValueError(f"Views: need N cameras and names, (N,H,W,3) images and (N,H,W) alphas, got "
                             f"{len(self.cameras)}, {len(self.names)}, {self.images.shape}, {self.alphas.shape}")

    def __len__(self) -> int:
        return len(self.cameras)

    def subset(self, rows) -> Views:
        """The views at `rows` (indices, in the order given)."""
        rows = np.asarray(rows, np.int64)
        return Views([self.cameras[i] for i in rows], self.images[rows], self.alphas[rows],
                     [self.names[i] for i in rows])

    def at_resolution(self, height: int) -> Views:
        """The same views at another image height: cameras scaled, RGBA area-averaged in
        premultiplied space (as reading a capture does)."""
        if int(height) == self.images.shape[1]:
            return self
        cams = [c.scaled(int(height)) for c in self.cameras]
        rgba = np.concatenate([self.images, self.alphas[..., None]], -1)
        out = np.stack([resize_rgba(x, cams[0].height, cams[0].width) for x in rgba])
        return Views(cams, out[..., :3], out[..., 3], list(self.names))

    def composite(self, background=(0.0, 0.0, 0.0)) -> np.ndarray:
        """(N,H,W,3) float32 images over a constant background: rgb*alpha + bg*(1-alpha)."""
        bg = np.asarray(background, np.float32).reshape(1, 1, 1, -1)
        a = self.alphas[..., None]
        return (self.images * a + bg * (1.0 - a)).astype(np.float32, copy=False)


def name_order(names: Sequence[str]) -> list[int]:
    """Indices of `names` sorted by name, numbers by value ("r_2" before "r_10", as a file browser
    lists them; the plain sort wherever numbers are zero-padded, as cameras name photos)."""
    def key(i: int):
        parts = re.split(r"(\d+)", names[i])
        return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts], names[i]
    return sorted(range(len(names)), key=key)


def every_nth(names: Sequence[str], every, offset=0) -> np.ndarray:
    """The one hold-out rule: the rows of every `every`-th of `names` sorted by name (`name_order`),
    from the `offset`-th, in ascending row order. `every` and `offset` may be fractions (a number of
    picks spread evenly: every n/k-th from half way); the k-th pick is the name at position
    round(offset + k * every), the rounding of the exact value (`fractions.Fraction`)."""
    n = len(names)
    every, offset = Fraction(every), Fraction(offset)
    if every <= 0 or offset < 0:
        raise ValueError(f"every_nth: every must be positive and offset >= 0, got {every}, {offset}")
    order = name_order(names)
    positions = []
    k = 0
    while offset + k * every < n:
        positions.append(int(np.round(float(offset + k * every))))
        k += 1
    return np.array(sorted({order[p] for p in positions if p < n}), np.int64)


def read_rgba(path: Path) -> np.ndarray:
    """(H,W,4) float32 in [0,1]; images without alpha get alpha 1."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                gray = np.asarray(im, np.float64) / 65535.0
                return np.dstack([gray, gray, gray, np.ones_like(gray)]).astype(np.float32)
            return np.asarray(im.convert("RGBA"), np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot read image: {exc}") from None


# ------------------------------------------------------------------------ area resampling

def _box_axis0(img: np.ndarray, n_out: int) -> np.ndarray:
    """The exact box filter along axis 0: output pixel i averages the input interval [i*s, (i+1)*s),
    s = n_in / n_out, as differences of the input's running sum at the interval's ends (the sum is
    linear within a pixel), in O(n_in) per column rather than a dense n_out x n_in product."""
    n_in = img.shape[0]
    s = n_in / n_out
    edges = np.arange(n_out + 1) * s
    row = np.minimum(np.floor(edges).astype(np.int64), n_in - 1)
    frac = (edges - row).reshape((-1,) + (1,) * (img.ndim - 1))
    running = np.concatenate([np.zeros((1,) + img.shape[1:]), np.cumsum(img, axis=0)])
    at_edges = running[row] + frac * img[row]
    return (at_edges[1:] - at_edges[:-1]) / s


def resize_area(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-average (H,W,...) to (height,width,...): separable exact box filter, float64 inside."""
    img = np.asarray(image, np.float64)
    out = _box_axis0(img, height)                                       # (height, W, ...)
    out = np.moveaxis(_box_axis0(np.moveaxis(out, 1, 0), width), 0, 1)  # (height, width, ...)
    return out.astype(np.float32)


def resize_area_reference(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Slow, obviously correct `resize_area`: integrate the piecewise-constant image over each
    output pixel's rectangle, pixel by pixel (for tests)."""
    img = np.asarray(image, np.float64)
    h, w = img.shape[:2]
    sy, sx = h / height, w / width
    out = np.zeros((height, width) + img.shape[2:])
    for i in range(height):
        y0, y1 = i * sy, (i + 1) * sy
        for j in range(width):
            x0, x1 = j * sx, (j + 1) * sx
            acc = np.zeros(img.shape[2:])
            for r in range(int(math.floor(y0)), min(h, int(math.ceil(y1)))):
                dy = min(y1, r + 1) - max(y0, r)
                for c in range(int(math.floor(x0)), min(w, int(math.ceil(x1)))):
                    dx = min(x1, c + 1) - max(x0, c)
                    if dy > 0 and dx > 0:
                        acc = acc + dy * dx * img[r, c]
            out[i, j] = acc / (sy * sx)
    return out.astype(np.float32)


def premultiplied(rgba: np.ndarray, resample) -> np.ndarray:
    """Straight RGBA resampled by `resample` ((H,W,4) -> (h,w,4), linear in the pixels) in
    premultiplied space, then un-premultiplied: transparent pixels lend no colour to the result."""
    alpha = rgba[..., 3:4].astype(np.float64)
    out = np.asarray(resample(np.concatenate([rgba[..., :3] * alpha, alpha], axis=-1)), np.float64)
    a = np.clip(out[..., 3:4], 0.0, 1.0)
    rgb = np.where(a > 0, out[..., :3] / np.where(a > 0, a, 1.0), 0.0)
    return np.concatenate([np.clip(rgb, 0.0, 1.0), a], axis=-1).astype(np.float32)


def resize_rgba(rgba: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize straight RGBA by area averaging in premultiplied space (`premultiplied`)."""
    return premultiplied(rgba, lambda x: resize_area(x, height, width))
