"""The compiled CPU kernels (`gvae_core.rendering.compiled`, Numba) against the torch code they
replace on the CPU: the same images (float32 rounding), the same gradients, the same tile lists,
the same Hessian blocks, in every anti-aliasing mode and on the hard cases; their on-disk cache."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import DILATION_KEY, FILTER_KEY
from gvae_core.hessian import hessian_blocks, hessian_blocks_reference
from gvae_core.rendering import RenderSettings, compiled, render
from gvae_core.rendering.projection import project
from gvae_core.rendering.reference import render_reference
from gvae_core.rendering.tiles import bin_gaussians

from .test_render import BG, FIELDS, HARD_CASES, _with, assert_parity, camera, hard_case, random_cloud, torch_cloud

pytestmark = pytest.mark.skipif(compiled.numba_missing() is not None, reason=str(compiled.numba_missing()))

TORCH, FAST = RenderSettings(kernels="torch"), RenderSettings(kernels="compiled")


def _with_sizes(cloud: GaussianCloud, *keys, seed: int = 0) -> GaussianCloud:
    """`cloud` with 3D anti-aliasing sizes around its Gaussians' scale (some clamp the 2D dilation)."""
    rng = np.random.default_rng(seed)
    extra = {key: rng.uniform(0.002, 0.1, len(cloud)).astype(np.float32) for key in keys}
    return cloud.replace(extra={**cloud.extra, **extra})


def _both(cloud: GaussianCloud, cam: Camera, antialias: str = "auto", **kw):
    """Image and gradients (six fields and means2d) of the compiled and the torch path."""
    weights = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1))
    out = {}
    for name, base in (("compiled", FAST), ("torch", TORCH)):
        tc = torch_cloud(cloud).replace(extra={k: torch.as_tensor(np.asarray(v)) for k, v in cloud.extra.items()})
        r = render(tc, cam, background=BG, settings=RenderSettings(kernels=base.kernels, antialias=antialias, **kw))
        r.means2d.retain_grad()
        ((r.image * weights).sum() + r.alpha.sum() + 0.05 * r.depth.sum()).backward()
        grads = {f: getattr(tc, f).grad for f in FIELDS} | {"means2d": r.means2d.grad}
        out[name] = (r, grads)
    return out


def _assert_same_gradients(got: dict, want: dict, rel: float = 1e-4):
    for name, ref in want.items():
        g = got[name]
        if ref is None or ref.numel() == 0:
            assert g is None or not g.abs().any(), name
            continue
        assert g is not None and torch.isfinite(g).all(), name
        assert (g - ref).abs().max() <= rel * max(1.0, ref.abs().max().item()), name


@pytest.mark.parametrize("degree, mode, keys", [(0, "classic", ()), (1, "mip", (FILTER_KEY,)), (2, "mip", ()),
                                                (3, "matched", (DILATION_KEY,)), (3, "auto", (FILTER_KEY,))])
def test_images_and_gradients_are_the_torch_paths(degree, mode, keys):
    cloud = _with_sizes(random_cloud(150, degree, seed=degree), *keys)
    cam = camera(37, 29)
    both = _both(cloud, cam, mode)
    fast, slow = both["compiled"][0], both["torch"][0]
    assert (fast.image - slow.image).abs().max() < 2e-5
    assert (fast.alpha - slow.alpha).abs().max() < 2e-5
    assert torch.allclose(fast.depth, slow.depth, rtol=1e-4, atol=1e-5)
    assert torch.equal(fast.visible, slow.visible) and torch.equal(fast.radii, slow.radii)
    assert fast.num_pairs == slow.num_pairs
    assert_parity(fast, render_reference(cloud, cam, background=BG, antialias=mode))
    _assert_same_gradients(both["compiled"][1], both["torch"][1])


