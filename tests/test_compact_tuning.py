"""Compaction's fine-tuning judged on views it does not train on (`compaction.finetune`, with the
project's `plateau.Plateau` and the trainer's `should_stop` hook, tested in test_plateau and
test_train): the images set aside, the best state kept, the time bound, the time estimate said
before the fine-tuning starts, and the default with photos."""

import math

import numpy as np
import pytest

import gvae_core.compaction as compaction
import gvae_core.compaction.finetune as finetune
import gvae_core.train as train
from gvae_core import Camera
from gvae_core.antialias import DILATION_KEY
from gvae_core.compaction import PHOTOS_PRUNE_FROM, compact, compaction_scores, default_method, set_aside
from gvae_core.compaction.finetune import Tuning, TuningOptions, tune, tuning_config
from gvae_core.datasets import Views
from gvae_core.examples import example_cloud
from gvae_core.rendering import RenderSettings, render


def _views(cloud, n, size=24):
    cams = [Camera.look_at((3 * math.cos(a), 3 * math.sin(a), 1.5), (0, 0, 0), width=size, height=size, fov_x=1.0)
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]
    imgs = np.stack([render(cloud, c, background=(1.0, 1.0, 1.0)).image.numpy() for c in cams])
    return Views(cams, np.clip(imgs, 0, 1), np.ones(imgs.shape[:3], np.float32), [f"v{i:02d}" for i in range(n)])


def test_set_aside_takes_every_nth_by_name_and_leaves_the_rest():
    views = _views(example_cloud(50, seed=0), 17, size=8)
    views.names = [f"v{(i * 7) % 17:02d}" for i in range(17)]  # names not in capture order
    fit, aside = set_aside(views, 8)
    assert sorted(aside.names) == ["v04", "v12"] and len(fit) == 15
    assert not set(fit.names) & set(aside.names)
    for sub in (fit, aside):  # each camera and image stays with its name
        for name, cam, img in zip(sub.names, sub.cameras, sub.images):
            i = views.names.index(name)
            assert cam is views.cameras[i] and np.array_equal(img, views.images[i])
    assert set_aside(_views(example_cloud(50), 4, size=8), 8)[1] is None  # too few to set any aside


def test_tune_keeps_the_best_state_the_set_aside_views_saw(monkeypatch):
    """The fine-tuning's judge is the set-aside views' PSNR: when it only falls, the input's own
    parameters are what comes back (the anti-aliasing size recomputed); the record says so."""
    cloud = example_cloud(60, seed=2).with_sh_degree(0)
    views = _views(cloud, 4, size=16)
    values = iter([10.0, 9.0, 8.0, 7.0, 6.0])
    monkeypatch.setattr(finetune, "aside_psnr", lambda *a, **k: next(values))
    config = tuning_config(cloud, RenderSettings(), 0)
    tuning = Tuning(Views(views.cameras[:3], views.images[:3]), Views(views.cameras[3:], views.images[3:]),
                    iterations=40, rounds=1, check_every=5, patience=3)
    out, record = tune(cloud, tuning, config, seed=0)
    assert record["iterations"] == 20 and record["best_at"] == 0  # (the plateau counts from the first check)
    assert (record["psnr_before"], record["psnr_after"]) == (10.0, 10.0)
    np.testing.assert_array_equal(out.means, cloud.means)
    assert out.extra[DILATION_KEY].min() > 0
    rising = iter(range(100))  # still paying, but past its time: the first check ends it
    monkeypatch.setattr(finetune, "aside_psnr", lambda *a, **k: float(next(rising)))
    timed = Tuning(tuning.images, tuning.aside, iterations=40, rounds=1, check_every=5, seconds=0.0)
    _, record = tune(cloud, timed, config, seed=0)
    assert record["iterations"] == 5 and record["best_at"] == 5


