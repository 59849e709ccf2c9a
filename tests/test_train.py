"""Progressive training: schedules, initialisation, and a tiny end-to-end run on a scene rendered
from a known cloud (PSNR rises stage to stage, lineage invariants, determinism and resume, outputs
and the CLI)."""

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial import cKDTree

from gvae_core.antialias import DILATION_KEY, FILTER_KEY, dilation_3d, filter_3d
from gvae_core.camera import orbit
from gvae_core.cli import main
from gvae_core.cloud import GaussianCloud
from gvae_core.datasets import Views
from gvae_core.lineage import Lineage
from gvae_core.ply import read_ply
from gvae_core.quaternions import from_rotmat
from gvae_core.rendering import RenderSettings, render
from gvae_core.initialization import hull_points, initial_bounds, initial_cloud
from gvae_core.camera import scene_extent
from gvae_core.train import (PROGRESS_KEYS, ParameterAverage, RunFolder, TrainConfig, evaluate_psnr, gaussian_limit,
                             fine_tune, position_lr, split_validation, train_progressive)
from gvae_core.train.model import GaussianModel
from gvae_core.train.unseen import seen_by_any
from gvae_core.train.run_folder import FORMAT_1_LEFT_OUT


def test_schedules_scale_with_the_budget():
    cfg = TrainConfig(resolutions=(10, 20), iterations=(3000, 600))
    s0, s1 = cfg.stage_schedule(0), cfg.stage_schedule(1)
    keys = ("densify_every", "densify_from", "densify_until", "opacity_reset_every")
    assert tuple(s0[k] for k in keys) == (25, 50, 1500, 300)
    assert s1["densify_until"] == 300 and s1["densify_every"] == 25
    assert TrainConfig(iterations=(30000,), resolutions=(10,)).stage_schedule(0) == dict(
        iterations=30000, densify_every=100, densify_from=500, densify_until=15000, opacity_reset_every=3000)
    assert [cfg.sh_degree_at(i) for i in (0, 119, 120, 240, 360, 3600)] == [0, 0, 1, 2, 3, 3]
    assert position_lr(cfg, 2.0, 0, 100) == pytest.approx(2 * 1.6e-4)
    assert position_lr(cfg, 2.0, 100, 100) == pytest.approx(2 * 1.6e-6)
    assert position_lr(cfg, 2.0, 50, 100) == pytest.approx(2 * 1.6e-5)
    assert TrainConfig.profile("tiny", seed=3).seed == 3
    with pytest.raises(ValueError):
        TrainConfig.profile("huge")
    with pytest.raises(ValueError):
        TrainConfig(resolutions=(10, 20), iterations=(1, 2, 3))


def test_initialisation_and_extent_from_cameras():
    cams = orbit(8, 4.0, math.radians(30), width=40, height=40, fov_x=math.radians(40), target=(1, 2, 3))
    center, half = initial_bounds(cams)
    np.testing.assert_allclose(center, [1, 2, 3], atol=1e-6)
    assert half == pytest.approx(4.0 * math.sin(math.radians(20)), rel=1e-6)
    _, extent = scene_extent(cams)
    assert extent == pytest.approx(1.1 * 4.0 * math.cos(math.radians(30)), rel=1e-6)
    points = [1, 2, 3] + (np.random.default_rng(0).random((500, 3)) * 2 - 1) * half
    cloud = initial_cloud(TrainConfig(init_count=500, sh_degree=2), points)
    assert len(cloud) == 500 and cloud.sh_degree == 2
    assert np.isfinite(cloud.scales).all() and (cloud.scales < 0).all()
    given = initial_cloud(TrainConfig(), np.array([[0, 0, 0, 1, 0, 0.5], [1, 0, 0, 0, 1, 0.5]]))
    np.testing.assert_allclose(given.base_color(), [[1, 0, 0.5], [0, 1, 0.5]], atol=1e-6)
    with pytest.raises(ValueError):
        initial_cloud(TrainConfig(), np.zeros((3, 2)))


# ------------------------------------------------------------------ end to end (renderer)

def ground_truth_cloud():
    rng = np.random.default_rng(42)
    n = 60
    return GaussianCloud(
        means=rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        scales=np.log(rng.uniform(0.06, 0.14, (n, 3))).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=np.full(n, 3.0, np.float32),
        sh_dc=rng.normal(0, 1.0, (n, 3)).astype(np.float32),
    )


_VIEW_CACHE = {}


