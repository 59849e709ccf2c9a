"""The fast renderer against the float64 reference, its gradients, and its hard cases."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import gvae_core
import gvae_core.refinement
import gvae_core.rendering.reference
from gvae_core import Camera, GaussianCloud
from gvae_core.examples import example_cloud
from gvae_core.rendering import RenderOutput, RenderSettings, render
from gvae_core.rendering.projection import project
from gvae_core.rendering.reference import render_reference
from gvae_core.rendering.tiles import _sort_key, bin_gaussians

BG = (0.25, 0.5, 0.8)
FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def random_cloud(n: int, degree: int, seed: int, spread: float = 0.6) -> GaussianCloud:
    """Mixed sizes and opacities: small and large, faint and opaque (cap and stop rule both hit)."""
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    scales = rng.uniform(-3.8, -1.2, (n, 3))
    scales[: n // 10] += 1.5  # some big ones
    return GaussianCloud(
        means=rng.normal(0, spread, (n, 3)).astype(np.float32),
        scales=scales.astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=rng.normal(1.0, 3.0, n).astype(np.float32),
        sh_dc=rng.normal(0, 1, (n, 3)).astype(np.float32),
        sh_rest=rng.normal(0, 0.4, (n, k, 3)).astype(np.float32))


def camera(w=40, h=30, eye=(3.0, 1.0, 1.5), target=(0.0, 0.0, 0.0), fov=45.0) -> Camera:
    return Camera.look_at(eye, target, width=w, height=h, fov_x=math.radians(fov))


def torch_cloud(cloud: GaussianCloud, dtype=torch.float32) -> GaussianCloud:
    """A torch copy whose every field is a leaf that requires grad."""
    return GaussianCloud(**{f: torch.tensor(np.asarray(getattr(cloud, f)), dtype=dtype, requires_grad=True)
                            for f in FIELDS})


def assert_parity(out: RenderOutput, ref, frac_tol=1e-4, max_tol=1e-2):
    for got, want in ((out.image, ref[0]), (out.alpha, ref[1])):
        err = np.abs(got.detach().numpy().astype(np.float64) - want)
        assert np.isfinite(err).all()
        assert (err <= frac_tol).mean() >= 0.999, f"{(err > frac_tol).mean():.4%} beyond {frac_tol}"
        assert err.max() <= max_tol, err.max()


# ------------------------------------------------------------------ parity
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_parity_with_reference(degree):
    cloud = random_cloud(120, degree, seed=degree)
    cam = camera()
    out = render(cloud, cam, background=BG)
    ref = render_reference(cloud, cam, background=BG)
    assert out.image.shape == (30, 40, 3) and out.image.dtype == torch.float32
    assert out.alpha.shape == (30, 40) and out.depth.shape == (30, 40)
    assert_parity(out, ref)
    drawn = ref[1] > 0.05
    assert drawn.mean() > 0.3  # the scene really covers the frame
    np.testing.assert_allclose(out.depth.numpy()[drawn], ref[2][drawn], rtol=1e-3, atol=1e-3)
    assert (out.radii > 0).sum() == out.visible.sum()


def test_parity_sh_degree_argument_and_off_centre_principal_point():
    cloud = random_cloud(80, 3, seed=11)
    cam = camera(36, 28)
    cam = Camera(cam.world_to_cam, cam.fx, cam.fy * 1.1, cam.cx + 3.3, cam.cy - 2.1, cam.width, cam.height)
    for degree in (0, 2):
        out = render(cloud, cam, background=BG, sh_degree=degree)
        assert_parity(out, render_reference(cloud, cam, background=BG, sh_degree=degree))


def test_tiling_is_invisible():
    """Tile size, exact-vs-box tile tests, block and budget never change the image."""
    cloud = random_cloud(150, 1, seed=5)
    cam = camera(37, 29)
    base = render(cloud, cam, background=BG).image
    for ts, exact, block, budget in ((4, False, 7, 1000), (8, False, 16, 3000), (32, True, 512, 1 << 20),
                                     (13, True, 3, 2000)):
        img = render(cloud, cam, background=BG,
                     settings=RenderSettings(tile_size=ts, exact_tiles=exact, block=block, budget=budget)).image
        assert (img - base).abs().max() < 2e-5  # float32 rounding only: no Gaussian lost


def test_binning_in_chunks_and_by_integer_depth_keys_changes_nothing():
    x = torch.tensor([3.0, -0.0, 0.0, -2.5, float("inf"), -float("inf"), 1e-40, -1e-40, 7.0, 3.0])
    for dtype in (torch.float32, torch.float64):
        v = x.to(dtype)
        assert torch.equal(torch.sort(_sort_key(v), stable=True).indices[[0, 1, 6, 7, 8, 9]],
                           torch.sort(v, stable=True).indices[[0, 1, 6, 7, 8, 9]])  # (-0.0 and 0.0 tie as floats)
        assert torch.equal(v[torch.sort(_sort_key(v), stable=True).indices], torch.sort(v).values)
    cloud = random_cloud(500, 0, seed=10)
    cam = camera(53, 41)
    c = cloud.to_torch()
    p = project(c.means, c.scales, c.quats, c.opacities, c.sh_dc, c.sh_rest, cam, 0)
    whole = bin_gaussians(p.means2d, p.footprint, p.depths, p.visible, cam.width, cam.height, 8)
    parts = bin_gaussians(p.means2d, p.footprint, p.depths, p.visible, cam.width, cam.height, 8, chunk=7)
    assert whole.num_pairs > 500
    assert torch.equal(whole.gaussian_ids, parts.gaussian_ids) and torch.equal(whole.offsets, parts.offsets)
    # within each tile, front to back
    depth = p.depths[whole.gaussian_ids]
    for t in range(len(whole.counts)):
        seg = depth[whole.offsets[t]:whole.offsets[t + 1]]
        assert (seg[1:] >= seg[:-1]).all()


def test_numpy_and_torch_clouds_render_the_same():
    cloud = random_cloud(50, 2, seed=3)
    cam = camera()
    a = render(cloud, cam, background=BG)
    b = render(cloud.to_torch(), cam, background=BG)
    assert torch.equal(a.image, b.image) and torch.equal(a.radii, b.radii)


# -------------------------------------------------------------- exact rules
def _stack_on_axis(opacities, colors, depths=None, log_scale=-1.0) -> GaussianCloud:
    """Gaussians centred on the optical axis of `_axis_camera` (the centre of its middle pixel)."""
    n = len(opacities)
    depths = depths if depths is not None else 2.0 + np.arange(n, dtype=np.float64)
    logits = np.log(np.asarray(opacities) / (1 - np.asarray(opacities)))
    colors = np.asarray(colors, np.float64)
    return GaussianCloud(means=np.stack([np.zeros(n), np.zeros(n), depths], 1),
                         scales=np.full((n, 3), log_scale), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                         opacities=logits, sh_dc=(colors - 0.5) / 0.28209479177387814)


def _axis_camera(size=9):
    return Camera(np.eye(4), 20.0, 20.0, size / 2, size / 2, size, size)  # pixel (4,4) centre = axis


def test_transmittance_stop_rule_cap_and_skip():
    cam = _axis_camera()
    bg = np.array(BG)
    # alpha 0.95 each: T = 0.05, 0.0025, 1.25e-4, then 6.25e-6 < 1e-4 -> stop before the 4th.
    cols = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]])
    stack = _stack_on_axis([0.95] * 4, cols)
    out = render(stack, cam, background=BG)
    want = sum(cols[i] * 0.95 * 0.05 ** i for i in range(3)) + 0.05 ** 3 * bg
    np.testing.assert_allclose(out.image[4, 4].numpy(), want, atol=2e-6)
    np.testing.assert_allclose(render_reference(stack, cam, background=BG, pixels=[[4, 4]])[0][0], want, atol=1e-12)
    # 0.99 cap: a fully opaque Gaussian lets 1% of the background through.
    out = render(_stack_on_axis([1.0 - 1e-12], [[0.2, 0.4, 0.6]]), cam, background=BG)
    np.testing.assert_allclose(out.image[4, 4].numpy(), 0.99 * np.array([0.2, 0.4, 0.6]) + 0.01 * bg, atol=2e-6)
    # 1/255 skip: just below is invisible everywhere, just above shows at the centre only.
    below = render(_stack_on_axis([0.999 / 255], [[1.0, 1.0, 1.0]]), cam, background=BG)
    assert torch.equal(below.image, torch.tensor(bg, dtype=torch.float32).expand(9, 9, 3))
    assert not below.visible.any() and below.radii.sum() == 0
    above = render(_stack_on_axis([1.01 / 255], [[1.0, 1.0, 1.0]], log_scale=-3.0), cam, background=BG)
    assert above.alpha[4, 4] == pytest.approx(1.01 / 255, rel=1e-4)
    assert (above.alpha > 0).sum() == 1


# --------------------------------------------------------------- gradients
@pytest.mark.parametrize("field", FIELDS)
def test_gradcheck_float64(field):
    cloud = random_cloud(6, 1, seed=2, spread=0.35)
    cloud = cloud.replace(opacities=np.full(6, 0.5, np.float32))
    base = {f: torch.tensor(np.asarray(getattr(cloud, f)), dtype=torch.float64) for f in FIELDS}
    cam = camera(12, 10, fov=35.0)
    weights = torch.randn(10, 12, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    settings = RenderSettings(dtype=torch.float64, tile_size=4, block=3, budget=200)

    def loss(x):
        out = render(GaussianCloud(**{**base, field: x}), cam, background=BG, settings=settings)
        return (out.image * weights).sum() + out.alpha.sum() + 0.1 * out.depth.sum()

    x = base[field].clone().requires_grad_()
    assert torch.autograd.gradcheck(loss, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_recomputing_backward_matches_autograd_and_fills_means2d_grad():
    cloud = random_cloud(60, 3, seed=9)
    cam = camera(30, 22)
    weights = torch.randn(22, 30, 3, generator=torch.Generator().manual_seed(1))
    grads = {}
    for mode in ("recompute", "autograd"):
        tc = torch_cloud(cloud)
        out = render(tc, cam, background=BG, settings=RenderSettings(backward=mode, tile_size=8, block=5))
        out.means2d.retain_grad()
        ((out.image * weights).sum() + out.alpha.sum() + 0.05 * out.depth.sum()).backward()
        grads[mode] = {f: getattr(tc, f).grad for f in FIELDS} | {"means2d": out.means2d.grad}
        visible = out.visible
    for name, g in grads["recompute"].items():
        ref = grads["autograd"][name]
        assert torch.isfinite(g).all()
        assert (g - ref).abs().max() <= 1e-4 * max(1.0, ref.abs().max().item()), name
    m2d = grads["recompute"]["means2d"]
    assert (m2d[~visible] == 0).all() and (m2d[visible].abs().sum(1) > 0).any()


def test_background_tensor_gets_gradient():
    cloud = random_cloud(20, 0, seed=4)
    bg = torch.tensor(BG, requires_grad=True)
    out = render(cloud, camera(16, 12), background=bg)
    out.image.sum().backward()
    np.testing.assert_allclose(bg.grad.numpy(), (1 - out.alpha).sum().item() * np.ones(3), rtol=1e-5)


# --------------------------------------------------------------- hard cases
def _check_finite(cloud: GaussianCloud, cam: Camera) -> RenderOutput:
    tc = torch_cloud(cloud)
    out = render(tc, cam, background=BG)
    out.means2d.retain_grad()
    for t in (out.image, out.alpha, out.depth):
        assert torch.isfinite(t).all()
    loss = (out.image * torch.linspace(-1, 1, out.image.numel()).reshape(out.image.shape)).sum()
    (loss + out.alpha.sum() + out.depth.sum()).backward()
    for f in FIELDS:
        g = getattr(tc, f).grad
        assert g is None or torch.isfinite(g).all(), f
    assert out.means2d.grad is None or torch.isfinite(out.means2d.grad).all()
    return out


def _with(cloud: GaussianCloud, **rows) -> GaussianCloud:
    """`cloud` with rows 0.. of some fields overwritten."""
    arrays = {f: np.array(getattr(cloud, f), dtype=np.float64) for f in FIELDS}
    for name, values in rows.items():
        values = np.asarray(values, np.float64)
        arrays[name][: len(values)] = values
    return GaussianCloud(**arrays)


HARD_CASES = ("log_scale_-30", "log_scale_+30", "zero_quat", "opacity_+50", "opacity_-50", "needles", "covers_image")


def hard_case(case: str) -> GaussianCloud:
    """A small random cloud whose first rows are made degenerate in the way `case` says."""
    cloud = random_cloud(12, 2, seed=7)
    if case == "log_scale_-30":
        return _with(cloud, scales=np.full((4, 3), -30.0))
    if case == "log_scale_+30":
        return _with(cloud, scales=np.full((2, 3), 30.0))
    if case == "zero_quat":
        return _with(cloud, quats=np.zeros((4, 4)))
    if case == "opacity_+50":
        return _with(cloud, opacities=np.full(6, 50.0))
    if case == "opacity_-50":
        return _with(cloud, opacities=np.full(6, -50.0))
    if case == "needles":
        return _with(cloud, scales=[[-1.0, -1.0 - math.log(1e5), -1.0 - math.log(1e5)],
                                    [-13.0, -13.0 + math.log(1e5), -13.0]], opacities=[3.0, 3.0])
    if case == "covers_image":
        return _with(cloud, means=[[0.0, 0.0, 0.0]], scales=[[1.5, 1.5, 1.5]], opacities=[2.0])
    raise ValueError(case)


@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_parameters(case):
    cloud = hard_case(case)
    cam = camera(24, 18)
    out = _check_finite(cloud, cam)
    if case not in ("opacity_-50", "log_scale_+30"):
        assert_parity(out, render_reference(cloud, cam, background=BG))
    if case == "covers_image":
        assert out.alpha.min() > 0.5
    if case == "opacity_-50":
        assert not out.visible[:6].any()


def test_gaussians_at_camera_centre_behind_and_on_near_plane():
    cam = Camera(np.eye(4), 20.0, 20.0, 8.0, 6.0, 16, 12)  # at the origin, looking along +z
    base = random_cloud(5, 1, seed=8)
    means = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, -1.0], [0.0, 0.0, 0.01], [0.0, 0.0, 0.0100001],
                      [0.05, -0.02, 2.0]])
    cloud = _with(base, means=means)
    out = _check_finite(cloud, cam)
    assert not out.visible[:3].any() and out.visible[4]
    assert_parity(out, render_reference(cloud, cam, background=BG))


def test_far_from_origin_renders_like_at_origin():
    cloud = random_cloud(60, 3, seed=12)
    # Positions on a 1/128 grid: exactly representable as float32 at 1e5 too, so both scenes
    # are exactly the same Gaussians, only translated.
    means = np.round(np.asarray(cloud.means, np.float64) * 128) / 128
    offset = np.array([1e5, -1e5, 1e5])
    near_cloud = cloud.replace(means=means.astype(np.float32))
    far_cloud = cloud.replace(means=(means + offset).astype(np.float32))
    assert np.array_equal(far_cloud.means.astype(np.float64) - offset, means)
    cam = camera()
    far_cam = Camera.look_at(np.array([3.0, 1.0, 1.5]) + offset, offset, width=40, height=30,
                             fov_x=math.radians(45))
    a = render(near_cloud, cam, background=BG)
    b = _check_finite(far_cloud, far_cam)
    assert (a.image - b.image).abs().max() < 1e-4
    assert a.alpha.max() > 0.5


def test_empty_and_fully_culled_clouds():
    cam = camera(20, 16)
    empty = GaussianCloud.empty(3)
    out = render(empty, cam, background=BG)
    assert out.radii.shape == (0,) and out.means2d.shape == (0, 2)
    assert torch.allclose(out.image, torch.tensor(BG).expand(16, 20, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    behind = random_cloud(10, 0, seed=1).replace(means=np.tile([[10.0, 3.3, 5.0]], (10, 1)).astype(np.float32))
    out = _check_finite(behind, camera(20, 16, eye=(3.0, 1.0, 1.5), target=(-1.0, 0.0, 0.0)))
    assert not out.visible.any() and (out.alpha == 0).all()


def test_bad_arguments():
    cloud = random_cloud(3, 0, seed=0)
    with pytest.raises(ValueError, match="sh_degree"):
        render(cloud, camera(), sh_degree=4)
    with pytest.raises(ValueError, match="camera"):
        render(cloud, "not a camera")
    with pytest.raises(ValueError, match="backward"):
        render(cloud, camera(), settings=RenderSettings(backward="magic"))


def test_package_functions_stay_functions_after_submodule_imports():
    assert callable(gvae_core.refine) and gvae_core.refine is gvae_core.refinement.refine
    out = gvae_core.render(random_cloud(5, 0, seed=0), camera(8, 6))
    assert isinstance(out, RenderOutput) and out.image.shape == (6, 8, 3)


def test_recomputing_backward_keeps_memory_bounded():
    """What autograd keeps for backward grows with Gaussians + pixels, not with pixel-Gaussian
    pairs (the plain-autograd path, for contrast, keeps every block)."""
    cloud = random_cloud(300, 1, seed=13)
    cloud = cloud.replace(scales=cloud.scales + 1.0)  # big ones: many pixel-Gaussian pairs
    cam = camera(96, 72)
    saved = {}
    for mode in ("recompute", "autograd"):
        total = [0]

        def pack_hook(t, total=total):
            total[0] += t.numel()
            return t

        tc = torch_cloud(cloud)
        with torch.autograd.graph.saved_tensors_hooks(pack_hook, lambda t: t):
            out = render(tc, cam, settings=RenderSettings(backward=mode))
        saved[mode] = total[0]
        pairs_x_pixels = out.num_pairs * out.tile_size ** 2
    n, pixels = len(cloud), 96 * 72
    assert saved["recompute"] < 200 * n + 20 * pixels + 11 * out.num_pairs
    assert saved["autograd"] > pairs_x_pixels > 3 * saved["recompute"], (saved, pairs_x_pixels)


def test_a_crop_of_a_camera_draws_the_same_pixels():
    # The Jacobian's clamp follows the image's own extent (the image widened by 15% of its size on
    # each side), so a crop of a camera (principal point moved, smaller image: what training on
    # patches renders) draws the pixels of the whole view, up to Gaussians centred far outside
    # the crop, which it clamps and the whole view does not; the reference renderer agrees.
    cloud = example_cloud(500, seed=2)
    cam = Camera.look_at((3.0, 1.0, 1.8), width=64, height=64)
    whole = render(cloud, cam).image.numpy()

    def crop(x0, y0, w, h):
        return dataclasses.replace(cam, cx=cam.cx - x0, cy=cam.cy - y0, width=w, height=h)

    np.testing.assert_allclose(render(cloud, crop(8, 8, 48, 48)).image.numpy(), whole[8:56, 8:56], atol=1e-5)
    for x0, y0 in ((0, 0), (40, 8), (17, 33)):
        part = render(cloud, crop(x0, y0, 24, 20)).image.numpy()
        assert np.abs(part - whole[y0:y0 + 20, x0:x0 + 24]).mean() < 2e-4
    pixels = np.array([[3, 5], [10, 20]])
    ref = render_reference(cloud, crop(40, 8, 24, 20), pixels=pixels)[0]
    np.testing.assert_allclose(render(cloud, crop(40, 8, 24, 20)).image.numpy()[pixels[:, 0], pixels[:, 1]], ref,
                               atol=1e-5)