def test_compact_with_images_sets_some_aside_and_says_what_it_will_take():
    cloud = example_cloud(120, seed=3).with_sh_degree(1)
    images = _views(cloud, 16, size=20)
    said = []
    r = compact(cloud, keep=0.5, images=images, rounds=1, iterations=30, views=2, resolution=20,
                progress=lambda f, msg: said.append(msg))
    rec = r.rounds[0]
    assert len(r.cloud) == 60 and rec["judged_on"] == "the 2 of the training images set aside"
    assert rec["psnr_after"] >= rec["psnr_before"] and 0 <= rec["best_at"] <= rec["iterations"] <= 30
    assert any("s an iteration" in m and "set-aside" in m for m in said)  # the estimate, before fine-tuning
    first = next(i for i, m in enumerate(said) if "s an iteration" in m)
    assert not any("fine-tuning 1" in m for m in said[:first])
    fixed = compact(cloud, keep=0.5, images=images, rounds=1, iterations=6, views=2, resolution=20, plateau=False)
    assert fixed.rounds[0]["iterations"] == 6 and fixed.rounds[0]["judged_on"] == "the training images"


def test_distillation_targets_are_drawn_as_the_fine_tuning_draws(monkeypatch):
    """A cloud trained the classic way carries its dilation (rendered `matched` by default); its own
    renders are drawn classic, as the fine-tuning draws (a mismatch the fine-tuning would learn)."""
    cloud = example_cloud(80, seed=4).with_sh_degree(0)
    cloud = cloud.replace(extra={DILATION_KEY: np.full(80, 0.004, np.float32)})
    modes = []
    real = finetune.own_renders

    def own_renders(src, cameras, resolution, settings, views):
        modes.append(settings.antialias)
        return real(src, cameras, resolution, settings, views)

    monkeypatch.setattr(compaction, "own_renders", own_renders)
    r = compact(cloud, keep=0.5, resolution=24, distill=4)
    assert modes == ["classic"] and len(r.rounds) == 1
    compact(cloud, keep=0.5, resolution=24, distill=4, tuning_options=TuningOptions(distill_target="auto"))
    assert modes[-1] == "auto"


def test_tuning_options_reach_the_fine_tuning(monkeypatch):
    """What a study changes (`TuningOptions`: the trainer's configuration, the averages) is passed
    down to the fine-tuning of both paths; no module global changes."""
    cloud = example_cloud(120, seed=6).with_sh_degree(0)
    images = _views(cloud, 10, size=16)
    seen = []
    real = train.fine_tune
    monkeypatch.setattr(train, "fine_tune", lambda *a, **k: seen.append((k["config"].position_lr_init,
                                                                          k["average"])) or real(*a, **k))
    options = TuningOptions(train_overrides={"position_lr_init": 3e-5}, average=None, distill_average=0.9)
    compact(cloud, keep=0.5, images=images, iterations=2, views=2, resolution=16, tuning_options=options)
    compact(cloud, keep=0.5, resolution=16, distill=2, tuning_options=options)
    compact(cloud, keep=0.5, resolution=16, distill=2)
    assert seen == [(3e-5, None), (3e-5, 0.9), (train.TrainConfig().position_lr_init, finetune.DISTILL_AVERAGE)]
    assert tuning_config(cloud, RenderSettings(), 0, {"position_lr_init": 3e-5}).position_lr_init == 3e-5
    with pytest.raises(ValueError, match="distill_target"):
        TuningOptions(distill_target="matched")