def synthetic_views(split, height):
    """Views of the ground-truth cloud rendered directly at each height (straight RGB + alpha)."""
    key = (split, height)
    if key not in _VIEW_CACHE:
        gt = ground_truth_cloud()
        cams = orbit(10 if split == "train" else 3, 2.5, math.radians(30 if split == "train" else 45),
                     width=height, height=height, fov_x=math.radians(45),
                     start_azimuth=0.0 if split == "train" else 0.5)
        imgs, alphas = [], []
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # tiny images: one thread beats two on a busy machine
        with torch.no_grad():
            for c in cams:
                out = render(gt, c, background=(0.0, 0.0, 0.0))
                a = out.alpha.numpy()
                imgs.append(np.clip(out.image.numpy() / np.maximum(a[..., None], 1e-6), 0, 1))
                alphas.append(a)
        torch.set_num_threads(threads)
        _VIEW_CACHE[key] = Views(cams, np.stack(imgs), np.stack(alphas))
    return _VIEW_CACHE[key]


TINY = dict(resolutions=(12, 18, 24), iterations=(150, 100, 100), init_count=300, sh_degree=1, max_gaussians=500,
            min_densify_every=20, min_opacity_reset_every=60, train_eval_views=4,
            background=(0.0, 0.0, 0.0), init="auto", validation_views=0, converge=False)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    pytest.importorskip("gvae_core.rendering")
    out = tmp_path_factory.mktemp("run")
    result = train_progressive(synthetic_views, TrainConfig(**TINY), out_dir=out, progress=False, threads=1)
    return result, out


def test_psnr_rises_from_stage_to_stage(tiny_run):
    result, _ = tiny_run
    test_psnr = [e["test_psnr"] for e in result.log]
    assert len(test_psnr) == 3
    assert test_psnr[0] < test_psnr[1] < test_psnr[2], test_psnr
    assert test_psnr[2] > 21.0


def test_a_stage_keeps_only_what_its_training_photos_draw(tiny_run):
    """Every Gaussian of every stage's result is drawn by one of that stage's training cameras (the
    log says how many were left out); `seen_by_any` tells a Gaussian in view from one behind every
    camera and one beside them all."""
    result, _ = tiny_run
    settings = RenderSettings(antialias=TrainConfig(**TINY).antialias)
    for s, snap in enumerate(result.lineage.snapshots):
        cams = synthetic_views("train", TINY["resolutions"][s]).cameras
        assert seen_by_any(snap.cloud.to_torch(), cams, settings).all(), s
        assert result.log[s]["unseen_removed"] >= 0
    cams = synthetic_views("train", 24).cameras
    far = 50.0 * cams[0].center  # far behind the first camera, and past all the others
    cloud = GaussianCloud(means=np.float32([[0, 0, 0], far, [0, 0, 40.0]]), scales=np.full((3, 3), -3.0, np.float32),
                          quats=np.tile(np.float32([1, 0, 0, 0]), (3, 1)), opacities=np.full(3, 3.0, np.float32),
                          sh_dc=np.zeros((3, 3), np.float32))
    assert seen_by_any(cloud.to_torch(), cams, settings).tolist() == [True, False, False]


def test_lineage_invariants_of_a_run(tiny_run):
    result, _ = tiny_run
    lin = result.lineage
    assert lin.n_stages == 3 and lin.resolutions == [12, 18, 24]
    seen_before = set()
    for k, snap in enumerate(lin.snapshots):
        ids = snap.ids
        assert len(np.unique(ids)) == len(ids)
        assert len(snap) == result.log[k]["n_gaussians"]
        if k == 0:
            assert (snap.parents == -1).all()
        else:
            prev = set(lin.snapshots[k - 1].ids.tolist())
            assert all(p in prev for p in snap.parents.tolist())
            # every parent is an earlier Gaussian: survivors are their own parent, new ones are younger
            new = ~np.isin(ids, list(prev))
            assert (snap.parents[~new] == ids[~new]).all() and (snap.parents[new] < ids[new]).all()
            assert not (set(ids[new].tolist()) & seen_before)  # ids are never reused
        seen_before |= set(ids.tolist())
        batch = lin.sequences(k)
        assert batch.geometry.shape[:2] == (len(snap), k + 1)
        for s in range(k + 1):
            alive = np.isin(batch.ids, lin.snapshots[s].ids)
            np.testing.assert_array_equal(batch.geometry[:, s, 10], alive.astype(np.float32))
            np.testing.assert_array_equal(batch.appearance[:, s, 49], alive.astype(np.float32))
    assert result.log[1]["cloned"] + result.log[1]["split"] > 0  # later stages densify too
    assert np.array_equal(result.cloud.extra["gvae_id"], lin.snapshots[-1].ids)