def test_gradients_of_the_image_alone_are_the_torch_paths():
    """A loss of the image only (alpha and depth get no gradient, as in training) reaches the six
    fields as the torch path's does."""
    cloud, cam = random_cloud(120, 2, seed=9), camera(21, 34)
    weights = torch.randn(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(2))
    grads = {}
    for name, settings in (("compiled", FAST), ("torch", TORCH)):
        tc = torch_cloud(cloud)
        (render(tc, cam, background=BG, settings=settings).image * weights).sum().backward()
        grads[name] = {f: getattr(tc, f).grad for f in FIELDS}
    _assert_same_gradients(grads["compiled"], grads["torch"])


@pytest.mark.parametrize("tile_size, exact", [(4, True), (8, False), (13, True)])
def test_tile_lists_are_the_torch_paths(tile_size, exact):
    """The same pairs in the same order (front to back per tile), any tile size; the compositing
    draws the same image; pixels past the image's edge in border tiles change nothing."""
    cloud = random_cloud(400, 0, seed=10)
    cam = camera(53, 41)
    c = cloud.to_torch()
    p = project(c.means, c.scales, c.quats, c.opacities, c.sh_dc, c.sh_rest, cam, 0)
    want = bin_gaussians(p.means2d, p.footprint, p.depths, p.visible, cam.width, cam.height, tile_size, exact=exact)
    proj, table = compiled.project(c.means, c.scales, c.quats, c.opacities, c.sh_dc, c.sh_rest, cam, 0)
    got = compiled.bin_gaussians(table, proj.footprint, proj.visible, cam.width, cam.height, tile_size, exact=exact)
    assert got.num_pairs > 400
    assert torch.equal(got.offsets, want.offsets) and torch.equal(got.gaussian_ids, want.gaussian_ids)
    settings = dict(tile_size=tile_size, exact_tiles=exact)
    a = render(cloud, cam, background=BG, settings=RenderSettings(kernels="compiled", **settings))
    b = render(cloud, cam, background=BG, settings=RenderSettings(kernels="torch", **settings))
    assert (a.image - b.image).abs().max() < 2e-5 and a.num_evaluations > 0


@pytest.mark.parametrize("case", HARD_CASES + ("at_camera", "far"))
def test_hard_cases_stay_finite_and_agree(case):
    """The numerical-robustness cases of test_render through the kernels (and Gaussians at, behind
    and on the near plane of the camera; a scene far from the origin): finite images and
    gradients, the torch path's image and gradients."""
    cam = camera(24, 18)
    if case == "at_camera":  # at the camera centre, behind it, on the near plane
        eye = np.array([3.0, 1.0, 1.5])
        cloud = _with(random_cloud(12, 2, seed=7),
                      means=[eye, eye + [0.5, 0.2, 0.4], eye - 0.01 * eye / np.linalg.norm(eye)])
    elif case == "far":
        cloud = random_cloud(12, 2, seed=7)
        cloud = cloud.replace(means=np.asarray(cloud.means, np.float64) + 1e5)
        cam = Camera.look_at(np.array([3.0, 1.0, 1.5]) + 1e5, np.full(3, 1e5), width=24, height=18,
                             fov_x=math.radians(45))
    else:
        cloud = hard_case(case)
    both = _both(cloud, cam)
    fast = both["compiled"][0]
    for t in (fast.image, fast.alpha, fast.depth):
        assert torch.isfinite(t).all()
    assert (fast.image - both["torch"][0].image).abs().max() < 1e-4
    _assert_same_gradients(both["compiled"][1], both["torch"][1], rel=1e-3)


