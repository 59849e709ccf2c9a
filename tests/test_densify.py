"""Density control: the split rule, the optimiser bookkeeping of structural edits, the reference
strategy's decisions and its schedule's hooks (no renderer)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from gvae_core import quaternions
from gvae_core.cloud import GaussianCloud
from gvae_core.densify import split_children
from gvae_core.train import TrainConfig
from gvae_core.train.model import GaussianModel
from gvae_core.train.strategy import DensifyState, DensifyStrategy


def cloud_of(n, rng, log_scale=-3.0, degree=1):
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    return GaussianCloud(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        scales=np.full((n, 3), log_scale, np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        opacities=np.zeros(n, np.float32),
        sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
        sh_rest=rng.normal(size=(n, k, 3)).astype(np.float32),
    )


def test_split_rule_is_the_same_for_numpy_and_torch():
    rng = np.random.default_rng(7)
    means, ls = rng.normal(size=(20, 3)), rng.normal(-3, 1, (20, 3))
    rot = quaternions.to_rotmat(quaternions.normalize(rng.normal(size=(20, 4))))
    normals = rng.normal(size=(20, 3))
    m_np, ls_np = split_children(means, ls, rot, normals)
    m_t, ls_t = split_children(*(torch.from_numpy(a) for a in (means, ls, rot, normals)))
    np.testing.assert_allclose(m_t.numpy(), m_np, rtol=1e-12)
    np.testing.assert_allclose(ls_np, ls - math.log(1.6), rtol=1e-12)
    np.testing.assert_allclose(ls_t.numpy(), ls_np, rtol=1e-12)
    # offsets are the normals mapped through the parent's axes and standard deviations
    local = np.einsum("nji,nj->ni", rot, m_np - means) / np.exp(ls)
    np.testing.assert_allclose(local, normals, atol=1e-9)
    _, ls4 = split_children(means, ls, rot, normals, n_children=4)
    np.testing.assert_allclose(ls4, ls - math.log(3.2), rtol=1e-12)


def model_with_state(cloud, config=None, extent=1.0, parents=None):
    """A model whose Adam moments are non-zero (one step with random gradients)."""
    n = len(cloud)
    ids = np.arange(n)
    parents = np.full(n, -1) if parents is None else parents
    m = GaussianModel(cloud, ids, parents, (config or TrainConfig()).learning_rates(extent), extent, next_id=n)
    gen = torch.Generator().manual_seed(0)
    for p in m.params.values():
        p.grad = torch.randn(p.shape, generator=gen)
    m.optimizer.step()
    m.optimizer.zero_grad(set_to_none=True)
    return m


def moments(m, name):
    return m.optimizer.state[m.params[name]]["exp_avg"]


def test_clone_copies_parameters_ids_parents_and_extends_adam_state():
    rng = np.random.default_rng(0)
    m = model_with_state(cloud_of(6, rng), parents=np.array([10, 11, 12, 13, 14, 15]))
    before = {k: v.detach().clone() for k, v in m.params.items()}
    mom = moments(m, "means").clone()
    mask = torch.tensor([False, True, False, True, False, False])
    assert m.clone(mask) == 2
    assert len(m) == 8 and m.ids.tolist() == [0, 1, 2, 3, 4, 5, 6, 7] and m.next_id == 8
    assert m.parents.tolist() == [10, 11, 12, 13, 14, 15, 11, 13]  # children inherit the anchor
    for k, v in m.params.items():
        assert torch.equal(v.detach()[:6], before[k]) and torch.equal(v.detach()[6:], before[k][[1, 3]])
        st = m.optimizer.state[v]
        assert st["exp_avg"].shape == v.shape and st["exp_avg_sq"].shape == v.shape
        assert torch.count_nonzero(st["exp_avg"][6:]) == 0
    assert torch.equal(moments(m, "means")[:6], mom)
    # the optimiser updates the new tensors (they are registered in it)
    for p in m.params.values():
        p.grad = torch.ones_like(p)
    old = m.params["means"].detach().clone()
    m.optimizer.step()
    assert (m.params["means"].detach() != old).all()


def test_split_replaces_parent_by_two_smaller_children_sampled_from_it():
    rng = np.random.default_rng(1)
    m = model_with_state(cloud_of(5, rng))
    scales = m.params["scales"].detach().clone()
    mom_rest = moments(m, "sh_dc")[[0, 2, 3, 4]].clone()
    assert m.split(torch.tensor([False, True, False, False, False]), torch.Generator().manual_seed(0)) == 1
    assert m.ids.tolist() == [0, 2, 3, 4, 5, 6] and m.parents.tolist() == [-1] * 6
    assert torch.equal(moments(m, "sh_dc")[:4], mom_rest)  # survivors keep their moments
    assert torch.count_nonzero(moments(m, "sh_dc")[4:]) == 0
    np.testing.assert_allclose(m.params["scales"].detach()[4:].numpy(),
                               (scales[[1, 1]] - math.log(1.6)).numpy(), atol=1e-6)

    # positions of the children ~ N(parent mean, R S^2 R^T)
    n = 3000
    parent = cloud_of(1, rng)
    parent.scales[:] = np.log([0.5, 0.1, 0.02])
    parent.quats[:] = [0.9, 0.3, -0.2, 0.25]
    parent.means[:] = [1.0, 2.0, 3.0]
    many = parent.select(np.zeros(n, np.int64))
    m = GaussianModel(many, np.arange(n), np.arange(n) + 100, TrainConfig().learning_rates(1.0), 1.0, n)
    m.split(torch.ones(n, dtype=torch.bool), torch.Generator().manual_seed(1))
    assert len(m) == 2 * n and m.ids.min() == n and sorted(set(m.parents.tolist())) == list(range(100, 100 + n))
    kids = m.params["means"].detach().double().numpy()
    r = parent.rotation_matrices()[0].astype(np.float64)
    cov = r @ np.diag(np.exp(parent.scales[0].astype(np.float64)) ** 2) @ r.T
    np.testing.assert_allclose(kids.mean(0), parent.means[0], atol=0.03)
    np.testing.assert_allclose(np.cov(kids.T), cov, atol=0.01)
    np.testing.assert_allclose(m.params["scales"].detach().numpy(), np.tile(parent.scales - np.log(1.6), (2 * n, 1)),
                               atol=1e-6)


def test_densify_and_prune_selects_by_gradient_size_and_opacity():
    rng = np.random.default_rng(2)
    cfg = TrainConfig(max_gaussians=None)
    strategy = DensifyStrategy.for_stage(cfg, 0, None)
    c = cloud_of(6, rng)
    c.scales[:] = np.log(0.001)          # small: cloned
    c.scales[1] = np.log(0.05)           # large: split (percent_dense * extent = 0.01)
    c.scales[4] = np.log(0.5)            # larger than 0.1 * extent: pruned when prune_large
    c.opacities[3] = -8.0                # sigmoid < 0.005: pruned
    m = model_with_state(c, cfg, extent=1.0)
    state = DensifyState(torch.tensor([3e-4, 3e-4, 1e-4, 0.0, 0.0, 1e-3]) * 2, torch.full((6,), 2.0), torch.zeros(6))
    done = strategy.densify_and_prune(m, state, torch.Generator().manual_seed(0), prune_large=True,
                                      image_height=100)
    assert done == {"cloned": 2, "split": 1, "pruned": 2}
    # kept originals 0, 2, 5; clones of 0 and 5; two children of 1
    assert m.ids.tolist() == [0, 2, 5, 6, 7, 8, 9]
    assert m.parents.tolist() == [-1] * 7
    assert float(state.grad_sum.abs().sum()) == 0.0 and len(state.count) == 7  # the statistics restart
    # without prune_large the oversized one stays
    m2 = model_with_state(c, cfg, extent=1.0)
    state = DensifyState(torch.tensor([3e-4, 3e-4, 1e-4, 0.0, 0.0, 1e-3]) * 2, torch.full((6,), 2.0), torch.zeros(6))
    strategy.densify_and_prune(m2, state, torch.Generator().manual_seed(0), prune_large=False, image_height=100)
    assert 4 in m2.ids.tolist() and 3 not in m2.ids.tolist()


def test_max_gaussians_keeps_the_highest_gradients():
    rng = np.random.default_rng(3)
    cfg = TrainConfig(max_gaussians=7)
    m = model_with_state(cloud_of(5, rng, log_scale=np.log(0.001)), cfg)
    state = DensifyState(torch.tensor([5e-4, 9e-4, 3e-4, 8e-4, 1e-5]), torch.ones(5), torch.zeros(5))
    DensifyStrategy.for_stage(cfg, 0, cfg.max_gaussians).densify_and_prune(m, state, torch.Generator(),
                                                                          prune_large=False, image_height=10)
    assert len(m) == 7
    assert m.ids.tolist() == [0, 1, 2, 3, 4, 5, 6]
    assert torch.equal(m.params["means"].detach()[5:], m.params["means"].detach()[[1, 3]])


def test_reset_opacity_and_stats_in_ndc_units():
    rng = np.random.default_rng(4)
    c = cloud_of(3, rng)
    c.opacities[:] = [-6.0, 0.0, 3.0]
    m = model_with_state(c)
    m.reset_opacity(0.01)
    op = torch.sigmoid(m.params["opacities"].detach())
    assert op[0] < 0.01 and op[1:].sub(0.01).abs().max() < 1e-6
    assert torch.count_nonzero(m.optimizer.state[m.params["opacities"]]["exp_avg"]) == 0
    assert torch.count_nonzero(moments(m, "means")) > 0
    # pixel gradient (2, 4) on a 100 x 50 image is (100, 100) in NDC units
    grad = torch.tensor([[2.0, 4.0], [1.0, 1.0], [0.0, 0.0]])
    visible = torch.tensor([True, False, True])
    state = DensifyState.zeros(3, "cpu")
    state.add(grad, visible, torch.tensor([3, 0, 7], dtype=torch.int32), 100, 50)
    assert state.grad_sum.tolist() == pytest.approx([math.hypot(100, 100), 0.0, 0.0])
    assert state.count.tolist() == [1.0, 0.0, 1.0] and state.max_radii.tolist() == [3.0, 0.0, 7.0]


def test_adam_state_carries_to_a_model_of_the_same_rows():
    """What the next stage starts from: the moments and step counts of every parameter, refused
    (nothing changed) by a model whose rows do not match; the fused and the plain Adam update alike."""
    rng = np.random.default_rng(3)
    cloud = cloud_of(7, rng, degree=2)
    m = model_with_state(cloud)
    state = m.optimizer_state()
    assert set(state) >= {f"{n}.{k}" for n in ("means", "sh_rest") for k in ("exp_avg", "exp_avg_sq", "step")}
    fresh = GaussianModel(cloud, np.arange(7), np.full(7, -1), TrainConfig().learning_rates(1.0), 1.0, 7)
    assert fresh.load_optimizer_state(state)
    for name, p in fresh.params.items():
        assert torch.equal(fresh.optimizer.state[p]["exp_avg"], m.optimizer.state[m.params[name]]["exp_avg"])
    other = GaussianModel(cloud_of(6, rng, degree=2), np.arange(6), np.full(6, -1),
                          TrainConfig().learning_rates(1.0), 1.0, 6)
    assert not other.load_optimizer_state(state) and not other.optimizer.state
    assert not other.load_optimizer_state({})
    # the same steps, fused or not
    a = GaussianModel(cloud, np.arange(7), np.full(7, -1), TrainConfig().learning_rates(1.0), 1.0, 7)
    copies = [p.detach().clone().requires_grad_(True) for p in a.params.values()]
    plain = torch.optim.Adam([{"params": [q], "lr": g["lr"]} for q, g in zip(copies, a.optimizer.param_groups)],
                             eps=1e-15)
    for k in range(3):
        for p, q in zip(a.params.values(), copies):
            p.grad = torch.full_like(p, 0.5 - k)
            q.grad = torch.full_like(q, 0.5 - k)
        a.optimizer.step()
        plain.step()
    for p, q in zip(a.params.values(), copies):
        torch.testing.assert_close(p.detach(), q.detach())


class _Result:
    """What the strategy's hooks read of a render: the projected centres, visibility, radii."""

    def __init__(self, n):
        self.means2d = torch.zeros(n, 2, requires_grad=True)
        self.visible = torch.ones(n, dtype=torch.bool)
        self.radii = torch.full((n,), 3)


