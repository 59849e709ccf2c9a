"""Refinement: budgets, sequential steps, result consistency, degenerate inputs, the CLI.

The mechanics of the steps are tested with random stand-in models and without the fidelity
check (which would put most of what they do back); the check has its own tests, test_fidelity.py."""

import functools
import json
import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud, refinement, resources
from gvae_core.antialias import with_dilation_3d
from gvae_core.cli import main as gvae
from gvae_core.detail import DetailConfig, DetailModel, save_detail
from gvae_core.formats import read_splat_file
from gvae_core.lineage import Lineage
from gvae_core.octaves import LIMIT_KEY, octave_fields
from gvae_core.ply import read_ply, write_ply
from gvae_core.refinement import RefineResult
from gvae_core.refinement import refine as checked_refine
from gvae_core.refinement import refine_steps as checked_refine_steps
from gvae_core.rendering import render
from gvae_core.vae import GaussianVAE, load_model, save_model


refine = functools.partial(checked_refine, fidelity=None)
refine_steps = functools.partial(checked_refine_steps, fidelity=None)


def _cloud(n=64, seed=0, degree=1) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    k = {0: 0, 1: 3, 3: 15}[degree]
    return GaussianCloud(means=rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                         scales=(math.log(0.05) + rng.normal(0, 0.3, (n, 3))).astype(np.float32),
                         quats=rng.normal(size=(n, 4)).astype(np.float32),
                         opacities=rng.normal(0, 1, n).astype(np.float32),
                         sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                         sh_rest=rng.normal(0, 0.1, (n, k, 3)).astype(np.float32),
                         extra={"nx": np.zeros(n, np.float32)})


def _model(exist_logit=None, seed=0) -> GaussianVAE:
    """A random model; with `exist_logit` every slot's existence logit is forced to that value."""
    model = GaussianVAE.create(seed=seed)
    if exist_logit is not None:
        last = model.geometry.decoder[-1]
        g = model.geometry
        width = g.state_dim + 1 + g.spread_dim   # per slot: state, existence logit, offset spread
        with torch.no_grad():
            last.weight[g.state_dim::width] = 0.0
            last.bias[g.state_dim::width] = exist_logit
    return model


def _scores(n, seed=0):
    return np.random.default_rng(seed).uniform(0, 10, n).astype(np.float32)


def _check_result(cloud: GaussianCloud, r: RefineResult, steps: int):
    n = len(cloud)
    assert isinstance(r, RefineResult)
    report = r.cloud.validate()
    assert len(report.nonfinite_rows) == 0
    # a zero quaternion can only be an input row the model left alone
    assert set(report.zero_quat_rows.tolist()) <= set(cloud.numpy().validate().zero_quat_rows.tolist())
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        assert np.isfinite(getattr(r.cloud, name)).all()
    np.testing.assert_allclose(np.linalg.norm(r.cloud.quats[n:], axis=1), 1.0, atol=1e-5)
    assert r.cloud.sh_degree == cloud.sh_degree
    np.testing.assert_array_equal(r.added, np.arange(n, len(r.cloud)))
    assert len(r.parents) == len(r.added) == len(r.step)
    assert r.added.dtype == r.parents.dtype == r.step.dtype == np.int64
    assert np.isin(r.parents, r.selected).all()
    assert ((r.step >= 1) & (r.step <= steps)).all() and (np.diff(r.step) >= 0).all()
    assert r.scores.shape == (n,) and np.isfinite(r.scores).all()
    assert {"hessian", "model", "total"} <= set(r.timings) and all(v >= 0 for v in r.timings.values())
    # Rows that were not selected are untouched; input order is kept.
    untouched = np.setdiff1d(np.arange(n), r.selected)
    src = cloud.numpy()
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(r.cloud, name)[untouched], getattr(src, name)[untouched])
    assert set(r.cloud.extra) == set(cloud.extra)


@pytest.mark.parametrize("budget", ["all", 0.25, 7, "auto", 0])
def test_result_fields_consistent(budget):
    cloud = _cloud()
    r = refine(cloud, steps=2, budget=budget, model=_model(), scores=_scores(len(cloud)))
    _check_result(cloud, r, 2)
    expected = {"all": 64, 0.25: 16, 7: 7, 0: 0}.get(budget)
    if expected is not None:
        assert len(r.selected) == expected
    assert np.isin(r.selected, np.argsort(-r.scores)[: max(len(r.selected), 1)]).all() or budget == "all"