def test_run_outputs(tiny_run):
    result, out = tiny_run
    log = json.loads((out / "log.json").read_text())
    assert [e["resolution"] for e in log] == [12, 18, 24]
    for e in log:
        for key in ("resolution", "iterations", "seconds", "n_gaussians", "train_psnr", "test_psnr", "peak_rss_mb"):
            assert key in e
        assert e["peak_rss_mb"] > 0 and e["seconds"] > 0
    for s in range(3):
        cloud = read_ply(out / f"stage_{s}.ply")
        snap = result.lineage.snapshots[s]
        assert cloud.extra["gvae_id"].dtype.kind == "i" and cloud.extra["gvae_parent"].dtype.kind == "i"
        np.testing.assert_array_equal(cloud.extra["gvae_id"], snap.ids)
        np.testing.assert_array_equal(cloud.extra["gvae_parent"], snap.parents)
        np.testing.assert_array_equal(cloud.means, snap.cloud.means)
        # the world dilation of the stage's own training cameras (not stored in the lineage)
        assert cloud.extra[DILATION_KEY].dtype == np.float32 and FILTER_KEY not in cloud.extra
        assert DILATION_KEY not in snap.cloud.extra
        np.testing.assert_array_equal(cloud.extra[DILATION_KEY],
                                      dilation_3d(cloud.means, synthetic_views("train", [12, 18, 24][s]).cameras))
    assert (read_ply(out / "stage_0.ply").extra[DILATION_KEY].mean()
            > 1.4 * read_ply(out / "stage_2.ply").extra[DILATION_KEY].mean())  # finer stages, smaller sizes
    np.testing.assert_array_equal(result.cloud.extra[DILATION_KEY],
                                  read_ply(out / "stage_2.ply").extra[DILATION_KEY])
    back = Lineage.load(out / "lineage.npz")
    np.testing.assert_array_equal(back.sequences(2).geometry, result.lineage.sequences(2).geometry)


def test_same_seed_same_result_and_resume(tiny_run, tmp_path):
    """A run interrupted during its last stage resumes from the last finished one and, seeded
    per stage, retrains that stage to exactly the same Gaussians."""
    result, out = tiny_run
    run_dir = tmp_path / "run"
    shutil.copytree(out, run_dir)
    state = json.loads((run_dir / "run.json").read_text())
    state["stages_done"], state["next_id"] = 2, result.log[1]["next_id"]
    (run_dir / "run.json").write_text(json.dumps(state))
    (run_dir / "stage_2.ply").unlink()
    resumed = train_progressive(synthetic_views, TrainConfig(**TINY), out_dir=run_dir, progress=False, threads=1)
    assert [e["resolution"] for e in resumed.log] == [12, 18, 24] and (run_dir / "stage_2.ply").is_file()
    assert resumed.log[:2] == result.log[:2]
    for a, b in zip(resumed.lineage.snapshots, result.lineage.snapshots):
        np.testing.assert_array_equal(a.ids, b.ids)
        np.testing.assert_array_equal(a.parents, b.parents)
        for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(a.cloud, name), getattr(b.cloud, name))
    # a finished run resumes to nothing (its size from the last stage's PLY); another configuration is refused
    again = train_progressive(synthetic_views, TrainConfig(**TINY), out_dir=run_dir, progress=False)
    assert again.log == resumed.log
    np.testing.assert_array_equal(again.cloud.extra[DILATION_KEY], result.cloud.extra[DILATION_KEY])
    with pytest.raises(ValueError, match="different configuration"):
        train_progressive(synthetic_views, TrainConfig(**{**TINY, "seed": 1}), out_dir=run_dir, progress=False)


def test_same_seed_same_result_from_scratch():
    pytest.importorskip("gvae_core.rendering")
    cfg = dict(TINY, resolutions=(12,), iterations=(50,))
    a, b, c = (train_progressive(synthetic_views, TrainConfig(**{**cfg, "seed": seed}), progress=False, threads=1)
               for seed in (0, 0, 1))
    np.testing.assert_array_equal(a.cloud.means, b.cloud.means)
    np.testing.assert_array_equal(a.cloud.extra["gvae_id"], b.cloud.extra["gvae_id"])
    assert len(a.cloud) != len(c.cloud) or not np.array_equal(a.cloud.means, c.cloud.means)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA GPU and CUDA build of torch here (optional runtime)"))])