@pytest.mark.parametrize("mode, keys", [("mip", (FILTER_KEY,)), ("matched", (DILATION_KEY,))])
def test_hessian_blocks_are_exact_in_every_mode(mode, keys):
    """The compiled sweep and blocks give J^T J of the definition (backward passes per pixel and
    channel in float64) to float32 precision, as the torch code does, in the filtered modes
    (test_hessian's float32 case holds the classic mode's to it)."""
    rng = np.random.default_rng(3)
    n = 10
    cloud = GaussianCloud(means=rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32),
                          scales=(math.log(0.15) + rng.normal(0, 0.2, (n, 3))).astype(np.float32),
                          quats=rng.normal(size=(n, 4)).astype(np.float32), opacities=np.full(n, 1.0, np.float32),
                          sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                          sh_rest=rng.normal(0, 0.3, (n, 15, 3)).astype(np.float32))
    for key in keys:
        cloud.extra[key] = rng.uniform(0.01, 0.3, n).astype(np.float32)
    cams = [Camera.look_at((2.5, 0.3, 1.0), width=11, height=10), Camera.look_at((-0.5, 2.5, 1.0), width=11, height=11)]
    exact = hessian_blocks_reference(cloud, cams, RenderSettings(backward="autograd", dtype=torch.float64,
                                                                 tile_size=4, antialias=mode))
    fast = hessian_blocks(cloud, cams, views=0, render_settings=RenderSettings(tile_size=4, antialias=mode,
                                                                               kernels="compiled"))
    assert (exact.norm(dim=(1, 2)) > 0).sum() >= 7
    err = ((fast - exact).norm(dim=(1, 2)) / exact.norm(dim=(1, 2)).clamp(min=1e-300)).max().item()
    assert err < 1e-4


def test_kernel_choice_and_where_it_cannot_run():
    assert compiled.use_compiled("auto", "cpu", torch.float32)
    assert not compiled.use_compiled("auto", "cpu", torch.float64)  # float64 (gradcheck) is the torch code's
    assert not compiled.use_compiled("torch", "cpu", torch.float32)
    assert not compiled.use_compiled("auto", "meta", torch.float32)
    with pytest.raises(ValueError, match="float32"):
        compiled.use_compiled("compiled", "cpu", torch.float64)
    with pytest.raises(ValueError, match="kernels must be"):
        render(random_cloud(3, 0, seed=0), camera(), settings=RenderSettings(kernels="fast"))


def test_without_numba_the_torch_code_renders(monkeypatch):
    """Where Numba is missing or does not load, "auto" renders with the torch code (the same image)
    and "compiled" says why it cannot."""
    cloud, cam = random_cloud(40, 1, seed=4), camera()
    want = render(cloud, cam, background=BG, settings=TORCH).image
    monkeypatch.setattr(compiled, "numba_missing", lambda: "Numba does not load here: a test")
    assert torch.equal(render(cloud, cam, background=BG).image, want)
    with pytest.raises(ValueError, match="does not load here"):
        render(cloud, cam, settings=FAST)


def test_kernels_are_cached_in_the_user_cache_directory(tmp_path, monkeypatch):
    """A compiled kernel goes to $GVAE_CACHE_DIR/kernels (a user cache directory), never beside the
    source, and a dispatcher made afresh (as in a new process) finds it there instead of compiling."""
    from gvae_core.rendering import kernels  # noqa: PLC0415 - (imports Numba)

    monkeypatch.setenv("GVAE_CACHE_DIR", str(tmp_path))
    package = Path(compiled.__file__).parent
    before = {p for p in package.rglob("*") if p.suffix in (".nbi", ".nbc")}
    first = kernels.kernel(kernels.radix_order.py_func)
    assert not kernels.is_cached(first)
    keys, order = np.array([3, 1, 2], np.uint32), np.arange(3, dtype=np.int64)
    first(keys, order)
    assert order.tolist() == [1, 2, 0]
    where = kernels.kernel_cache_dir()
    assert where.parent == tmp_path / "kernels" and any(where.glob("kernels.radix_order-*.nbc"))
    assert kernels.is_cached(kernels.kernel(kernels.radix_order.py_func))
    assert {p for p in package.rglob("*") if p.suffix in (".nbi", ".nbc")} == before