def test_steps_are_sequential():
    cloud = _cloud(n=40)
    model = _model(exist_logit=30.0)  # every slot exists: each lineage becomes `slots` Gaussians
    c = model.slots
    for steps in (1, 2, 3):
        r = refine(cloud, steps=steps, budget=5, model=model, scores=_scores(40))
        counts = np.bincount(r.step, minlength=steps + 1)[1:]
        expected = [5 * c ** (k - 1) * (c - 1) for k in range(1, steps + 1)]
        assert counts.tolist() == expected
        _check_result(cloud, r, steps)
        assert len(r.cloud) == 40 + sum(expected)
        # Every selected input Gaussian is the root of c**steps - 1 added ones.
        assert (np.bincount(r.parents, minlength=40)[r.selected] == c ** steps - 1).all()
    none = refine(cloud, steps=2, budget="all", model=_model(exist_logit=-30.0), scores=_scores(40))
    assert len(none.added) == 0 and len(none.cloud) == 40


def test_degenerate_inputs_give_finite_outputs():
    cloud = _cloud(n=12, degree=3)
    cloud.quats[0] = 0.0
    cloud.scales[1] = -30.0
    cloud.scales[2] = 30.0
    cloud.opacities[3] = 50.0
    cloud.opacities[4] = -50.0
    cloud.means[5] = [1e7, -1e7, 3e6]
    cloud.sh_dc[6] = 1e6
    cloud.means[7:] = 0.0
    cloud.scales[7:] = 0.0
    cloud.quats[7:] = 0.0
    for model in (_model(exist_logit=30.0), _model(seed=1)):
        r = refine(cloud, steps=3, budget="all", model=model, scores=np.zeros(12, np.float32))
        _check_result(cloud, r, 3)
        assert np.all(r.cloud.scales[12:] >= -20) and np.all(r.cloud.scales[12:] <= 12)
    # far-away Gaussians stay near where they were (positions are not squashed)
    r = refine(cloud, steps=1, budget="all", model=_model(exist_logit=30.0), scores=np.zeros(12, np.float32))
    far = r.cloud.means[r.added[r.parents == 5]]
    assert np.allclose(far, cloud.means[5], rtol=1e-3)
    # one Gaussian, all-zero, and an empty cloud
    one = GaussianCloud(means=np.zeros((1, 3), np.float32), scales=np.zeros((1, 3), np.float32),
                        quats=np.zeros((1, 4), np.float32), opacities=np.zeros(1, np.float32),
                        sh_dc=np.zeros((1, 3), np.float32))
    _check_result(one, refine(one, steps=2, budget="all", model=_model(exist_logit=30.0), scores=[0.0]), 2)
    empty = refine(GaussianCloud.empty(), steps=1, budget="auto", model=_model(), scores=np.zeros(0))
    assert len(empty.cloud) == 0 and len(empty.added) == 0


def test_with_hessian_scores_and_torch_input():
    cloud = _cloud(n=30)
    calls = []
    r = refine(cloud.to_torch(), steps=1, budget=0.2, model=_model(exist_logit=30.0),
               hessian_options={"views": 1, "resolution": 24},
               progress=lambda fraction, message: calls.append((fraction, message)))
    _check_result(cloud, r, 1)
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and all(isinstance(m, str) for _, m in calls)
    assert (r.scores >= 0).all() and r.scores.max() > 0
    np.testing.assert_array_equal(np.sort(np.argsort(-r.scores, kind="stable")[:6]), r.selected)


def test_bad_inputs():
    cloud = _cloud(n=10)
    cloud.means[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"non-finite .*\[3\]"):
        refine(cloud, model=_model(), scores=np.zeros(10))
    with pytest.raises(ValueError, match="steps"):
        refine(_cloud(), steps=0, model=_model(), scores=np.zeros(64))
    with pytest.raises(ValueError, match="scores"):
        refine(_cloud(), model=_model(), scores=np.zeros(3))