def test_with_images_the_default_is_what_the_set_aside_images_chose(monkeypatch):
    """With images and neither a score nor a removal asked for: LightGaussian's prune from
    PHOTOS_PRUNE_FROM kept, the Hessian's merge below it and without images; what is asked for
    is kept (one alone goes with the other's usual partner)."""
    photos = object()
    assert default_method(photos, 0.5, None, 100, None, None) == ("lightgaussian", "prune")
    assert default_method(photos, None, 30, 100, None, None) == ("lightgaussian", "prune")
    assert default_method(photos, 0.1, None, 100, None, None) == ("hessian", "merge")
    assert default_method(None, 0.5, None, 100, None, None) == ("hessian", "merge")
    assert default_method(photos, 0.5, None, 100, "hessian", None) == ("hessian", "merge")
    assert default_method(photos, 0.5, None, 100, None, "merge") == ("hessian", "merge")
    assert default_method(photos, "half", None, 100, None, None) == ("hessian", "merge")  # (refused later)
    cloud = example_cloud(120, seed=5).with_sh_degree(0)
    images = _views(cloud, 10, size=16)
    used = []
    real = finetune.compaction_scores
    monkeypatch.setattr(finetune, "compaction_scores",
                        lambda c, name, *a, **k: used.append(name) or real(c, name, *a, **k))
    for keep, name in ((PHOTOS_PRUNE_FROM, "lightgaussian"), (0.1, "hessian")):
        r = compact(cloud, keep=keep, images=images, iterations=2, views=2, resolution=16)
        kept = r.groups[r.groups >= 0]
        merged = len(kept) > len(np.unique(kept))  # some output row stands for two or more input rows
        assert used[-1] == name and merged == (name == "hessian") and len(r.cloud) == round(120 * keep)


def test_with_images_lightgaussian_counts_every_camera_and_the_result_is_averaged(monkeypatch):
    """With images LightGaussian's score sums its hits over every camera (set-aside ones too), not
    `views` of them (the Hessian's); the fine-tuning ends on the running average of its iterates
    (AVERAGE), the distillation as DISTILL_AVERAGE says."""
    cloud = example_cloud(120, seed=6).with_sh_degree(0)
    images = _views(cloud, 10, size=16)
    averages = []
    real = train.fine_tune
    monkeypatch.setattr(train, "fine_tune", lambda *a, **k: averages.append(k["average"]) or real(*a, **k))
    r = compact(cloud, keep=0.5, images=images, iterations=2, views=2, resolution=16)
    np.testing.assert_allclose(r.scores, compaction_scores(cloud, "lightgaussian", images.cameras))
    assert not np.allclose(r.scores, compaction_scores(cloud, "lightgaussian", images.cameras[:2]))
    compact(cloud, keep=0.5, resolution=16, distill=2)
    assert averages == [finetune.AVERAGE, finetune.DISTILL_AVERAGE] and 0 < finetune.AVERAGE < 1


def test_with_images_the_fine_tuning_is_shorter_where_the_prune_is_the_default(monkeypatch):
    """At most PRUNE_FROM_ITERATIONS a round keeping PHOTOS_PRUNE_FROM or more, DEFAULT_ITERATIONS
    below (what the images set aside preferred on the plush); `iterations` given wins."""
    assert compaction.default_iterations(0.5, None, 100) == compaction.PRUNE_FROM_ITERATIONS < \
        compaction.DEFAULT_ITERATIONS == compaction.default_iterations(None, 10, 100)
    monkeypatch.setattr(compaction, "PRUNE_FROM_ITERATIONS", 3)
    monkeypatch.setattr(compaction, "DEFAULT_ITERATIONS", 2)
    cloud = example_cloud(120, seed=5).with_sh_degree(0)
    images = _views(cloud, 10, size=16)
    for keep, ran in ((0.5, 3), (0.1, 2)):
        r = compact(cloud, keep=keep, images=images, plateau=False, views=2, resolution=16)
        assert r.rounds[0]["iterations"] == ran
    assert compact(cloud, keep=0.5, images=images, iterations=1, plateau=False, views=2,
                   resolution=16).rounds[0]["iterations"] == 1


def test_a_fine_tuning_stopped_by_its_cap_while_still_improving_is_said():
    """Judged by a plateau, ran every iteration and liked the last best: a warning naming how to allow
    more; stopped by the plateau (best earlier) or run without one (no checks): none."""
    from gvae_core.compaction.finetune import still_gaining  # noqa: PLC0415

    capped = {"iterations": 1000, "best_at": 1000, "checks": [(100, 30.0), (1000, 31.0)]}
    said = still_gaining([{**capped, "best_at": 600}, capped], "--iterations (more than 1,000)")
    assert said == ["round 2 of the fine-tuning was still improving at its last iteration (1,000): allow more with "
                    "--iterations (more than 1,000)"]
    assert still_gaining([{**capped, "checks": []}], "--distill") == []