def test_training_on_a_named_device(device):
    """The device path (parameters, Adam state, densification statistics and edits, targets and
    the filter on `device`; random draws from the CPU generator) trains the same run as the
    default: bit for bit on the CPU; on a GPU a render and its gradients agree closely, and a run
    (whose float reductions go in another order, so its trajectory drifts: up to 0.02 in a few
    means after 100 steps on an H200) densifies the same and reaches the same PSNR. A device this
    machine cannot use is refused before any work, naming it."""
    pytest.importorskip("gvae_core.rendering")
    cfg = TrainConfig(**{**TINY, "resolutions": (12, 18), "iterations": (60, 40), "antialias": "mip"})
    default = train_progressive(synthetic_views, cfg, progress=False, threads=1)
    named = train_progressive(synthetic_views, cfg, progress=False, threads=1, device=device)
    assert [e["n_gaussians"] for e in named.log] == [e["n_gaussians"] for e in default.log]
    assert sum(e["cloned"] + e["split"] + e["pruned"] for e in named.log) > 0  # densification ran there
    if device == "cpu":
        np.testing.assert_array_equal(named.cloud.means, default.cloud.means)
        np.testing.assert_array_equal(named.cloud.extra[FILTER_KEY], default.cloud.extra[FILTER_KEY])
    else:
        cloud = default.cloud.replace(extra={})
        grads = []
        for dev in ("cpu", device):
            c = cloud.to_torch(device=dev)
            means = c.means.detach().clone().requires_grad_(True)
            out = render(c.replace(means=means), synthetic_views("train", 18).cameras[0], background=(1.0, 1.0, 1.0),
                         settings=RenderSettings(antialias="classic"))
            out.image.square().mean().backward()
            grads.append((out.image.detach().cpu().numpy(), means.grad.cpu().numpy()))
        np.testing.assert_allclose(grads[1][0], grads[0][0], atol=1e-4)
        np.testing.assert_allclose(grads[1][1], grads[0][1], atol=1e-5 + 1e-3 * np.abs(grads[0][1]).max())
        assert np.median(np.abs(named.cloud.means - default.cloud.means)) < 1e-3
    assert named.log[-1]["test_psnr"] == pytest.approx(default.log[-1]["test_psnr"], abs=0.05)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="'cuda'.*no CUDA GPU"):
            train_progressive(synthetic_views, cfg, progress=False, device="cuda")
    with pytest.raises(ValueError, match="unknown torch device 'gpu0'"):
        train_progressive(synthetic_views, cfg, progress=False, device="gpu0")


def test_the_configuration_round_trips_and_refuses_what_it_does_not_know():
    default, mip = TrainConfig.profile("default"), TrainConfig.profile("default", antialias="mip")
    assert mip.to_dict() == {**default.to_dict(), "antialias": "mip"}
    for config in (default, mip, TrainConfig.profile("legacy"), TrainConfig.profile("tiny")):
        assert TrainConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(ValueError, match="antialias"):
        TrainConfig(antialias="auto")
    with pytest.raises(ValueError, match="unknown field"):
        TrainConfig.from_dict({**default.to_dict(), "wobble": 1})


def test_a_run_folder_of_the_first_format_reads_back_as_the_training_it_was(tmp_path):
    """run.json of format 1 left out the fields still at the values it trained with: read back,
    they take those values (such a run resumes); format 2 writes every field."""
    legacy = TrainConfig.profile("legacy", resolutions=(10,), iterations=(5,))
    old = {k: v for k, v in legacy.to_dict().items() if k not in FORMAT_1_LEFT_OUT}
    (tmp_path / "run.json").write_text(json.dumps({"config": old, "stages_done": 0, "next_id": 0, "data": None}))
    state = RunFolder(tmp_path).state()
    assert state.config == legacy and state.stages_done == 0 and state.data is None
    assert RunFolder(tmp_path).resume(legacy) is None  # nothing finished, nothing to refuse
    with pytest.raises(ValueError, match="different configuration .*seed"):
        RunFolder(tmp_path).resume(dataclasses.replace(legacy, seed=4))
    (tmp_path / "run.json").write_text("{")
    with pytest.raises(ValueError, match="not a training run state file"):
        RunFolder(tmp_path).state()


def test_the_budget_follows_the_photos_pixels():
    """`gaussians_per_pixel` caps a stage at that many Gaussians per pixel of one training photo,
    the smaller of it and `max_gaussians` wins and says so."""
    cam = orbit(1, 2.5, 0.5, width=40, height=30, fov_x=1.0)[0]
    assert gaussian_limit(TrainConfig(gaussians_per_pixel=0.5, max_gaussians=None), 8, cam) == (
        600, "0.5 per pixel of a photo")
    assert gaussian_limit(TrainConfig(gaussians_per_pixel=0.5, max_gaussians=100), 8, cam) == (100, "max_gaussians")
    assert gaussian_limit(TrainConfig(gaussians_per_pixel=None, max_gaussians=None), 8, cam)[1] == "what memory allows"
    with pytest.raises(ValueError, match="gaussians_per_pixel"):
        TrainConfig(gaussians_per_pixel=0)