def test_lineage_history_is_used():
    rng = np.random.default_rng(0)
    stage0, stage1 = _cloud(n=10, seed=1), _cloud(n=16, seed=2)
    lin = Lineage(np.zeros(3), 1.0)
    lin.add_stage(stage0, np.arange(10), np.full(10, -1), 50)
    lin.add_stage(stage1, np.arange(16), np.r_[np.arange(10), rng.integers(0, 10, 6)], 75)
    model = _model(exist_logit=30.0)
    seen = []
    predict = model.predict

    def spy(hg, ha, densify=None, **kw):
        seen.append((np.asarray(hg).copy(), np.asarray(ha).copy()))
        return predict(hg, ha, densify, **kw)

    model.predict = spy
    with_history = refine(stage1, budget="all", model=model, lineage=lin, scores=np.zeros(16))
    _check_result(stage1, with_history, 1)
    (hg, ha), = seen  # the model saw each Gaussian's two-stage lineage, as the lineage records it
    want = lin.sequences(1)
    np.testing.assert_array_equal(hg, want.geometry)
    np.testing.assert_array_equal(ha, want.appearance)
    seen.clear()
    refine(stage1, budget="all", model=model, scores=np.zeros(16))
    assert seen[0][0].shape[1] == 1  # without a lineage: one-node lineages
    with pytest.raises(ValueError, match=r"\[10, 16\]"):  # no stage of the lineage has 12 Gaussians
        refine(_cloud(n=12, seed=1), model=model, lineage=lin, scores=np.zeros(12))
    # rows are matched to the lineage by the cloud's gvae_id when it has one
    perm = np.random.default_rng(1).permutation(16)
    shuffled = stage1.select(perm)
    shuffled.extra["gvae_id"] = perm.astype(np.int64)
    _check_result(shuffled, refine(shuffled, budget="all", model=model, lineage=lin, scores=np.zeros(16)), 1)
    shuffled.extra["gvae_id"] = perm.astype(np.int64) + 100
    with pytest.raises(ValueError, match="not alive"):
        refine(shuffled, budget="all", model=model, lineage=lin, scores=np.zeros(16))


def _three_stage_lineage():
    """Stages of 10, 16 and 20 Gaussians (ids persist; stage 2 prunes id 3 and adds four)."""
    rng = np.random.default_rng(0)
    stages = [_cloud(n=10, seed=1), _cloud(n=16, seed=2), _cloud(n=19, seed=3)]
    lin = Lineage(np.zeros(3), 1.0)
    lin.add_stage(stages[0], np.arange(10), np.full(10, -1), 50)
    lin.add_stage(stages[1], np.arange(16), np.r_[np.arange(10), rng.integers(0, 10, 6)], 75)
    ids2 = np.r_[np.delete(np.arange(16), 3), 16, 17, 18, 19]
    lin.add_stage(stages[2], ids2, np.r_[np.delete(np.arange(16), 3), 0, 1, 2, 4], 100)
    lin.set_normalization(*stages[2].normalization())
    return lin


def test_a_stage_of_a_longer_run_is_refined_with_its_own_history():
    """A stage PLY of a run that went on to later stages: the lineage is cut at the cloud's stage
    (found from its ids and positions, or given), as the trainer would have left it there."""
    lin = _three_stage_lineage()
    model = _model(exist_logit=30.0)
    seen = []
    predict = model.predict

    def spy(hg, ha, densify=None, **kw):
        seen.append(np.asarray(hg).copy())
        return predict(hg, ha, densify, **kw)

    model.predict = spy
    stage1 = lin.stage_cloud(1)  # as `gvae train` writes stage_1.ply: with gvae_id, gvae_parent
    assert lin.stage_of(stage1) == 1 and lin.stage_of(lin.stage_cloud(2)) == 2
    r = refine(stage1, budget="all", model=model, lineage=lin, scores=np.zeros(16))
    assert r.stage == 1
    want = lin.prefix(2)
    np.testing.assert_array_equal(seen[0], want.sequences(1).geometry)
    # stage 0's ids are all alive at stage 1 too (and at 2 but for id 3): the positions decide
    assert lin.stage_of(lin.stage_cloud(0)) == 0
    assert refine(lin.stage_cloud(0), budget=3, model=model, lineage=lin, scores=_scores(10)).stage == 0
    # without ids: by count and positions
    plain = lin.stage_cloud(1).replace(extra={})
    assert refine(plain, budget=3, model=model, lineage=lin, scores=_scores(16)).stage == 1
    # a stage given explicitly, and a wrong one
    assert refine(stage1, budget=3, model=model, lineage=lin, stage=1, scores=_scores(16)).stage == 1
    with pytest.raises(ValueError, match="not alive"):
        refine(stage1, budget=3, model=model, lineage=lin, stage=0, scores=_scores(16))
    with pytest.raises(ValueError, match="stage 5"):
        refine(stage1, budget=3, model=model, lineage=lin, stage=5, scores=_scores(16))


