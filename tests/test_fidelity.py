"""The fidelity check of refine: views at the training sampling rate, per-lineage colour change
(against a per-lineage, per-pixel reference), putting lineages back, and its effect in refine."""

import math

import numpy as np
import pytest
import torch

from gvae_core import Camera, GaussianCloud
from gvae_core.antialias import DILATION_KEY, FILTER_KEY, with_dilation_3d, with_filter_3d
from gvae_core.fidelity import changed_rows, lineage_changes, revert_lineages, training_rate_views
from gvae_core.refinement import FidelityCheck, refine
from gvae_core.octaves import with_octaves
from gvae_core.rendering import RenderSettings, render
from gvae_core.vae import GaussianVAE


def _cloud(n=24, seed=0) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    return GaussianCloud(means=rng.uniform(-0.8, 0.8, (n, 3)).astype(np.float32),
                         scales=np.full((n, 3), math.log(0.08), np.float32),
                         quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                         opacities=np.full(n, 2.0, np.float32),
                         sh_dc=rng.normal(0, 1.0, (n, 3)).astype(np.float32),
                         sh_rest=np.zeros((n, 0, 3), np.float32))


def _cameras(height: int) -> list[Camera]:
    return [Camera.look_at((4 * math.cos(a), 4 * math.sin(a), 1.0), (0, 0, 0), width=height, height=height,
                           fov_x=math.radians(40.0)) for a in (0.3, 2.0, 4.0)]


@pytest.mark.parametrize("add", [with_dilation_3d, with_filter_3d])
def test_views_at_the_training_sampling_rate(add):
    """Trained from one camera at 40 px, seen from it at 160 px: back to 40 px. Trained from three,
    each Gaussian's rate is the highest of the three (a nearer camera), so each view comes back a
    little above 40 px."""
    for k in range(3):
        one = add(_cloud(), _cameras(40)[k:k + 1])
        assert {DILATION_KEY, FILTER_KEY} & set(one.extra)
        assert training_rate_views(one, _cameras(160)[k:k + 1])[0].height == 40
        assert training_rate_views(one, _cameras(160)[k:k + 1], max_height=30)[0].height == 30
    heights = [v.height for v in training_rate_views(add(_cloud(), _cameras(40)), _cameras(160))]
    assert all(40 <= h <= 48 for h in heights), heights
    assert [v.height for v in training_rate_views(_cloud(), _cameras(160))] == [160, 160, 160]  # no size: as given


def test_the_check_reads_the_training_rate_from_the_capture_cameras():
    """A cloud without a stored size, refined with its capture's cameras (512 px, scored at 256 px):
    the check renders at the cameras' own 512 px, the rate the cloud was trained at; with a size,
    the size decides; without either, the scoring views as they are."""
    cams = _cameras(512)
    plain = _cloud()
    check = FidelityCheck.around(plain, cams, 0.01)  # each Gaussian's rate: the nearest camera's
    assert len(check.cameras) == 3 and all(512 <= c.height <= 600 for c in check.cameras), check.cameras
    sized = with_dilation_3d(_cloud(), _cameras(64))
    assert all(64 <= c.height <= 75 for c in FidelityCheck.around(sized, cams, 0.01).cameras)
    assert {c.height for c in FidelityCheck.around(plain, None, 0.01, {"resolution": 48}).cameras} == {48}