def test_validation_photos_are_set_aside_evenly():
    views = synthetic_views("train", 12)
    train, val = split_validation(views, 8)
    assert len(val) == 1 and len(train) == 9  # at most one in eight of ten
    assert not {tuple(c.center) for c in val.cameras} & {tuple(c.center) for c in train.cameras}
    assert [tuple(c.center) for c in split_validation(synthetic_views("train", 18), 8)[1].cameras] == [
        tuple(c.center) for c in val.cameras]  # the same photo at every height
    thrice = Views(views.cameras * 3, np.concatenate([views.images] * 3), np.concatenate([views.alphas] * 3))
    train, val = split_validation(thrice, 8)
    assert len(val) == 3 and len(train) == 27
    assert split_validation(views, 0) == (views, None)
    small = Views(views.cameras[:7], views.images[:7], views.alphas[:7])
    assert split_validation(small, 8)[1] is None


def _converging(**changes):
    return TrainConfig(**{**TINY, "resolutions": (12, 18), "iterations": (60, 60), "validation_views": 8,
                          "converge": True, "validation_every": 20, "patience": 40, "max_iterations": 400,
                          "cool_down": 0, **changes})


def test_the_last_stage_trains_until_the_validation_photo_stops_improving():
    """With no gain large enough to count, the plateau rule stops the last stage `patience`
    iterations after its planned count; a spent time budget stops it at the planned count; the
    progress hook sees every stage, the validation measurements and the end."""
    pytest.importorskip("gvae_core.rendering")
    reports = []
    result = train_progressive(synthetic_views, _converging(min_gain=100.0), progress=False, threads=1,
                               on_progress=reports.append)
    first, last = result.log
    assert first["iterations"] == 60 and "stopped" not in first  # the coarse stage: fixed
    assert last["iterations"] == 100 and last["stopped"].startswith("converged: no gain of 100")
    assert last["validation_views"] == 1 and [s for s, _ in last["validation_curve"]] == [20, 40, 60, 80, 100]
    assert last["best_step"] in (60, 80, 100) and last["validation_psnr"] > 15
    assert all(set(PROGRESS_KEYS) <= set(r) for r in reports)
    assert {r["stage"] for r in reports} == {0, 1} and all(r["stages"] == 2 for r in reports)
    assert any("validation_psnr" in r for r in reports) and "test_psnr" in reports[-1]
    assert reports[-1]["n_gaussians"] == len(result.cloud)
    budget = train_progressive(synthetic_views, _converging(min_gain=0.0, max_minutes=1e-9), progress=False,
                               threads=1)
    assert budget.log[-1]["iterations"] == 60 and "time budget" in budget.log[-1]["stopped"]


def test_a_progress_hook_that_raises_stops_the_run_and_it_resumes(tmp_path):
    pytest.importorskip("gvae_core.rendering")
    cfg = _converging(converge=False)

    def cancel(report):
        if report["stage"] == 1 and report["step"] >= 20:
            raise KeyboardInterrupt("cancelled")

    with pytest.raises(KeyboardInterrupt):
        train_progressive(synthetic_views, cfg, out_dir=tmp_path, progress=False, threads=1, on_progress=cancel)
    assert json.loads((tmp_path / "run.json").read_text())["stages_done"] == 1
    resumed = train_progressive(synthetic_views, cfg, out_dir=tmp_path, progress=False, threads=1)
    whole = train_progressive(synthetic_views, cfg, progress=False, threads=1)
    np.testing.assert_array_equal(resumed.cloud.means, whole.cloud.means)


def test_fine_tune_stops_when_asked():
    pytest.importorskip("gvae_core.rendering")
    views = synthetic_views("train", 12)
    cloud = ground_truth_cloud()
    calls = []

    def stop(it, current):
        calls.append((it, len(current), current.means.requires_grad))
        return it >= 20

    cfg = TrainConfig(**TINY)
    early = fine_tune(cloud, views, 60, config=cfg, should_stop=stop, check_every=10)
    assert calls == [(10, len(cloud), False), (20, len(cloud), False)]
    short = fine_tune(cloud, views, 20, config=cfg)
    assert not np.array_equal(early.means, cloud.means)
    assert np.abs(early.means - short.means).max() < np.abs(early.means - cloud.means).max()
    with pytest.raises(ValueError, match="check_every"):
        fine_tune(cloud, views, 10, config=cfg, should_stop=stop, check_every=0)


def test_parameter_average_weights_the_iterates():
    """The running average of the iterates is the weighted sum its definition gives: each step t's
    parameters weighted (1 - d_t) x the later decays, the start by all of them, d_t = min(decay,
    (1 + t) / (10 + t)); a decay outside (0, 1) is refused."""
    cloud = ground_truth_cloud()
    model = GaussianModel(cloud, np.arange(len(cloud)), np.full(len(cloud), -1), TrainConfig().learning_rates(1.0), 1.0,
                          len(cloud))
    rng = np.random.default_rng(3)
    states = [{k: p.detach().clone() for k, p in model.params.items()}]
    mean = ParameterAverage(model, 0.5)  # (the cap binds from step 8)
    for _ in range(12):
        model.load_params({k: torch.from_numpy(rng.normal(size=p.shape).astype(np.float32))
                           for k, p in model.params.items()})
        states.append({k: p.detach().clone() for k, p in model.params.items()})
        mean.update(model)
    decays = [min(0.5, (1.0 + t) / (10.0 + t)) for t in range(1, 13)]
    weights = [float(np.prod(decays))] + [(1 - decays[t - 1]) * float(np.prod(decays[t:])) for t in range(1, 13)]
    assert sum(weights) == pytest.approx(1.0)
    for name in model.params:
        expected = sum(w * states[t][name].double() for t, w in enumerate(weights))
        np.testing.assert_allclose(mean.values[name].double(), expected, atol=1e-5)
    for bad in (0.0, 1.0, 1.5):
        with pytest.raises(ValueError, match="decay"):
            ParameterAverage(model, bad)