def test_a_cloud_too_large_for_the_memory_is_refused_before_any_work(monkeypatch):
    calls = []
    monkeypatch.setattr(refinement, "hessian_scores", lambda *a, **k: calls.append(1))
    monkeypatch.setattr(resources, "available_memory", lambda: 200 << 20)  # 200 MiB free
    with pytest.raises(resources.NotEnoughMemoryError, match=r"64 Gaussians .* needs about \d+\.\d GiB"):
        refine(_cloud(n=64), model=_model())
    assert not calls
    need = resources.estimate_refine_memory(1_000_000, 3)
    assert need > resources.estimate_refine_memory(1_000_000, 0) > resources.estimate_refine_memory(100_000, 0)
    monkeypatch.setattr(resources, "available_memory", lambda: need - 1)
    with pytest.raises(resources.NotEnoughMemoryError, match="1,000,000 Gaussians"):
        resources.check_refine_memory(1_000_000, 3)
    monkeypatch.setattr(resources, "available_memory", lambda: None)  # unknown: not refused
    assert resources.check_refine_memory(10 ** 9, 3) > 0


def test_cli_refine_and_fit(tmp_path, capsys):
    model_dir = tmp_path / "model"
    save_model(_model(exist_logit=30.0), model_dir)
    write_ply(_cloud(n=50), tmp_path / "in.ply")
    code = gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"), "--steps", "2", "--budget", "4",
                 "--model", str(model_dir), "--views", "1", "--resolution", "16", "--fidelity", "off"])
    assert code == 0
    out = read_ply(tmp_path / "out.ply")
    c = 4  # slots
    assert len(out) == 50 + 4 * (c - 1) + 4 * c * (c - 1)
    text = capsys.readouterr().out
    assert "4 selected" in text and "hessian" in text
    assert gvae(["refine", str(tmp_path / "missing.ply"), str(tmp_path / "x.ply"), "--model", str(model_dir)]) == 2
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "x.ply"), "--budget", "many"]) == 2
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "x.ply"), "--fidelity", "-1"]) == 2
    # With the fidelity check (the default), the random stand-in's lineages are put back
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "x.ply"), "--steps", "2", "--budget", "4",
                 "--model", str(model_dir), "--views", "1", "--resolution", "16", "--fidelity", "0"]) == 0
    assert len(read_ply(tmp_path / "x.ply")) == 50 and "4 of them put back" in capsys.readouterr().out
    (tmp_path / "x.ply").unlink()
    assert not (tmp_path / "x.ply").exists()

    lin = Lineage(np.zeros(3), 1.0)
    lin.add_stage(_cloud(n=12, seed=3), np.arange(12), np.full(12, -1), 50)
    lin.add_stage(_cloud(n=20, seed=4), np.arange(20), np.r_[np.arange(12), np.arange(8)], 75)
    (tmp_path / "run").mkdir()
    lin.save(tmp_path / "run" / "lineage.npz")
    code = gvae(["fit-vae", str(tmp_path / "run"), "--holdout", str(tmp_path / "run"), "--out",
                 str(tmp_path / "fitted"), "--steps", "3", "--batch", "8", "--quiet", "--d-model", "16",
                 "--layers", "1", "--decoder-hidden", "24"])
    assert code == 0
    fitted = load_model(tmp_path / "fitted")
    assert fitted.meta["steps"] == 3 and "holdout" in fitted.meta["metrics"]
    for vae in (fitted.geometry, fitted.appearance):
        assert (vae.config.d_model, vae.config.layers, vae.config.decoder_hidden) == (16, 1, 24)
    assert gvae(["fit-vae", str(tmp_path / "nothing"), "--out", str(tmp_path / "f2"), "--quiet"]) == 2


def test_refine_steps_yields_each_step_like_refine():
    cloud = _cloud(n=30)
    model = _model()
    results = []
    for r in refine_steps(cloud, steps=3, budget=6, model=model, scores=_scores(30), seed=4):
        results.append(r)
    assert len(results) == 3
    for k, r in enumerate(results, 1):
        alone = refine(cloud, steps=k, budget=6, model=model, scores=_scores(30), seed=4)
        for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(r.cloud, name), getattr(alone.cloud, name))
        np.testing.assert_array_equal(r.parents, alone.parents)