def test_the_strategy_owns_its_schedule_statistics_and_opacity_reset():
    """A round only every `every` steps from `start` to `stop`, none at the stage's last step; the
    statistics gather between rounds and restart after one; the opacity reset every `reset_every`
    before `stop` when the configuration has resets, never without; large ones pruned only after
    the first reset interval."""
    rng = np.random.default_rng(5)
    cfg = TrainConfig(resolutions=(10,), iterations=(3000,), max_gaussians=None, opacity_resets=True)
    strategy = DensifyStrategy.for_stage(cfg, 0, None)
    assert (strategy.start, strategy.stop, strategy.every, strategy.reset_every, strategy.last) == (50, 1500, 25,
                                                                                                       300, 3000)
    m = model_with_state(cloud_of(4, rng, log_scale=np.log(0.001)), cfg)
    m.params["opacities"].data[:] = 3.0
    state = strategy.initialize_state(m)
    camera = type("Cam", (), {"width": 20, "height": 10})()
    rounds = []
    for step in range(1, 301):
        result = _Result(len(m))
        strategy.step_pre_backward(result)
        (result.means2d * torch.tensor([1e-2, 0.0])).sum().backward()  # a gradient above the threshold
        done = strategy.step_post_backward(m, state, result, camera, step, torch.Generator().manual_seed(step))
        if done is not None:
            rounds.append(step)
    assert rounds == list(range(50, 301, 25))  # from `start`, every `every`
    assert float(state.count.max()) == 0.0  # (a round at 300 restarted them)
    assert float(torch.sigmoid(m.params["opacities"].detach()).max()) == pytest.approx(0.01)  # reset at 300
    late = dataclasses.replace(strategy, last=325)
    n = len(m)
    for step in (325, 1525):  # the stage's last step, and past `stop`: nothing
        assert late.step_post_backward(m, state, _Result(n), camera, step, torch.Generator()) is None
    off = DensifyStrategy.for_stage(dataclasses.replace(cfg, opacity_resets=False), 0, None)
    m.params["opacities"].data[:] = 3.0
    off.step_post_backward(m, off.initialize_state(m), _Result(len(m)), camera, 300, torch.Generator())
    assert float(torch.sigmoid(m.params["opacities"].detach()).min()) > 0.9  # no reset without resets
