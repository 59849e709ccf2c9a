"""Refine from the capture's images (`gvae_core.superres`, `refine(images=...)`): the fit raises the
higher-resolution picture toward the truth while the training-resolution picture stays the input's,
children draw nothing at the training rate, the per-image guards do what they say, images that do
not belong to the cloud are refused before any work, and degenerate Gaussians stay finite."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from gvae_core import Camera
from gvae_core.antialias import DILATION_KEY, with_dilation_3d
from gvae_core.cli import main
from gvae_core.capture import load_nerf_synthetic
from gvae_core.datasets import Views
from gvae_core.examples import example_cloud
from gvae_core.losses import psnr
from gvae_core.octaves import training_height, with_octaves
from gvae_core.ply import read_ply, write_ply
from gvae_core.refinement import refine
from gvae_core.rendering import render
from gvae_core.scenes.faults import FAULTS, faulted_scene
from gvae_core.superres import ImageMismatchError, SuperResConfig, capture_images, fit_octaves
from gvae_core.detail.fit import crop
from gvae_core.superres.children import CHILD_LOGIT
from gvae_core.superres.fit import _reach, _reaching, _tiles, holdout_rows
from gvae_core.superres.guards import ExposureCorrection, PoseCorrection, _skew

H = 24  # training height of the synthetic capture


def _cameras(n, height=H):
    return [Camera.look_at((3 * math.cos(a), 3 * math.sin(a), 1.2 + 0.3 * math.sin(3 * a)), (0, 0, 0),
                           width=height, height=height, fov_x=1.0) for a in np.linspace(0, 2 * math.pi, n,
                                                                                         endpoint=False)]


def _capture(n_views=6, n=400, seed=0):
    """A sharp 'scene' (the truth), its images at 2H area-averaged to H (the training images) and a
    'trained' cloud: the truth blurred a little, carrying the anti-aliasing size of the cameras at H."""
    truth = example_cloud(n, seed=seed).with_sh_degree(1)
    cams = _cameras(n_views)
    big = [c.scaled(2 * H) for c in cams]
    sharp = with_dilation_3d(truth, big)
    images = []
    for c in big:
        img = render(sharp, c, background=(1.0, 1.0, 1.0)).image
        images.append(torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0).numpy())
    views = Views(cams, np.clip(np.stack(images), 0, 1))
    trained = with_dilation_3d(truth.replace(scales=truth.scales + np.float32(0.25)), cams)
    return truth, trained, views


def _psnr_at(cloud, cams, truth_images):
    return float(np.mean([psnr(render(cloud, c, background=(1.0, 1.0, 1.0)).image.numpy(), t)
                          for c, t in zip(cams, truth_images)]))


def test_the_fit_sharpens_the_higher_resolution_picture_and_keeps_the_training_one():
    truth, trained, views = _capture()
    fit = fit_octaves(trained, views, 1, SuperResConfig(steps=15, patch=0, start="zero", lr=3.0))
    refined = with_octaves(trained, fit.changes, 1.0)
    assert fit.psnr_after > fit.psnr_before + 2.0  # the averaged-down 2x render reproduces the images better
    big = [c.scaled(2 * H) for c in views.cameras]
    sharp = with_dilation_3d(truth, big)
    truth_2x = [render(sharp, c, background=(1.0, 1.0, 1.0)).image.numpy() for c in big]
    assert _psnr_at(refined, big, truth_2x) > _psnr_at(trained, big, truth_2x) + 2.0
    for cam in views.cameras:  # at the training resolution nothing is drawn changed
        assert torch.equal(render(refined, cam).image, render(trained, cam).image)
    assert all(np.isfinite(v).all() for v in fit.changes.values())


def test_a_patch_is_drawn_from_the_gaussians_that_reach_it_exactly_as_from_all():
    _, trained, views = _capture(n=600)
    rng = np.random.default_rng(1)
    changes = {"scales": rng.normal(0, 0.3, trained.scales.shape).astype(np.float32),
               "means": rng.normal(0, 0.01, trained.means.shape).astype(np.float32)}
    rows = trained.to_torch()
    tc = {f: torch.from_numpy(v) for f, v in changes.items()}
    full = with_octaves(rows, tc, 1.0)
    kept = []
    for cam in views.cameras[:3]:
        big = cam.scaled(2 * H)
        for x0, y0, size in ((0, 0, 16), (20, 8, 12), (30, 30, 18)):
            patch = crop(big, x0, y0, size, size)
            keep = torch.from_numpy(_reaching(rows.means.double().numpy().T.copy(), _reach(rows, tc, 1.0), patch))
            sub = with_octaves(rows.select(keep), {f: v[keep] for f, v in tc.items()}, 1.0)
            assert torch.equal(render(sub, patch).image, render(full, patch).image)
            kept.append(len(keep) / len(rows))
    assert min(kept) < 0.9  # (and it does leave some out)


def test_children_draw_nothing_at_the_training_rate_and_appear_above_it():
    _, trained, views = _capture(n=200)
    fit = fit_octaves(trained, views, 1, SuperResConfig(steps=30, patch=0, start="zero", children=0.0,
                                                        densify_at=(0.3,), max_children=0.25))
    assert 0 < len(fit.child_roots) <= 50 and fit.children is not None
    assert np.all(fit.children.opacities == CHILD_LOGIT)
    refined = with_octaves(trained, fit.changes, 1.0).append_children(fit.children, fit.child_roots)
    assert len(refined) == len(trained) + len(fit.child_roots)
    assert np.array_equal(refined.extra[DILATION_KEY][len(trained):], trained.extra[DILATION_KEY][fit.child_roots])
    for cam in views.cameras:
        assert torch.equal(render(refined, cam).image, render(refined.select(np.arange(len(trained))), cam).image)
    big = views.cameras[0].scaled(2 * H)
    assert not torch.equal(render(refined, big).image, render(refined.select(np.arange(len(trained))), big).image)


def test_pose_correction_moves_the_cloud_as_the_corrected_camera_would_see_it():
    cloud = example_cloud(300, seed=1).with_sh_degree(0)
    cam = Camera.look_at([3.0, 0.5, 1.0], width=48, height=48)
    pose = PoseCorrection([cam, cam], np.array([3.0, 3.0]), 1.0)
    with torch.no_grad():
        pose.params[0] = torch.tensor([0.3, -0.2, 0.1, 0.2, 0.1, -0.3], dtype=torch.float64)
    p = pose.centred()[0].detach()  # (the mean over the images is held at zero)
    omega, tau = p[:3] / pose.focal[0], p[3:] / pose.focal[0] * 3.0
    rot = torch.linalg.matrix_exp(_skew(omega)).numpy()
    w2c = cam.world_to_cam.copy()
    w2c[:3, :3], w2c[:3, 3] = rot @ w2c[:3, :3], rot @ w2c[:3, 3] + tau.numpy()
    moved = Camera(w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    with torch.no_grad():
        a = render(pose.apply(cloud.to_torch(), 0), cam).image
    b = render(cloud, moved).image
    assert float((a - b).abs().max()) < 1e-4
    assert pose.pixels()[0] == pytest.approx(float(p.norm()))


def test_exposure_changes_what_the_cloud_draws_not_the_background():
    exposure = ExposureCorrection(2, 1.0)
    image, alpha = torch.rand(8, 8, 3), torch.zeros(8, 8)
    alpha[2:5] = 1.0
    bg = torch.tensor([1.0, 1.0, 1.0])
    image = image * alpha[..., None] + (1 - alpha[..., None]) * bg
    assert torch.allclose(exposure.apply(image, alpha, bg, 0), image)
    with torch.no_grad():
        exposure.params[0, :3] = math.log(1.2)
    out = exposure.apply(image, alpha, bg, 0)
    assert torch.allclose(out[0], bg.expand(8, 3))  # transparent: the background as it was
    assert torch.allclose(out[3], image[3] * math.sqrt(1.2), atol=1e-6)  # mean over the images is held at zero


def test_images_that_are_not_the_clouds_are_refused_before_any_fit():
    truth, trained, views = _capture(n_views=4)
    other = Views(views.cameras, np.clip(views.images[::-1] * 0 + np.random.default_rng(0).random(views.images.shape),
                                         0, 1).astype(np.float32))
    with pytest.raises(ImageMismatchError, match="not the images the cloud was trained on"):
        capture_images(trained, other)
    with pytest.raises(ValueError, match="trained at about 24 px"):
        capture_images(trained, views, height=48)
    captured = capture_images(trained, views)
    assert captured.views.cameras[0].height == H and captured.match.background == (1.0, 1.0, 1.0)
    assert "24 px" in captured.height_source
    assert training_height(trained, [c.scaled(3 * H) for c in views.cameras])[0] == pytest.approx(H)


def _write_capture(views, folder):
    from PIL import Image  # noqa: PLC0415

    folder.mkdir()
    frames = []
    for i, (cam, img) in enumerate(zip(views.cameras, views.images)):
        Image.fromarray((img * 255).round().astype(np.uint8)).save(folder / f"r_{i}.png")
        frames.append({"file_path": f"r_{i}", "transform_matrix": cam.to_blender_c2w().tolist()})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": views.cameras[0].fov_x,
                                                              "frames": frames}))
    return folder


def test_refine_with_images_and_the_cli(tmp_path, capsys):
    _, trained, views = _capture(n_views=4, n=200)
    folder = _write_capture(views, tmp_path / "capture")
    r = refine(trained, images=folder, fit=SuperResConfig(steps=6, patch=16))
    assert r.fit is not None and len(r.cloud) == len(trained) + len(r.added)
    assert "training resolution: 24 px" in r.summary() and "dB PSNR" in r.summary()
    src = write_ply(trained, tmp_path / "in.ply")
    out = tmp_path / "out.ply"
    assert main(["refine", str(src), str(out), "--images", str(folder), "--fit-steps", "4"]) == 0
    text = capsys.readouterr().out
    assert "training resolution: 24 px" in text and len(read_ply(out)) == len(trained)  # no children by default
    assert main(["refine", str(src), str(out), "--images", str(folder), "--fit-steps", "4", "--children",
                 "--pose-correction", "--exposure-correction"]) == 0
    assert "training resolution: 24 px" in capsys.readouterr().out and len(read_ply(out)) > len(trained)
    for args, message in ((["--images", str(folder), "--image-height", "48"], "trained at about 24 px"),
                          (["--images", str(tmp_path / "missing")], "missing"),
                          (["--image-height", "24"], "need --images"),
                          (["--pose-correction"], "need --images")):
        bad = tmp_path / "never.ply"
        assert main(["refine", str(src), str(bad), *args]) == 2
        assert message in capsys.readouterr().err and not bad.exists()
    with pytest.raises(ValueError, match="not by 'vae'"):
        refine(trained, images=folder, method="vae")


def test_degenerate_gaussians_fit_to_finite_changes():
    _, trained, views = _capture(n_views=3, n=120)
    c = trained.copy()
    c.scales[:5] = -30.0
    c.scales[5:10] = 8.0
    c.quats[10:15] = 0.0
    c.opacities[15:20] = 40.0
    c.opacities[20:25] = -40.0
    c.means[25:30] = views.cameras[0].center  # at a camera
    fit = fit_octaves(c, views, 1, SuperResConfig(steps=5, patch=0, start="zero", children=0.0, densify_at=(0.5,)))
    assert all(np.isfinite(v).all() for v in fit.changes.values())
    assert fit.children is None or not len(fit.children.nonfinite_rows())


def test_faulted_captures_change_what_they_say(tmp_path):
    _, _, views = _capture(n_views=4)
    scene = _write_capture(Views([c.scaled(2 * H) for c in views.cameras],
                                 np.repeat(np.repeat(views.images, 2, 1), 2, 2)), tmp_path / "scene")
    (scene / "transforms_test.json").write_text((scene / "transforms_train.json").read_text())
    clean = load_nerf_synthetic(faulted_scene(scene, "none", H, cache=tmp_path / "cache"), "train")
    assert np.abs(clean.images - views.images).max() < 1.5 / 255  # the area average, as 8-bit
    moved = load_nerf_synthetic(faulted_scene(scene, "pose 0.5 px", H, cache=tmp_path / "cache"), "train")
    centre = np.zeros((1, 3))
    for a, b in zip(clean.cameras, moved.cameras):  # the scene's centre moves by half a pixel
        assert np.linalg.norm(a.project(centre)[0] - b.project(centre)[0]) == pytest.approx(0.5, rel=0.05)
    exposed = load_nerf_synthetic(faulted_scene(scene, "exposure 10%", H, cache=tmp_path / "cache"), "train")
    ratio = exposed.images.mean((1, 2, 3)) / clean.images.mean((1, 2, 3))
    assert np.all(np.abs(ratio - 1) <= 0.11) and np.ptp(ratio) > 0.01
    cubic = load_nerf_synthetic(faulted_scene(scene, "bicubic", H, cache=tmp_path / "cache"), "train")
    assert np.abs(cubic.images - clean.images).max() > 2 / 255
    assert set(FAULTS) >= {"none", "pose 0.1 px", "pose 0.25 px", "pose 0.5 px", "exposure 10%", "bicubic", "lanczos"}


def test_a_fit_too_large_for_the_memory_is_refused_before_the_images_are_read(monkeypatch, tmp_path):
    import gvae_core.refinement as refinement  # noqa: PLC0415
    import gvae_core.resources as resources  # noqa: PLC0415
    import gvae_core.superres.match as match  # noqa: PLC0415

    _, trained, views = _capture(n_views=3, n=100)
    folder = _write_capture(views, tmp_path / "capture")
    need = resources.estimate_image_fit_memory(100, 1, images=3, height=H, width=H)
    more = resources.estimate_image_fit_memory(100, 1, images=300, height=H, width=H, children=0.5)
    assert more > need > resources.estimate_image_fit_memory(50, 1, images=3, height=H, width=H)
    drawn = [resources.estimate_image_fit_memory(100, 1, images=3, height=750, width=1000, **k)
             for k in ({"octaves": 2}, {}, {"patch": 96})]  # a whole 4x, a whole 2x, a 96 px tile's 2x render
    assert drawn[0] > drawn[1] > drawn[2]
    monkeypatch.setattr(resources, "available_memory", lambda: need - 1)
    monkeypatch.setattr(refinement, "check_refine_memory", lambda *a, **k: 0)  # the detail model's own check
    monkeypatch.setattr(match, "load_capture_images", lambda *a, **k: pytest.fail("images read"))
    with pytest.raises(resources.NotEnoughMemoryError, match="from 3 images of 24x24 px"):
        refine(trained.with_sh_degree(1), images=folder, fit={"children": None})


def test_visible_adam_is_adam_on_rows_seen_and_leaves_the_others_where_they_are():
    from gvae_core.superres.optim import VisibleAdam  # noqa: PLC0415

    torch.manual_seed(0)
    a = torch.randn(6, 3, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    ours, adam = VisibleAdam([a], lr=0.1), torch.optim.Adam([b], lr=0.1, eps=1e-15)
    for _ in range(3):  # every row seen: Adam, step for step
        g = torch.randn(6, 3)
        a.grad, b.grad = g.clone(), g.clone()
        ours.step()
        adam.step()
    assert torch.allclose(a, b, atol=1e-6)
    kept = a.detach()[:3].clone()
    for _ in range(5):  # rows 0-2 unseen (zero gradient): they stay put; Adam's momentum would move them
        g = torch.randn(6, 3)
        g[:3] = 0.0
        a.grad, b.grad = g.clone(), g.clone()
        ours.step()
        adam.step()
    assert torch.equal(a.detach()[:3], kept) and not torch.allclose(b.detach()[:3], kept, atol=1e-3)
    assert torch.allclose(a.detach()[3:], b.detach()[3:], atol=1e-6)  # the rows seen: Adam's update, its step count


def test_a_fit_the_held_out_images_do_not_like_is_not_kept():
    """Every 8th image judges the fit instead of being fitted; a fit that draws them far worse than
    its best is stopped and taken back; one that does not draw them better than its step 0 is not
    kept (the better of the detail model's changes and the input instead), and the summary says so;
    with too few images to hold any out, its own images judge it."""
    _, trained, views = _capture(n_views=16, n=150)
    detail = refine(trained, fidelity=None).cloud
    for start in ("detail", "zero"):
        r = refine(trained, images=views, fit=SuperResConfig(steps=6, start=start, lr=300.0, check_every=0.1,
                                                             slow_down=0.0))  # (going on slower: the next test)
        fit = r.fit
        assert fit.holdout_views == 2 and fit.images == 14 and fit.kept != "fit" and not fit.improves
        assert fit.fit_step == 0 and fit.steps_run < fit.steps_planned  # stopped, back at its step 0
        assert "so not kept" in r.summary() and "held-out images" in r.summary()
        # the best on the held-out images of where it began, the detail model's changes and the input,
        # drawn at 2x exactly as it is
        others = {"begin": fit.holdout_begin, "start": fit.holdout_start, "input": fit.holdout_input}
        assert fit.kept == max(others, key=others.get)
        same_as = {"begin": with_octaves(trained, fit.changes, 1.0), "input": trained,
                   "start": detail if start == "detail" else trained}[fit.kept]
        cam = views.cameras[0].scaled(2 * H)
        assert torch.equal(render(r.cloud, cam).image, render(same_as, cam).image)
    few = Views(views.cameras[:6], views.images[:6])
    r = refine(trained, images=few, fit=SuperResConfig(steps=4, start="zero", lr=300.0))
    assert r.fit.holdout_views == 0 and r.fit.kept == "start" and "no images held out" in r.summary()
    good = refine(trained, images=views, fit=SuperResConfig(steps=24, start="zero", lr=3.0, check_every=0.2))
    assert good.fit.kept == "fit" and good.fit.holdout_fit > good.fit.holdout_begin
    assert good.fit.fit_step == good.fit.steps_run == good.fit.steps_planned  # ran its steps: the last state kept
    assert [s for s, _ in good.fit.checks][0] == 0 and len(good.fit.checks) > 2


def test_a_fit_that_falls_goes_back_to_its_best_and_on_slower():
    """A fit whose held-out figure falls `tolerance` below its best is taken back there and goes on
    at `slow_down` times its rates, once; with slow_down 0 it stops at the first fall."""
    _, trained, views = _capture(n_views=16, n=150)
    fits = {sd: refine(trained, images=views, fit=SuperResConfig(steps=24, start="zero", lr=30.0, check_every=0.2,
                                                                 slow_down=sd)).fit for sd in (0.3, 0.0)}
    slower, stopped = fits[0.3], fits[0.0]
    assert stopped.slowed_at == 0 and stopped.steps_run < stopped.steps_planned  # stopped at its first fall
    assert stopped.fit_step < stopped.steps_run and stopped.holdout_fit == max(v for _, v in stopped.checks)
    assert slower.slowed_at == stopped.steps_run and slower.steps_run == slower.steps_planned  # on, to the end
    assert slower.kept == "fit" and slower.holdout_fit > stopped.holdout_fit
    assert "slower from step" in slower.judged() and "slower" not in stopped.judged()
    with pytest.raises(ValueError, match="slow_down"):
        SuperResConfig(slow_down=1.0)


def test_tiles_cover_each_image_and_held_out_rows_are_spread():
    for width, height, patch in ((100, 75, 32), (64, 48, 0), (40, 30, 64), (33, 17, 16)):
        covered = np.zeros((height, width), int)
        for x0, y0, w, h in _tiles(width, height, patch):
            assert 0 <= x0 and x0 + w <= width and 0 <= y0 and y0 + h <= height
            covered[y0:y0 + h, x0:x0 + w] += 1
        assert covered.min() >= 1, (width, height, patch)
    names = [f"r_{i}" for i in range(84)]  # (by name, numbers by value: r_4 is the fifth)
    assert holdout_rows(names, 8).tolist() == [4, 12, 20, 28, 36, 44, 52, 60, 68, 76]
    assert len(holdout_rows(names[:15], 8)) == 0 and len(holdout_rows(names, 0)) == 0


def test_several_views_a_step_tiles_and_the_pull_towards_the_start():
    """The steps a fit plans are its passes over the (image, tile) pairs over the views a step sums;
    pulling the changes back towards their start keeps them smaller."""
    _, trained, views = _capture(n_views=6, n=200)
    plain = fit_octaves(trained, views, 1, SuperResConfig(epochs=2, patch=12, views_per_step=2, start="zero",
                                                          holdout=0))
    assert plain.steps_planned == plain.steps_run == math.ceil(2 * 6 * 4 / 2)  # four 12 px tiles a 24 px image
    assert all(np.isfinite(v).all() for v in plain.changes.values())
    pulled = fit_octaves(trained, views, 1, SuperResConfig(epochs=2, patch=12, views_per_step=2, start="zero",
                                                           holdout=0, pull=0.5))
    size = {name: sum(float(np.abs(f.changes[k]).sum()) for k in ("scales", "means", "sh_dc")) for name, f in
            (("plain", plain), ("pulled", pulled))}
    assert size["pulled"] < 0.7 * size["plain"], size


def test_the_optimizer_is_a_setting_of_the_fit():
    """`SuperResConfig.optimizer`: the fit's own VisibleAdam by default, torch's plain Adam on
    request (its momentum moves rows a tile did not see, so the two part), anything else refused."""
    _, trained, views = _capture(n_views=6, n=200)
    config = SuperResConfig(steps=4, patch=12, start="zero", holdout=0)
    visible = fit_octaves(trained, views, 1, config)
    plain = fit_octaves(trained, views, 1, dataclasses.replace(config, optimizer="adam"))
    assert not np.array_equal(visible.changes["means"], plain.changes["means"])
    with pytest.raises(ValueError, match="optimizer"):
        SuperResConfig(optimizer="sgd")
