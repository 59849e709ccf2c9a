"""NeRF-Synthetic style datasets: `transforms_{split}.json` plus RGBA images, read with Pillow.

Cameras are converted from the Blender/OpenGL camera-to-world matrices of the JSON file to the
OpenCV convention of `Camera`. Images are straight (not premultiplied) RGB in [0, 1] with a
separate alpha; downsampling averages areas exactly (box filter with fractional overlaps) in
premultiplied space, so transparent pixels do not bleed their colour into the result.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .camera import Camera

__all__ = ["DatasetError", "Views", "load_nerf_synthetic", "resize_area", "resize_area_reference"]

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".webp")


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

    def at_resolution(self, height: int) -> Views:
        """The same views at another image height: cameras scaled, RGBA area-averaged in
        premultiplied space (as `load_nerf_synthetic` does)."""
        if int(height) == self.images.shape[1]:
            return self
        cams = [c.scaled(int(height)) for c in self.cameras]
        rgba = np.concatenate([self.images, self.alphas[..., None]], -1)
        out = np.stack([_resize_rgba(x, cams[0].height, cams[0].width) for x in rgba])
        return Views(cams, out[..., :3], out[..., 3], list(self.names))

    def composite(self, background=(0.0, 0.0, 0.0)) -> np.ndarray:
        """(N,H,W,3) float32 images over a constant background: rgb*alpha + bg*(1-alpha)."""
        bg = np.asarray(background, np.float32).reshape(1, 1, 1, -1)
        a = self.alphas[..., None]
        return (self.images * a + bg * (1.0 - a)).astype(np.float32, copy=False)


def read_transforms(path: Path) -> tuple[dict, list]:
    """A transforms JSON (NeRF-Synthetic, Instant-NGP, nerfstudio) and its non-empty 'frames'
    list; DatasetError naming the file when it is not one."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: malformed JSON: {exc}") from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{path}: malformed: expected an object with a non-empty 'frames' list")
    return meta, frames


def load_nerf_synthetic(root, split: str = "train", resolution: int | None = None) -> Views:
    """Read `root/transforms_{split}.json` and its images.

    `resolution` is the image height in pixels to downsample to (width keeps the aspect ratio,
    rounded like `Camera.scaled`); None keeps the stored size."""
    root = Path(root)
    meta_path = root / f"transforms_{split}.json"
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path}: missing (no {split!r} split in {root})")
    meta, frames = read_transforms(meta_path)
    try:
        angle_x = float(meta["camera_angle_x"])
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{meta_path}: malformed: missing or non-numeric 'camera_angle_x'") from None
    if not 0.0 < angle_x < math.pi:
        raise DatasetError(f"{meta_path}: camera_angle_x {angle_x} is not in (0, pi)")
    if resolution is not None and int(resolution) <= 0:
        raise ValueError(f"load_nerf_synthetic: resolution must be a positive height, got {resolution}")

    cameras, names = [], []
    images = alphas = None  # allocated once the first image gives the size (no list + stack copy)
    size = None
    for i, frame in enumerate(frames):
        try:
            c2w = np.asarray(frame["transform_matrix"], np.float64)
            rel = str(frame["file_path"])
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{meta_path}: malformed frame {i}: needs 'file_path' and a numeric "
                               "'transform_matrix'") from None
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise DatasetError(f"{meta_path}: frame {i}: transform_matrix must be a finite 4x4 matrix")
        image_path = _find_image(root, rel, meta_path, i)
        rgba = _read_rgba(image_path)
        h, w = rgba.shape[:2]
        if size is None:
            size = (h, w)
        elif size != (h, w):
            raise DatasetError(f"{image_path}: size {w}x{h} differs from the first image's "
                               f"{size[1]}x{size[0]}")
        cam = Camera.from_blender_c2w(c2w, angle_x, w, h)
        if resolution is not None and int(resolution) != h:
            cam = cam.scaled(int(resolution))
            rgba = _resize_rgba(rgba, cam.height, cam.width)
        if images is None:
            images = np.empty((len(frames), cam.height, cam.width, 3), np.float32)
            alphas = np.empty((len(frames), cam.height, cam.width), np.float32)
        images[i] = rgba[..., :3]
        alphas[i] = rgba[..., 3]
        cameras.append(cam)
        names.append(Path(rel).stem)
    return Views(cameras, images, alphas, names)


def _find_image(root: Path, rel: str, meta_path: Path, index: int) -> Path:
    """The image a frame's file_path refers to; NeRF-Synthetic omits the '.png' suffix."""
    base = root / rel
    candidates = [base] if base.suffix.lower() in _IMAGE_SUFFIXES else []
    candidates += [base.with_name(base.name + s) for s in _IMAGE_SUFFIXES]
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetError(f"{candidates[0]}: image not found (frame {index} of {meta_path}, file_path {rel!r})")


def _read_rgba(path: Path) -> np.ndarray:
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

def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of the exact box filter: output pixel i covers the input interval
    [i*s, (i+1)*s) with s = n_in/n_out; the weight of input pixel j is its overlap divided by s."""
    s = n_in / n_out
    lo = np.arange(n_out)[:, None] * s
    j = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(lo + s, j + 1) - np.maximum(lo, j), 0.0, None)
    return overlap / s


def resize_area(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-average (H,W,...) to (height,width,...): separable exact box filter, float64 inside."""
    img = np.asarray(image, np.float64)
    wy = _area_weights(img.shape[0], height)
    wx = _area_weights(img.shape[1], width)
    out = np.tensordot(wy, img, axes=(1, 0))                 # (height, W, ...)
    out = np.moveaxis(np.tensordot(wx, out, axes=(1, 1)), 0, 1)  # (height, width, ...)
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


def _resize_rgba(rgba: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize straight RGBA by area averaging in premultiplied space, then un-premultiply."""
    alpha = rgba[..., 3:4].astype(np.float64)
    premult = np.concatenate([rgba[..., :3] * alpha, alpha], axis=-1)
    out = resize_area(premult, height, width).astype(np.float64)
    a = np.clip(out[..., 3:4], 0.0, 1.0)
    rgb = np.where(a > 0, out[..., :3] / np.where(a > 0, a, 1.0), 0.0)
    return np.concatenate([np.clip(rgb, 0.0, 1.0), a], axis=-1).astype(np.float32)
