"""Anti-aliasing that follows the training resolution: the 3D filter size from cameras, and every
render mode against the float64 reference, its gradients and its hard cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud, orbit
from gvae_core.antialias import (CLASSIC_DILATION, DILATION_KEY, FILTER_3D_VARIANCE, FILTER_KEY, _camera_rate,
                                 dilation_3d,
                                 filter_3d, filter_3d_reference, max_sampling_rate, resolve_antialias,
                                 with_dilation_3d, with_filter_3d, with_training_cameras)
from gvae_core.rendering import ANTIALIAS_MODES, RenderSettings, render
from gvae_core.rendering.reference import render_reference

from .test_render import BG, FIELDS, _with, assert_parity, camera, random_cloud

MODES = ("classic", "mip", "matched", "auto")


def filtered(cloud: GaussianCloud, seed: int = 0, lo: float = -5.0, hi: float = -1.5,
             key: str = FILTER_KEY) -> GaussianCloud:
    """`cloud` with random sizes (`key`: Mip's 3D filter or the world dilation) from exp(lo) to
    exp(hi) world units."""
    f = np.exp(np.random.default_rng(seed).uniform(lo, hi, len(cloud))).astype(np.float32)
    return cloud.replace(extra={**cloud.extra, key: f})


# ------------------------------------------------------------ the filter size
def test_filter_size_of_one_camera_is_sqrt_k_depth_over_focal():
    cam = Camera(np.eye(4), 50.0, 40.0, 20.0, 15.0, 40, 30)  # at the origin, looking along +z
    means = np.array([[0.0, 0.0, 2.0], [0.1, -0.1, 4.0]])
    np.testing.assert_allclose(filter_3d(means, [cam]), math.sqrt(FILTER_3D_VARIANCE) * np.array([2.0, 4.0]) / 50.0,
                               rtol=1e-6)
    # the finest sampling wins: a second camera twice as close halves the filter
    w2c = np.eye(4)
    w2c[2, 3] = -1.0  # a camera at z = 1: depth 1 instead of 2 for the first point
    near = Camera(w2c, 50.0, 50.0, 20.0, 15.0, 40, 30)
    np.testing.assert_allclose(filter_3d(means[:1], [cam, near]), math.sqrt(FILTER_3D_VARIANCE) * 1.0 / 50.0,
                               rtol=1e-6)


def test_filter_matches_slow_reference_including_unseen_behind_and_near_plane():
    rng = np.random.default_rng(3)
    cams = orbit(9, 3.0, math.radians(25), width=40, height=30, fov_x=math.radians(45))
    cams.append(Camera.look_at((0.2, 0.1, 0.3), (1.0, 1.0, 0.0), width=16, height=12))  # inside the cloud
    means = np.concatenate([rng.normal(0, 1.2, (400, 3)),
                            [[40.0, 0.0, 0.0], [0.0, 0.0, -30.0]],  # seen by no camera
                            [c.center for c in cams[:2]],  # at a camera centre (depth 0)
                            [cams[0].center + 0.01 * cams[0].rotation[2]],  # exactly on the near plane
                            [cams[0].center + 0.010001 * cams[0].rotation[2]]])
    fast, slow = filter_3d(means, cams), filter_3d_reference(means, cams)
    assert fast.dtype == np.float32 and np.isfinite(fast).all() and (fast > 0).all()
    np.testing.assert_allclose(fast, slow, rtol=1e-6)
    rate = max_sampling_rate(means, cams)
    assert rate[400] == 0 and rate[401] == 0 and rate[-1] > 0
    assert fast[400] == fast[:400].max()  # unseen: the largest filter of the seen ones
    # nothing seen at all: no filter; no camera: an error
    assert (filter_3d(np.array([[0.0, 0.0, -5.0]]), [Camera(np.eye(4), 10, 10, 5, 5, 10, 10)]) == 0).all()
    with pytest.raises(ValueError, match="camera"):
        filter_3d(means, [])


def test_with_filter_3d_follows_the_training_resolution():
    cloud = random_cloud(50, 1, seed=4)
    cams = orbit(6, 3.0, width=64, height=48)
    a = with_filter_3d(cloud, cams)
    half = with_filter_3d(cloud, cams, resolution=24)  # cameras at half the height: twice the filter
    np.testing.assert_allclose(half.extra[FILTER_KEY], 2 * a.extra[FILTER_KEY], rtol=1e-5)
    t = with_filter_3d(cloud.to_torch(), cams)
    assert torch.is_tensor(t.extra[FILTER_KEY]) and np.allclose(t.extra[FILTER_KEY].numpy(), a.extra[FILTER_KEY])
    tagged = cloud.replace(extra={"tag": np.arange(50)})
    assert set(with_filter_3d(tagged, cams).extra) == {"tag", FILTER_KEY}
    # the world dilation: the same sampling rate, sqrt(0.3) instead of sqrt(0.2) sampling intervals
    d = with_dilation_3d(cloud, cams).extra[DILATION_KEY]
    np.testing.assert_allclose(d, a.extra[FILTER_KEY] * math.sqrt(CLASSIC_DILATION / FILTER_3D_VARIANCE), rtol=1e-6)
    np.testing.assert_array_equal(d, dilation_3d(cloud.means, cams))
    # with_training_cameras sets the size its training calls for and drops the other
    both = tagged.replace(extra={**tagged.extra, FILTER_KEY: a.extra[FILTER_KEY], DILATION_KEY: d})
    assert set(with_training_cameras(both, cams).extra) == {"tag", DILATION_KEY}
    assert set(with_training_cameras(both, cams, trained="mip").extra) == {"tag", FILTER_KEY}
    np.testing.assert_array_equal(with_training_cameras(cloud, cams, 24).extra[DILATION_KEY],
                                  with_dilation_3d(cloud, cams, 24).extra[DILATION_KEY])
    with pytest.raises(ValueError, match="trained"):
        with_training_cameras(cloud, cams, trained="msaa")


def test_auto_mode_follows_what_the_cloud_carries():
    cloud = random_cloud(4, 0, seed=0)
    f = filtered(cloud)
    d = filtered(cloud, key=DILATION_KEY)
    both = filtered(d)
    assert [resolve_antialias("auto", c) for c in (cloud, f, d, both)] == ["classic", "mip", "matched", "mip"]
    assert resolve_antialias("matched", cloud) == "classic" and resolve_antialias("mip", cloud) == "mip"
    assert resolve_antialias("classic", both) == "classic" and resolve_antialias("matched", both) == "matched"


# ------------------------------------------------------------------- render modes
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("sizes", ["none", "filter", "dilation"])
def test_parity_of_every_mode(mode, sizes):
    cloud = random_cloud(120, 2, seed=21)
    if sizes != "none":
        cloud = filtered(cloud, seed=1, key=FILTER_KEY if sizes == "filter" else DILATION_KEY)
    cam = camera()
    out = render(cloud, cam, background=BG, settings=RenderSettings(antialias=mode))
    ref = render_reference(cloud, cam, background=BG, antialias=mode)
    assert_parity(out, ref)
    assert ref[1].mean() > 0.3
    drawn = ref[1] > 0.05
    np.testing.assert_allclose(out.depth.numpy()[drawn], ref[2][drawn], rtol=1e-3, atol=1e-3)


def test_classic_is_unchanged_and_auto_follows_the_sizes():
    cloud = random_cloud(80, 3, seed=5)
    cam = camera()
    base = render(cloud, cam, background=BG, settings=RenderSettings(antialias="classic"))
    with_f = filtered(cloud)
    with_d = filtered(cloud, key=DILATION_KEY)
    both = filtered(with_d)
    for c, mode in ((both, "classic"), (cloud, "auto"), (cloud, "matched"), (with_f, "matched")):
        out = render(c, cam, background=BG, settings=RenderSettings(antialias=mode))  # bit for bit classic
        assert torch.equal(out.image, base.image) and torch.equal(out.radii, base.radii)
    for c, mode in ((with_f, "mip"), (with_d, "matched")):
        explicit = render(c, cam, background=BG, settings=RenderSettings(antialias=mode))
        auto = render(c, cam, background=BG, settings=RenderSettings(antialias="auto"))
        assert torch.equal(explicit.image, auto.image) and (explicit.image - base.image).abs().max() > 0.05
    with pytest.raises(ValueError, match="antialias"):
        render(cloud, cam, settings=RenderSettings(antialias="msaa"))
    assert set(ANTIALIAS_MODES) == set(MODES)


def test_zero_sizes_change_nothing():
    cloud = random_cloud(60, 1, seed=6)
    cam = camera()
    zeros = np.zeros(60, np.float32)
    for mode, key in (("mip", FILTER_KEY), ("matched", DILATION_KEY)):
        settings = RenderSettings(antialias=mode)
        plain = render(cloud, cam, background=BG, settings=settings)
        zero = render(cloud.replace(extra={key: zeros}), cam, background=BG, settings=settings)
        assert (zero.image - plain.image).abs().max() <= 1e-6, mode


def test_matched_is_classic_at_the_training_sampling_and_keeps_its_blur_above_it():
    """A small Gaussian on the optical axis, its world dilation from the camera that renders it:
    matched = classic (2D variance σ² + 0.3). Through a camera of twice the resolution the classic
    render shrinks the blur to 0.3 of the new pixels, matched keeps 0.3 old pixels = 1.2 new ones:
    Σ alpha = 2π (4σ² + 1.2)(o - 1/255) (the integral cut at 1/255, as in the test below)."""
    o, z, focal, t = 0.5, 2.0, 20.0, 1 / 255
    cam = Camera(np.eye(4), focal, focal, 20.5, 20.5, 41, 41)
    big = Camera(np.eye(4), 2 * focal, 2 * focal, 41.0, 41.0, 82, 82)
    cloud = GaussianCloud(means=[[0.0, 0.0, z]], scales=[[math.log(0.1)] * 3], quats=[[1.0, 0, 0, 0]],
                          opacities=[math.log(o / (1 - o))], sh_dc=[[0.0, 0.0, 0.0]])
    cloud = with_dilation_3d(cloud, [cam])
    matched, classic = RenderSettings(antialias="matched"), RenderSettings(antialias="classic")
    assert (render(cloud, cam, settings=matched).image - render(cloud, cam, settings=classic).image).abs().max() < 1e-5
    sigma2 = (2 * focal * 0.1 / z) ** 2
    got = render(cloud, big, settings=matched).alpha.sum().item()
    assert got == pytest.approx(2 * math.pi * (sigma2 + 4 * 0.3) * (o - t), rel=5e-3)
    assert render(cloud, big, settings=classic).alpha.sum().item() == pytest.approx(
        2 * math.pi * (sigma2 + 0.3) * (o - t), rel=5e-3)


def test_3d_filter_is_the_smoothed_covariance_with_compensated_opacity():
    """Rendering with filter f is rendering Gaussians of scales sqrt(s² + f²) and opacity times
    prod s / sqrt(s² + f²) (isotropic filter), in the same 2D mode."""
    cloud = filtered(random_cloud(70, 2, seed=7), seed=2, lo=-4.0, hi=-2.0)
    cam = camera()
    s = np.exp(cloud.scales.astype(np.float64))
    f = cloud.extra[FILTER_KEY].astype(np.float64)[:, None]
    eff = np.sqrt(s * s + f * f)
    o = 1 / (1 + np.exp(-cloud.opacities.astype(np.float64))) * np.prod(s / eff, 1)
    same = cloud.replace(scales=np.log(eff).astype(np.float32), opacities=np.log(o / (1 - o)).astype(np.float32),
                         extra={})
    settings = RenderSettings(antialias="mip")
    a = render(cloud, cam, background=BG, settings=settings).image
    b = render(same, cam, background=BG, settings=settings).image
    assert (a - b).abs().max() < 2e-4


def test_2d_mip_filter_keeps_the_integral_of_alpha():
    """A faint Gaussian facing the camera on its axis, σ px wide: Σ alpha over the pixels is the
    integral of a Gaussian of variance σ² + d and peak p cut at t = 1/255, 2π (σ² + d)(p - t),
    with p = o for the classic dilation d = 0.3 and p = o σ² / (σ² + 0.1) for the compensated
    Mip filter d = 0.1 (whose integral is then o 2π σ², the unfiltered one, less the cut)."""
    o, z, focal, size, t = 0.5, 2.0, 20.0, 41, 1 / 255
    cam = Camera(np.eye(4), focal, focal, size / 2, size / 2, size, size)
    for s_world in (0.1, 0.25):
        sigma2 = (focal * s_world / z) ** 2  # 1 and 2.5 px
        cloud = GaussianCloud(means=[[0.0, 0.0, z]], scales=[[math.log(s_world)] * 3], quats=[[1.0, 0, 0, 0]],
                              opacities=[math.log(o / (1 - o))], sh_dc=[[0.0, 0.0, 0.0]])
        mip = render(cloud, cam, settings=RenderSettings(antialias="mip")).alpha.sum().item()
        classic = render(cloud, cam, settings=RenderSettings(antialias="classic")).alpha.sum().item()
        assert mip == pytest.approx(2 * math.pi * (o * sigma2 - t * (sigma2 + 0.1)), rel=5e-3)
        assert classic == pytest.approx(2 * math.pi * (sigma2 + 0.3) * (o - t), rel=5e-3)


def test_footprint_covers_every_pixel_the_compensated_alpha_reaches():
    """Tiling never changes the image in the filtered mode (compensated opacities included)."""
    cloud = filtered(random_cloud(150, 1, seed=5), seed=3)
    cam = camera(37, 29)
    mip = RenderSettings(antialias="mip")
    base = render(cloud, cam, background=BG, settings=mip)
    for ts, exact, block in ((4, False, 7), (13, True, 3), (32, True, 512)):
        img = render(cloud, cam, background=BG,
                     settings=RenderSettings(antialias="mip", tile_size=ts, exact_tiles=exact, block=block)).image
        assert (img - base.image).abs().max() < 2e-5
    assert_parity(base, render_reference(cloud, cam, background=BG, antialias="mip"))


# ---------------------------------------------------------------------- gradients
@pytest.mark.parametrize("mode", ["classic", "mip", "matched"])
@pytest.mark.parametrize("field", ["means", "scales", "opacities", "quats", "filter"])
def test_gradcheck_float64_every_mode(mode, field):
    cloud = random_cloud(6, 1, seed=2, spread=0.35)
    cloud = cloud.replace(opacities=np.full(6, 0.5, np.float32))
    base = {f: torch.tensor(np.asarray(getattr(cloud, f)), dtype=torch.float64) for f in FIELDS}
    filt = torch.tensor(np.exp(np.random.default_rng(0).uniform(-4, -2, 6)), dtype=torch.float64)
    cam = camera(12, 10, fov=35.0)
    weights = torch.randn(10, 12, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    settings = RenderSettings(antialias=mode, dtype=torch.float64, tile_size=4, block=3, budget=200)

    def loss(x):
        fields = dict(base)
        f = x if field == "filter" else filt
        if field != "filter":
            fields[field] = x
        out = render(GaussianCloud(**fields, extra={FILTER_KEY if mode == "mip" else DILATION_KEY: f}), cam,
                     background=BG, settings=settings)
        return (out.image * weights).sum() + out.alpha.sum() + 0.1 * out.depth.sum()

    x = (filt if field == "filter" else base[field]).clone().requires_grad_()
    assert torch.autograd.gradcheck(loss, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("mode", ["mip", "matched"])
def test_recomputing_backward_matches_autograd_in_the_filtered_modes(mode):
    cloud = filtered(filtered(random_cloud(60, 3, seed=9), seed=4), seed=4, key=DILATION_KEY)
    cam = camera(30, 22)
    weights = torch.randn(22, 30, 3, generator=torch.Generator().manual_seed(1))
    grads = {}
    for backward in ("recompute", "autograd"):
        tc = GaussianCloud(**{f: torch.tensor(np.asarray(getattr(cloud, f)), requires_grad=True) for f in FIELDS},
                           extra={k: torch.tensor(v) for k, v in cloud.extra.items()})
        out = render(tc, cam, background=BG, settings=RenderSettings(antialias=mode, backward=backward, block=5))
        ((out.image * weights).sum() + out.alpha.sum()).backward()
        grads[backward] = {f: getattr(tc, f).grad for f in FIELDS}
    for name, g in grads["recompute"].items():
        ref = grads["autograd"][name]
        assert torch.isfinite(g).all()
        assert (g - ref).abs().max() <= 1e-4 * max(1.0, ref.abs().max().item()), name


# --------------------------------------------------------------------- hard cases
def _finite_everywhere(cloud: GaussianCloud, cam: Camera, mode: str):
    fields = {f: torch.tensor(np.asarray(getattr(cloud, f), np.float32), requires_grad=True) for f in FIELDS}
    filt = torch.tensor(np.asarray(cloud.extra[FILTER_KEY], np.float32), requires_grad=True)
    tc = GaussianCloud(**fields, extra={FILTER_KEY: filt, DILATION_KEY: filt})
    out = render(tc, cam, background=BG, settings=RenderSettings(antialias=mode))
    for t in (out.image, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    loss = (out.image * torch.linspace(-1, 1, out.image.numel()).reshape(out.image.shape)).sum()
    (loss + out.alpha.sum() + out.depth.sum()).backward()
    for name, t in list(fields.items()) + [("filter", filt)]:
        assert t.grad is None or torch.isfinite(t.grad).all(), name
    return out


@pytest.mark.parametrize("mode", ["classic", "mip", "matched"])
@pytest.mark.parametrize("case", ["log_scale_-30", "log_scale_+30", "filter_0", "filter_huge", "filter_tiny",
                                  "filter_nonfinite", "needles", "near_plane"])
def test_hard_cases_every_mode(mode, case):
    cloud = filtered(random_cloud(12, 2, seed=7), seed=5)
    cam = camera(24, 18)
    f = cloud.extra[FILTER_KEY].copy()
    if case == "log_scale_-30":
        cloud = _with(cloud, scales=np.full((4, 3), -30.0))
        f[:2] = 0.0
    elif case == "log_scale_+30":
        cloud = _with(cloud, scales=np.full((2, 3), 30.0))
    elif case == "filter_0":
        f[:] = 0.0
    elif case == "filter_huge":
        f[:4] = [1e30, 1e8, np.finfo(np.float32).max, 1e3]
    elif case == "filter_tiny":
        f[:4] = [1e-45, 1e-30, -1.0, 1e-12]
    elif case == "filter_nonfinite":
        f[:3] = [np.nan, np.inf, -np.inf]
    elif case == "needles":
        cloud = _with(cloud, scales=[[-1.0, -1.0 - math.log(1e5), -1.0 - math.log(1e5)],
                                     [-13.0, -13.0 + math.log(1e5), -13.0]], opacities=[3.0, 3.0])
        f[:2] = [0.0, 1e-4]
    elif case == "near_plane":
        cam = Camera(np.eye(4), 20.0, 20.0, 12.0, 9.0, 24, 18)
        cloud = _with(cloud, means=[[0.0, 0.0, 0.0], [0.1, 0.0, -1.0], [0.0, 0.0, 0.01], [0.0, 0.0, 0.0100001],
                                    [0.05, -0.02, 2.0]])
    cloud = cloud.replace(extra={FILTER_KEY: f.astype(np.float32), DILATION_KEY: f.astype(np.float32)})
    out = _finite_everywhere(cloud, cam, mode)
    if case not in ("log_scale_+30", "filter_huge", "filter_nonfinite"):
        assert_parity(out, render_reference(cloud, cam, background=BG, antialias=mode))
    if case == "filter_huge" and mode == "mip":
        assert not out.visible[:3].any()  # spread over the whole world: transparent
    if case == "near_plane":
        assert not out.visible[:3].any() and out.visible[4]
    if case == "log_scale_-30" and mode == "mip":
        assert not out.visible[:4].any()  # no volume, nothing to keep: compensated to nothing


def test_sizes_of_the_wrong_length_are_an_error():
    cloud = random_cloud(5, 0, seed=0)
    for mode, key in (("mip", FILTER_KEY), ("matched", DILATION_KEY)):
        bad = cloud.replace(extra={key: np.zeros((5, 2), np.float32)})
        with pytest.raises(ValueError, match=key):
            render(bad, camera(), settings=RenderSettings(antialias=mode))


def test_max_sampling_rate_in_threads_is_the_camera_loop():
    """The rate over enough Gaussians to be split into ranges run in threads, against one pass per
    camera over all of them (the definition): the same values, bit for bit."""
    rng = np.random.default_rng(5)
    means = rng.normal(0.0, 1.5, (150_001, 3))
    means[:7] = [[np.nan, 0, 0], [np.inf, 0, 0], [0, 0, 4.0], [0, 0, -4.0], [0, 0, 0], [40, 0, 0], [0, 1e30, 0]]
    cams = [Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 1.0), (0, 0, 0), width=64, height=48) for a in (0.3, 2.5)]
    want = np.zeros(len(means))
    for cam in cams:
        want = np.maximum(want, _camera_rate(means, cam, 0.01, 0.15))
    got = max_sampling_rate(means, cams, near=0.01, margin=0.15)
    np.testing.assert_array_equal(got, want)
    assert (got > 0).mean() > 0.3 and (got == 0).any()