def test_the_callers_time_between_steps_is_not_refine_time(monkeypatch):
    """A clock that moves one second per reading, and a day whenever refine_steps hands a result
    to its caller: the totals must not contain those days."""
    ticks = iter(range(10 ** 9))
    day = [0]
    monkeypatch.setattr(refinement.time, "perf_counter", lambda: next(ticks) + 86400 * day[0])
    totals = []
    for r in refine_steps(_cloud(n=30), steps=3, budget=6, model=_model(), scores=_scores(30), seed=4):
        totals.append(r.timings["total"])
        day[0] += 1
    assert len(totals) == 3 and totals[0] < totals[1] < totals[2] < 86400


def test_budget_forces_densification_at_the_first_step_only():
    model = _model()
    calls = []
    predict = model.predict

    def spy(hg, ha, densify=None, **kw):
        calls.append(None if densify is None else np.asarray(densify).copy())
        return predict(hg, ha, densify, **kw)

    model.predict = spy
    refine(_cloud(n=30), steps=3, budget=5, model=model, scores=_scores(30))
    assert len(calls[0]) == 5 and calls[0].all()         # the budget's choice densifies
    assert len(calls) == 3 and all(c is None for c in calls[1:])  # then the model decides
    calls.clear()
    refine(_cloud(n=30), steps=2, budget="all", model=model)
    assert len(calls) == 2 and all(c is None for c in calls)


def _appearances(cloud: GaussianCloud) -> set[bytes]:
    rows = np.concatenate([cloud.opacities[:, None], cloud.sh_dc, cloud.sh_rest.reshape(len(cloud), -1)], 1)
    return {row.tobytes() for row in np.ascontiguousarray(rows, np.float32)}


@pytest.mark.parametrize("carry", [True, False])
def test_appearance_is_carried_after_the_first_step(carry):
    """With `carry_appearance` (the default) the second step adds and updates geometry only: every
    Gaussian after +2 has an appearance that some Gaussian had after +1. Without it the model's
    appearance changes apply again, and new appearances appear."""
    cloud = _cloud(48, seed=5)
    first, second = refine_steps(cloud, steps=2, budget=1.0, model=_model(exist_logit=4.0), seed=2,
                                 carry_appearance=carry)
    assert len(second.cloud) > len(first.cloud)  # the second step did add Gaussians
    assert (_appearances(second.cloud) <= _appearances(first.cloud)) == carry