def test_compiling_is_announced(monkeypatch):
    """`compile_kernels` says when it must compile (the Blender job shows it) and is silent when the
    kernels are only loaded; either way they are ready after it."""
    said = []
    monkeypatch.setattr(compiled, "kernels_cached", lambda: False)
    compiled.compile_kernels(lambda fraction, message: said.append((fraction, message)))
    assert len(said) == 1 and said[0][0] == 0.0 and "Compiling" in said[0][1]
    monkeypatch.setattr(compiled, "kernels_cached", lambda: True)
    compiled.compile_kernels(lambda fraction, message: said.append((fraction, message)))
    assert len(said) == 1


_ALL_WARMED = """
import json
from gvae_core import warmup
from gvae_core.compaction import compact, kernels as compaction_kernels
from gvae_core.detail import kernels as detail_kernels
from gvae_core.examples import example_cloud
from gvae_core.refinement import refine
from gvae_core import Camera
from gvae_core.rendering import kernels, render
from gvae_core.train import photometric_kernels
from gvae_core.train.photometric import photometric_loss
warmup.compile_kernels()
def signatures():
    return {f"{m.__name__}.{d.__name__}": len(d.signatures)
            for m in (kernels, detail_kernels, compaction_kernels, photometric_kernels)
            for d in kernels.module_kernels(m)}
ready = signatures()
cloud = example_cloud(300, seed=3)
refine(cloud)
compact(cloud, keep=0.5, distill=0)
image = render(cloud.to_torch(), Camera.look_at((2, 1, 1), width=40, height=30)).image.requires_grad_()
photometric_loss(image, image.detach().flip(0)).backward()
print(json.dumps([ready, signatures()]))
"""


def test_the_warm_up_makes_ready_what_refine_and_compact_run():
    """`warmup.compile_kernels` alone (in a fresh process) makes every room's kernels ready (the
    renderer's, the detail model's, compaction's, the training loss's) with the argument types a real
    refine, compact and training step give them: none compiles another signature afterwards
    (compaction's hit counts, which only the LightGaussian score and a sight of unseen rows run,
    stay unloaded)."""
    proc = subprocess.run([sys.executable, "-c", _ALL_WARMED], capture_output=True, text=True, check=True)
    ready, after = json.loads(proc.stdout.strip().splitlines()[-1])
    for room in ("rendering", "detail", "compaction", "train"):
        assert sum(n for name, n in ready.items() if f".{room}." in name) >= 2, (room, ready)
    assert max(ready.values()) == 1 and after == ready, (ready, after)


_WARMED = ("import json; from gvae_core.rendering import compiled; compiled.compile_kernels(); k = compiled.kernels(); "
           "print(json.dumps({n: [str(s) for s in getattr(k, n).signatures] for n in k.KERNELS}))")


def test_compile_kernels_makes_ready_what_render_and_the_hessian_run():
    """`compile_kernels` alone (in a fresh process) makes every kernel ready, with the argument types
    that `render` (forward and backward, in each anti-aliasing mode) and the Hessian's sweep give it:
    one set each, so nothing compiles again on first use. It drives the renderer's own steps (the
    renderer imports nothing above it), so this is what ties it to the Hessian's use of them."""
    proc = subprocess.run([sys.executable, "-c", _WARMED], capture_output=True, text=True, check=True)
    warmed = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(len(s) == 1 for s in warmed.values()), warmed
    for keys in ((), (FILTER_KEY,), (DILATION_KEY,)):
        cloud = _with_sizes(random_cloud(30, 3, seed=5), *keys)
        drawn = torch_cloud(cloud).replace(extra=cloud.extra)
        render(drawn, camera(), settings=FAST).image.sum().backward()
        hessian_blocks(cloud, [camera()], views=0, render_settings=RenderSettings(tile_size=4, kernels="compiled"))
    k = compiled.kernels()
    assert {n: [str(s) for s in getattr(k, n).signatures] for n in k.KERNELS} == warmed