def test_fine_tune_ends_on_the_average_its_checks_saw():
    """With `average`, a fine-tune's result is the averaged cloud its last check saw (not the last
    iterate: the run without it ends elsewhere)."""
    pytest.importorskip("gvae_core.rendering")
    views = synthetic_views("train", 12)
    cloud = ground_truth_cloud()
    cfg = TrainConfig(**TINY)
    seen = []
    averaged = fine_tune(cloud, views, 30, config=cfg, check_every=10, average=0.9,
                         should_stop=lambda it, current: seen.append(current.means.numpy().copy()) and False)
    last = fine_tune(cloud, views, 30, config=cfg)
    assert len(seen) == 3
    np.testing.assert_array_equal(averaged.means, seen[-1])
    assert not np.array_equal(averaged.means, last.means) and not np.array_equal(averaged.means, cloud.means)


def test_training_with_the_filters():
    """Mip-Splatting training: the filter follows the Gaussians while they densify, the run learns
    the scene, and renders in the mip mode (its stored filter) better than in the classic one."""
    pytest.importorskip("gvae_core.rendering")
    cfg = TrainConfig(**{**TINY, "resolutions": (12, 24), "iterations": (150, 150), "antialias": "mip"})
    result = train_progressive(synthetic_views, cfg, progress=False, threads=1)
    cloud = result.cloud
    np.testing.assert_array_equal(cloud.extra[FILTER_KEY], filter_3d(cloud.means, synthetic_views("train", 24).cameras))
    assert DILATION_KEY not in cloud.extra
    assert result.log[-1]["test_psnr"] > 21.0 and result.log[-1]["cloned"] + result.log[-1]["split"] > 0
    test = synthetic_views("test", 24)
    mip = evaluate_psnr(cloud, test, TINY["background"], 1, settings=RenderSettings(antialias="mip"))
    classic = evaluate_psnr(cloud, test, TINY["background"], 1, settings=RenderSettings(antialias="classic"))
    assert mip == pytest.approx(result.log[-1]["test_psnr"], abs=1e-3) and mip > classic


def test_hull_initialisation_lies_inside_the_object():
    pytest.importorskip("gvae_core.rendering")

    views = synthetic_views("train", 24)
    pts = hull_points(views, 400, np.random.default_rng(0))
    assert pts.shape == (400, 6) and (pts[:, 3:] >= 0).all() and (pts[:, 3:] <= 1).all()
    for cam, alpha in zip(views.cameras, views.alphas):
        uv, z = cam.project(pts[:, :3])
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        assert (alpha[row[inside], col[inside]] > 0.1).all()
    tree = cKDTree(ground_truth_cloud().means)
    center, half = initial_bounds(views.cameras)
    uniform = center + (np.random.default_rng(1).random((400, 3)) * 2 - 1) * half
    assert np.median(tree.query(pts[:, :3])[0]) < 0.5 * np.median(tree.query(uniform)[0])


def test_views_at_resolution_area_averages_premultiplied():
    cams = orbit(2, 3.0, 0.3, width=8, height=8)
    images = np.zeros((2, 8, 8, 3), np.float32)
    alphas = np.zeros((2, 8, 8), np.float32)
    images[:, :, :4] = [1.0, 0.0, 0.0]
    alphas[:, :, :4] = 1.0
    images[:, :, 4:] = [0.0, 1.0, 0.0]  # invisible colour must not bleed in
    small = Views(cams, images, alphas).at_resolution(2)
    assert small.images.shape == (2, 2, 2, 3) and small.cameras[0].height == 2
    np.testing.assert_allclose(small.alphas[0], [[1, 0], [1, 0]])
    np.testing.assert_allclose(small.images[0, :, 0], [[1, 0, 0], [1, 0, 0]])