def _reference_changes(before, after, roots, added, added_roots, cameras, window=3, settings=None):
    """Per lineage, per camera, per point: the window mean of the per-pixel change, in loops."""
    out = np.zeros(len(roots))
    for cam in cameras:
        a, b = (render(c, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1).numpy()
                .astype(np.float64) for c in (before, after))
        diff = np.abs(b - a).mean(-1)
        h, w = diff.shape
        for i, root in enumerate(roots):
            points = [before.means[root], after.means[root]] + [after.means[r] for r, q in zip(added, added_roots)
                                                                 if q == root]
            for p in points:
                (x, y), z = (v[0] for v in cam.project(np.asarray(p)[None]))
                if not (np.isfinite(x) and z > 0.01 and 0 <= x < w and 0 <= y < h):
                    continue
                r, c = int(math.floor(y)), int(math.floor(x))
                box = diff[max(r - window // 2, 0):r + window // 2 + 1, max(c - window // 2, 0):c + window // 2 + 1]
                out[i] = max(out[i], box.mean())
    return out


def test_lineage_changes_and_putting_lineages_back():
    before = _cloud()
    roots = np.array([3, 5, 7, 9])
    # Root 3 moves, root 5 gets a bright child far away, root 7 a child on top of itself with no
    # opacity to speak of, root 9 is untouched.
    after = before.select(np.arange(len(before)))
    after.means[3] += np.float32([0.3, 0.0, 0.2])
    kids = before.select(np.array([5, 7]))
    kids.means[0] = np.float32([0.0, 0.0, 0.9])
    kids.sh_dc[0] = np.float32([3.0, -3.0, 3.0])
    kids.opacities[1] = np.float32(-12.0)
    after = GaussianCloud.concat([after, kids])
    added, added_roots = np.array([24, 25]), np.array([5, 7])
    cams = _cameras(48)
    change = lineage_changes(before, after, roots, added, added_roots, cams)
    np.testing.assert_allclose(change, _reference_changes(before, after, roots, added, added_roots, cams),
                               atol=1e-6)
    assert change[0] > 0.05 and change[1] > 0.05 and change[2] < 1e-3 and change[3] == pytest.approx(0.0, abs=1e-6)

    cloud, kept = revert_lineages(before, after, len(before), added_roots, roots[change > 0.01])
    assert kept.tolist() == [False, True] and len(cloud) == len(before) + 1
    np.testing.assert_array_equal(cloud.means[:24], before.means)
    np.testing.assert_array_equal(cloud.opacities[24], after.opacities[25])


def test_lineage_changes_when_every_row_changes():
    """The detail method changes every row and moves none: the refined cloud is drawn afresh, each
    centre sampled once, and each lineage's change is the reference's; one moved root and a child
    are sampled at their own places."""
    before = _cloud(40, seed=3)
    after = before.select(np.arange(len(before)))
    after.scales[:] += np.where(np.arange(len(before)) % 2 == 0, 0.25, -0.2).astype(np.float32)[:, None]
    after.opacities[::4] -= np.float32(3.0)
    after.means[11] += np.float32([0.0, 0.3, 0.0])
    kid = before.select(np.array([20]))
    kid.means[0] = np.float32([0.1, -0.6, 0.5])
    after = GaussianCloud.concat([after, kid])
    roots, added, added_roots = np.arange(len(before)), np.array([40]), np.array([20])
    assert len(changed_rows(before, after)) == len(after)
    cams = _cameras(48)
    change = lineage_changes(before, after, roots, added, added_roots, cams)
    np.testing.assert_allclose(change, _reference_changes(before, after, roots, added, added_roots, cams),
                               atol=1e-6)
    assert (change > 1e-3).mean() > 0.5


def test_views_where_no_change_per_octave_shows_are_not_drawn():
    """Changes per octave only (what the detail method makes): through a camera at or below the
    training rate every row draws as it was, so the check draws nothing there and finds no change;
    through one at twice the rate the changes show, and the check is the per-pixel reference's."""
    before = with_dilation_3d(_cloud(30, seed=4), _cameras(48))
    changes = {"scales": np.full((30, 3), 0.4, np.float32), "opacities": np.full(30, -1.5, np.float32)}
    after = with_octaves(before, changes, limit=1.0)
    roots, none = np.arange(30), np.zeros(0, np.int64)
    low, high = _cameras(40), _cameras(96)
    frames = [None] * len(low)
    assert (lineage_changes(before, after, roots, none, none, low, frames=frames) == 0).all()
    assert frames == [None] * len(low)  # nothing drawn
    settings = RenderSettings(antialias="matched")
    change = lineage_changes(before, after, roots, none, none, high, settings=settings, frames=frames)
    assert all(f is not None for f in frames) and (change > 1e-3).mean() > 0.5
    np.testing.assert_allclose(change, _reference_changes(before, after, roots, none, none, high, settings=settings),
                               atol=1e-6)


def test_changed_rows_are_the_rows_that_draw_differently():
    before = with_dilation_3d(_cloud(), _cameras(48))
    after = GaussianCloud.concat([before, before.select(np.array([2]))])
    assert changed_rows(before, after).tolist() == [24]
    after.quats[4, 1] = 0.5
    after.extra[DILATION_KEY][9] *= 2.0
    after.extra["gvae_id"] = np.arange(len(after))  # not drawn: not a change
    assert changed_rows(before, after).tolist() == [4, 9, 24]
    assert len(changed_rows(_cloud(), before)) == len(before)  # a drawn size appeared: every row
    with pytest.raises(ValueError, match="fewer rows"):
        changed_rows(after, before)


def _stand_in(exist_logit=30.0) -> GaussianVAE:
    model = GaussianVAE.create(seed=0)
    g = model.geometry
    width = g.state_dim + 1 + g.spread_dim
    with torch.no_grad():
        g.decoder[-1].weight[g.state_dim::width] = 0.0
        g.decoder[-1].bias[g.state_dim::width] = exist_logit
    return model


def test_refine_puts_back_what_changes_the_training_picture():
    """A random stand-in model changes the picture wherever it works: with tolerance 0 every lineage
    is put back (the input, unchanged), with a tolerance no change reaches everything is kept, and
    the default keeps a part in between; each result is a consistent refine result."""
    cloud = with_dilation_3d(_cloud(n=40), _cameras(48))
    model = _stand_in()
    scores = np.linspace(0, 1, 40).astype(np.float32)
    free = refine(cloud, budget=10, model=model, scores=scores, cameras=_cameras(48), fidelity=None)
    none = refine(cloud, budget=10, model=model, scores=scores, cameras=_cameras(48), fidelity=0.0)
    every = refine(cloud, budget=10, model=model, scores=scores, cameras=_cameras(48), fidelity=2.0)
    assert len(free.added) > 0 and len(free.reverted) == 0
    assert len(none.added) == 0 and len(none.reverted) == 10 and "10 of them put back" in none.summary()
    for name in ("means", "scales", "quats", "opacities", "sh_dc"):
        np.testing.assert_array_equal(getattr(none.cloud, name), getattr(cloud, name))
        np.testing.assert_array_equal(getattr(every.cloud, name), getattr(free.cloud, name))
    assert len(every.reverted) == 0 and "fidelity" in every.timings
    with pytest.raises(ValueError, match="fidelity"):
        refine(cloud, budget=10, model=model, scores=scores, fidelity=-0.1)
