"""Tests for gvae_core.metrics.niqe (NIQE no-reference image quality)."""

import importlib
import warnings

import numpy as np
import pytest
import skvideo.measure
from scipy import ndimage
from skvideo.measure.niqe import get_patches_test_features

from gvae_core.metrics.niqe import niqe, niqe_features, niqe_model

niqe_mod = importlib.import_module("gvae_core.metrics.niqe")


def smooth_scene(h, w, seed=0):
    """Natural-ish smooth image in [0, 1]: random oriented sinusoids + band-limited noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w))
    for _ in range(12):
        f = rng.uniform(0.005, 0.08)
        th, ph = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        img += rng.uniform(0.3, 1) / (1 + 20 * f) * np.sin(2 * np.pi * f * (xx * np.cos(th) + yy * np.sin(th)) + ph)
    noise = ndimage.gaussian_filter(rng.standard_normal((h, w)), 1.5)
    img += 0.4 * img.std() * noise / noise.std()
    return (img - img.min()) / (img.max() - img.min())


def pink_texture(n, seed=0):
    """Sharp textured image in [0, 1] with a natural 1/f amplitude spectrum."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n)
    fr = np.hypot(*np.meshgrid(f, f))
    fr[0, 0] = 1.0
    img = np.fft.ifft2((rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) / fr).real
    return (img - img.min()) / (img.max() - img.min())


def reference_niqe(img01):
    """The package's own (slow, per-patch) NIQE on 0..255 float luminance."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # skvideo imports scipy.misc

        return float(skvideo.measure.niqe(np.asarray(img01, dtype=np.float64) * 255.0)[0])


def reference_features(img01):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)

        return get_patches_test_features(np.asarray(img01, dtype=np.float64) * 255.0, 96)


_SCENE = smooth_scene(260, 330)
_CASES = {
    "smooth": _SCENE,
    "smooth_blurred": ndimage.gaussian_filter(_SCENE, 2.0),
    "pink_texture": pink_texture(300, seed=3),
}


@pytest.mark.parametrize("name", sorted(_CASES))
def test_agrees_with_package(name):
    img = _CASES[name]
    ours, ref = niqe(img), reference_niqe(img)
    assert np.isfinite(ours)
    assert ours == pytest.approx(ref, rel=1e-3)
    # per-patch features match too (measured ~1e-7; float32 vs float64 sums). Under NumPy 2 the
    # package's own float32 arithmetic changes with the type promotion rules (NEP 50; numpy 1.26 with
    # weak promotion gives the same): up to 8e-4 relative; ours is the same under both.
    rtol = 1e-5 if np.lib.NumpyVersion(np.__version__) < "2.0.0" else 2e-3
    np.testing.assert_allclose(niqe_features(img), reference_features(img), rtol=rtol, atol=1e-9)


def test_blur_raises_score():
    sharp = pink_texture(384, seed=0)
    s0 = niqe(sharp)
    for sigma in (1.0, 1.5):
        assert niqe(ndimage.gaussian_filter(sharp, sigma)) > 1.1 * s0


def test_flat_images_finite_without_warnings():
    half = _SCENE.copy()
    half[:, 165:] = 1.0
    images = [np.full((256, 256), 0.5), np.zeros((200, 300)), np.full((256, 256, 3), 255, np.uint8), half]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scores = [niqe(im) for im in images]
        feats = niqe_features(np.full((400, 400), 0.5))
    assert all(np.isfinite(s) for s in scores)
    assert np.isfinite(feats).all()
    # an interior patch of a flat image (4x4 patches, index 5) has all-zero MSCN and
    # paired-product data at both scales: every shape is 0.2 and every other feature 0
    expected = np.zeros(36)
    expected[[0, 2, 6, 10, 14, 18, 20, 24, 28, 32]] = 0.2
    np.testing.assert_allclose(feats[5], expected, rtol=1e-12, atol=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the package takes NaN paths here
        assert scores[3] == pytest.approx(reference_niqe(half), rel=1e-3)


def test_aggd_degenerate_rows():
    rng = np.random.default_rng(0)
    pos = np.abs(rng.standard_normal(500)) + 0.1
    rows = np.stack([np.zeros(500), pos, -pos, rng.standard_normal(500)]).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alpha, n, bl, br = niqe_mod._aggd_fit(rows)
    for v in (alpha, n, bl, br):
        assert np.isfinite(v).all()
    assert (alpha[0], n[0], bl[0], br[0]) == (pytest.approx(0.2), 0.0, 0.0, 0.0)
    # no-left and no-right data are mirror images: same shape, swapped scales, negated mean
    assert alpha[1] == alpha[2] and bl[1] == br[2] and br[1] == bl[2] and n[1] == -n[2]
    assert bl[1] == 0.0 and br[1] > 0


@pytest.mark.parametrize("shape", [(192, 400), (400, 150), (100, 100, 3)])
def test_too_small_raises(shape):
    h, w = shape[:2]
    with pytest.raises(ValueError, match=f"{h}x{w}"):
        niqe(np.zeros(shape))


def test_bad_input_raises():
    img = _SCENE.copy()
    img[10, 10] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        niqe(img)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        niqe(_SCENE * 255.0)
    with pytest.raises(ValueError, match="patch_size"):
        niqe(_SCENE, patch_size=95)


def test_uint8_and_float_inputs_agree():
    rgb8 = np.round(np.stack([_SCENE, _SCENE**1.5, 1 - _SCENE], axis=-1) * 255).astype(np.uint8)
    grey8 = rgb8[..., 0]
    assert niqe(grey8) == pytest.approx(niqe(grey8 / 255.0), rel=1e-9)
    assert niqe(rgb8) == pytest.approx(niqe(rgb8 / 255.0), rel=1e-9)
    # float32 input perturbs the luminance by ~1 ulp; the float32 MSCN (as in the
    # package) amplifies that where I - mu cancels, to ~1e-5 relative in the score
    assert niqe(rgb8) == pytest.approx(niqe(rgb8.astype(np.float32) / np.float32(255)), rel=1e-4)
    lum = rgb8.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    assert niqe(rgb8) == pytest.approx(niqe(lum / 255.0), rel=1e-6)
    assert niqe(rgb8) == pytest.approx(reference_niqe(lum / 255.0), rel=1e-3)


def test_model_loaded_once():
    mu, cov = niqe_model()
    assert mu.shape == (36,) and cov.shape == (36, 36)
    assert np.allclose(cov, cov.T)
    assert niqe_model()[0] is mu
    assert not mu.flags.writeable