def test_cli_trains_a_scene_dir(tmp_path):
    """`gvae train` on a NeRF-Synthetic folder written from the synthetic views."""
    pytest.importorskip("gvae_core.rendering")


    scene = tmp_path / "scene"
    for split in ("train", "test"):
        views = synthetic_views(split, 24)
        (scene / split).mkdir(parents=True)
        frames = []
        for i, (cam, img, a) in enumerate(zip(views.cameras, views.images, views.alphas)):
            rgba = np.dstack([img, a])
            Image.fromarray(np.round(rgba * 255).astype(np.uint8), "RGBA").save(scene / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": cam.to_blender_c2w().tolist()})
        (scene / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": views.cameras[0].fov_x,
                                                                    "frames": frames}))
    out = tmp_path / "run"
    code = main(["train", str(scene), "--out", str(out), "--resolutions", "12", "24", "--iterations", "40",
                 "--sh-degree", "0", "--init-count", "200", "--background", "0", "0", "0", "--quiet",
                 "--threads", "1"])
    assert code == 0
    log = json.loads((out / "log.json").read_text())
    assert [e["resolution"] for e in log] == [12, 24] and all(e["test_psnr"] > 10 for e in log)
    config = TrainConfig.from_dict(json.loads((out / "run.json").read_text())["config"])
    assert not config.converge and config.iterations == (40, 40)  # --iterations fixes the count
    assert (out / "stage_1.ply").is_file() and (out / "lineage.npz").is_file()
    assert main(["train", str(tmp_path / "nowhere"), "--out", str(out)]) == 2
    shutil.rmtree(out)