def test_cli_refines_a_stage_of_a_longer_run_with_the_capture_cameras(tmp_path, capsys):
    """`gvae refine RUN/stage_1.ply out.ply --lineage RUN/lineage.npz --cameras transforms.json` on
    a run that went on to stage 2."""
    model_dir = tmp_path / "model"
    save_model(_model(exist_logit=30.0), model_dir)
    lin = _three_stage_lineage()
    run = tmp_path / "run"
    run.mkdir()
    lin.save(run / "lineage.npz")
    write_ply(lin.stage_cloud(1), run / "stage_1.ply")
    cams = [Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 1.5), (0, 0, 0), width=80, height=60)
            for a in np.linspace(0, 6, 6)]
    frames = [{"file_path": f"view_{i}", "transform_matrix": c.to_blender_c2w().tolist()} for i, c in enumerate(cams)]
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": cams[0].fov_x, "w": 80, "h": 60,
                                                          "frames": frames}))
    out = tmp_path / "out.ply"
    base = ["refine", str(run / "stage_1.ply"), str(out), "--lineage", str(run / "lineage.npz"), "--model",
            str(model_dir), "--budget", "4", "--fidelity", "off"]
    assert gvae(base + ["--cameras", str(tmp_path / "transforms.json"), "--views", "3"]) == 0
    text = capsys.readouterr().out
    assert "IN.ply is stage 1" in text and "6 capture cameras" in text and "4 selected" in text
    assert len(read_ply(out)) > 16
    assert gvae(base + ["--stage", "2"]) == 2
    assert "not alive at the lineage's stage 2" in capsys.readouterr().err
    assert gvae(base + ["--cameras", str(tmp_path / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the detail method

def _detail_model(seed=0):
    """A detail model with random weights (an untrained one changes nothing)."""
    torch.manual_seed(seed)
    model = DetailModel(DetailConfig(hidden=16))
    with torch.no_grad():
        for layer in (model.axis[-1], model.rest[-1]):
            layer.weight.normal_(0, 0.5)
            layer.bias.normal_(0, 0.2)
    return model


def _rated(cloud):
    return with_dilation_3d(cloud, [Camera.look_at((0, -4, 1), width=48, height=48)])


def test_detail_refine_keeps_the_training_picture_and_adds_nothing():
    cloud = _rated(_cloud(80, degree=1))
    r = refine(cloud, model=_detail_model(), steps=2)
    assert len(r.cloud) == len(cloud) and len(r.added) == 0 and len(r.selected) == len(cloud)
    for name in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
        np.testing.assert_array_equal(getattr(r.cloud, name), getattr(cloud, name))
    changes = octave_fields(r.cloud)
    assert set(changes) == {"scales", "opacities"} and np.abs(changes["scales"]).max() > 0
    assert np.all(r.cloud.extra[LIMIT_KEY] == 2.0)
    train_cam = Camera.look_at((0, -4, 1), width=48, height=48)
    assert torch.equal(render(cloud, train_cam).image, render(r.cloud, train_cam).image)
    twice = Camera.look_at((0, -4, 1), width=96, height=96)
    assert not torch.allclose(render(cloud, twice).image, render(r.cloud, twice).image, atol=1e-3)
    assert "octave" in r.summary()


def test_detail_refine_leaves_a_cloud_trained_with_the_3d_filter_as_it_is():
    """The detail model lowered PSNR at 2x on a Mip-Splatting-trained cloud: such a cloud is
    returned unchanged, and the summary says why."""
    cloud = _cloud(30)
    cloud.extra["filter_3D"] = np.full((30, 1), 0.01, np.float32)
    r = refine(cloud, model=_detail_model())
    assert len(r.selected) == 0 and not octave_fields(r.cloud)
    np.testing.assert_array_equal(r.cloud.scales, cloud.scales)
    assert "filter_3D" in r.summary() and "nothing was changed" in r.summary()


def test_detail_refine_changes_only_the_budget_and_says_where_the_rate_came_from():
    cloud = _cloud(80, degree=0)  # no anti-aliasing size: the rate is assumed from placed views
    r = refine(cloud, model=_detail_model(1), budget=0.25, scores=_scores(80))
    changed = np.flatnonzero(np.abs(octave_fields(r.cloud)["scales"]).sum(1) > 0)
    np.testing.assert_array_equal(changed, np.sort(r.selected))
    assert len(r.selected) == 20 and "assumed" in r.notes["training rate"]
    assert "gvae_dilation_3D" in r.cloud.extra
    with pytest.raises(ValueError, match="cannot refine"):
        refine(cloud, model=_detail_model(), method="vae")


def test_detail_refine_with_the_check_puts_back_nothing_at_the_training_rate():
    cloud = _rated(_cloud(60, degree=1))
    r = checked_refine(cloud, model=_detail_model(2))
    assert len(r.reverted) == 0


def test_detail_refine_replaces_the_changes_of_a_refined_cloud():
    cloud = _rated(_cloud(40))
    once = refine(cloud, model=_detail_model(3))
    twice = refine(once.cloud, model=_detail_model(3))
    for name, change in octave_fields(once.cloud).items():
        np.testing.assert_array_equal(octave_fields(twice.cloud)[name], change)


def test_cli_refine_with_the_detail_model(tmp_path, capsys):
    save_detail(_detail_model(4), tmp_path / "detail")
    write_ply(_rated(_cloud(n=50)), tmp_path / "in.ply")
    args = ["--model", str(tmp_path / "detail"), "--fidelity", "off"]
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "out.ply"), *args]) == 0
    out = read_ply(tmp_path / "out.ply")
    assert len(out) == 50 and LIMIT_KEY in out.extra and "octave" in capsys.readouterr().out
    # a plain PLY for other tools, drawn as the refined cloud is at 2x; .spz keeps no extras: baked at 2^steps
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "baked.ply"), "--bake", "2", *args]) == 0
    baked = read_ply(tmp_path / "baked.ply")
    assert LIMIT_KEY not in baked.extra and not np.array_equal(baked.scales, out.scales)
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "out.spz"), *args]) == 0
    assert "baked for 2x" in capsys.readouterr().out and len(read_splat_file(tmp_path / "out.spz")) == 50
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "out.compressed.ply"), *args]) == 0
    assert "baked for 2x" in capsys.readouterr().out
    assert gvae(["refine", str(tmp_path / "in.ply"), str(tmp_path / "x.ply"), "--bake", "0", *args]) == 2
    assert not (tmp_path / "x.ply").exists()