def _photo_capture(folder, height=24, background=(0.35, 0.4, 0.45)):
    """A COLMAP text capture of the known cloud, photographed opaque over a grey `background` from
    13 cameras (PINHOLE, off-centre principal point), with its centres as the SfM points."""
    gt = ground_truth_cloud()
    cams = orbit(13, 2.5, math.radians(35), width=height + 8, height=height, fov_x=math.radians(45))
    (folder / "images").mkdir(parents=True)
    (folder / "sparse" / "0").mkdir(parents=True)
    cam_lines, image_lines = [], []
    for i, cam in enumerate(cams):
        with torch.no_grad():
            img = render(gt, cam, background=background).image.clamp(0, 1).numpy()
        Image.fromarray(np.round(img * 255).astype(np.uint8)).save(folder / "images" / f"{i:02d}.png")
        cam_lines.append(f"{i + 1} PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}")
        q = from_rotmat(cam.rotation)
        pose = " ".join(repr(float(v)) for v in (*q, *cam.translation))
        image_lines += [f"{i + 1} {pose} {i + 1} {i:02d}.png", ""]
    (folder / "sparse" / "0" / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (folder / "sparse" / "0" / "images.txt").write_text("\n".join(image_lines) + "\n")
    rgb = np.clip(gt.base_color() * 255, 0, 255).astype(int)
    (folder / "sparse" / "0" / "points3D.txt").write_text("\n".join(
        f"{i} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.5" for i, (p, c) in
        enumerate(zip(gt.means.astype(float), rgb))) + "\n")
    return cams


def test_cli_trains_a_colmap_capture_with_held_out_views(tmp_path):
    """`gvae train CAPTURE --test-every 4` on a COLMAP capture of opaque photos: the SfM points are
    the start and cover every training pixel, the held-out photos are scored (PSNR and SSIM), the
    background is stored with the cloud and `gvae render` draws over it; `--more N` trains the last
    stage N more iterations with the same Gaussians."""
    pytest.importorskip("gvae_core.rendering")
    _photo_capture(tmp_path / "cap", background=(0.35, 0.4, 0.45))
    out = tmp_path / "run"
    assert main(["train", str(tmp_path / "cap"), "--out", str(out), "--resolutions", "12", "24", "--iterations", "60",
                 "--sh-degree", "0", "--background", "0.35", "0.4", "0.45", "--test-every", "4", "--quiet",
                 "--threads", "1"]) == 0
    log = json.loads((out / "log.json").read_text())
    assert log[0]["start"].startswith("60 SfM points") and log[0]["start_coverage"] == 1.0
    assert all(e["test_psnr"] > 18 and 0.3 < e["test_ssim"] <= 1 for e in log), log
    cloud = read_ply(out / "stage_1.ply")
    assert cloud.background == pytest.approx((0.35, 0.4, 0.45))
    assert json.loads((out / "run.json").read_text())["config"]["test_every"] == 4
    # gvae render draws over the stored background unless told otherwise
    assert main(["render", str(out / "stage_1.ply"), "--out", str(tmp_path / "png"), "--cameras",
                 str(tmp_path / "cap"), "--height", "24"]) == 0
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert len(pngs) == 13
    corner = np.asarray(Image.open(pngs[0]))[0, 0] / 255.0
    assert corner == pytest.approx((0.35, 0.4, 0.45), abs=0.03)
    assert main(["train", str(out), "--more", "20", "--quiet", "--threads", "1"]) == 0
    more = json.loads((out / "more.json").read_text())
    assert [(e["stage"], e["more"], e["n_gaussians"]) for e in more] == [(1, 20, len(cloud))]
    assert read_ply(out / "stage_1_more_20.ply").background == pytest.approx((0.35, 0.4, 0.45))
    assert more[0]["test_psnr"] > log[-1]["test_psnr"] - 1.0
    assert more[0]["test_psnr_before"] == log[-1]["test_psnr"]  # (what the held-out photos did: before, after)


def test_the_last_stage_ends_on_the_average_of_its_iterates():
    """With `average`, the last stage keeps the running average of its iterates from the end of its
    densification (the rows fixed from there) and its validation photos judge that average; without
    it, the last iterate. The earlier stages are the same either way."""
    from gvae_core.train.loop import Stage, run_stage  # noqa: PLC0415

    pytest.importorskip("gvae_core.rendering")
    config = _converging(validation_views=8, min_gain=100.0, average=0.9)
    plain = train_progressive(synthetic_views, dataclasses.replace(config, average=None), progress=False, threads=1)
    averaged = train_progressive(synthetic_views, config, progress=False, threads=1)
    assert plain.log[0]["test_psnr"] == averaged.log[0]["test_psnr"]  # (the coarse stage: no average)
    assert not np.array_equal(plain.cloud.means, averaged.cloud.means)
    assert len(plain.cloud) == len(averaged.cloud)  # (densification is over when the average begins)
    views = synthetic_views("train", 12)
    model = GaussianModel.fresh(averaged.cloud.replace(extra={}), config.learning_rates(1.0), 1.0)
    stage = Stage(model, views.cameras, torch.from_numpy(views.composite((0, 0, 0))), config, 30,
                  np.random.default_rng(0), torch.Generator(), lambda it: 1, average_from=21, average_decay=0.9)
    assert stage.result_params() is model.params
    run_stage(stage)
    assert stage.average is not None and stage.average.steps == 9  # begun at 21, then 22..30
    assert stage.result_params() is stage.average.values
    with pytest.raises(ValueError, match="average"):
        TrainConfig(average=1.5)


def test_a_converged_last_stage_cools_down_and_keeps_what_the_validation_photos_like():
    """With `cool_down`, a converged last stage trains that many more iterations (Adam afresh, the
    position rate decaying again, ending on their average); the validation photos judge the average
    against the stage's best and the better one is the result (the log says which)."""
    pytest.importorskip("gvae_core.rendering")
    plain = train_progressive(synthetic_views, _converging(min_gain=100.0), progress=False, threads=1)
    cooled = train_progressive(synthetic_views, _converging(min_gain=100.0, cool_down=40), progress=False,
                               threads=1)
    before, last = plain.log[-1], cooled.log[-1]
    assert last["iterations"] == before["iterations"] + 40 and last["cool_down"] == 40
    assert last["validation_curve"][:-1] == before["validation_curve"]
    step, value = last["validation_curve"][-1]
    assert step == last["iterations"]
    best = max(v for s, v in before["validation_curve"] if s >= 60)
    assert last["cool_down_kept"] == (value > best)
    if last["cool_down_kept"]:
        assert last["best_step"] == step and not np.array_equal(cooled.cloud.means, plain.cloud.means)
    else:
        assert last["best_step"] == before["best_step"]
        np.testing.assert_array_equal(cooled.cloud.means, plain.cloud.means)
    assert (plain.log[0]["test_psnr"], plain.log[0]["n_gaussians"]) == (cooled.log[0]["test_psnr"],
                                                                     cooled.log[0]["n_gaussians"])
    with pytest.raises(ValueError, match="cool_down"):
        TrainConfig(cool_down=-1)


def test_validation_keeps_only_a_state_its_photos_like_better():
    """`Validation.judge`: a state the photos like better becomes the best; a worse one (faded) does not."""
    from gvae_core.train.model import PARAMS  # noqa: PLC0415
    from gvae_core.train.validation import Validation  # noqa: PLC0415

    config = _converging()
    views = synthetic_views("train", 12)
    trained = train_progressive(synthetic_views, config, progress=False, threads=1).cloud
    watch = Validation(config, views, views.cameras, RenderSettings(), 0.0, 0, True, lambda message: None)
    good = {n: torch.as_tensor(getattr(trained, n)) for n in PARAMS}
    faded = {**good, "opacities": good["opacities"] - 8.0}
    assert watch.judge(good, 10, 1) and watch.best_step == 10
    assert not watch.judge(faded, 20, 1) and watch.best_step == 10
    assert torch.equal(watch.best_params["opacities"], good["opacities"])
    assert [s for s, _ in watch.curve] == [10, 20] and watch.curve[1][1] < watch.curve[0][1]
