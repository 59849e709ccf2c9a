"""Lineage VAEs: flow prior, KL, matching, training, persistence, degenerate lineages."""

import json
import math

import numpy as np
import pytest
import torch

from gvae_core import GaussianCloud
from gvae_core.lineage import Lineage, Transition
from gvae_core.quaternions import from_rotmat as rotmat_to_quat
from gvae_core.quaternions import multiply as quat_multiply
from gvae_core.quaternions import to_rotmat as quat_to_rotmat
from gvae_core.vae import (EncoderBlock, FitConfig, FlowPrior, GaussianVAE, LineageVAE, ParentFrame,
                           VAEConfig, copy_parent_baseline, cyclic_beta, default_model_dir, evaluate, fit,
                           lineage_transitions, load_model, match_slots, match_slots_reference, save_model,
                           synthetic_transitions)


def _perturbed_flow(dim=6, layers=4, seed=0) -> FlowPrior:
    torch.manual_seed(seed)
    flow = FlowPrior(dim, layers, 32)
    with torch.no_grad():
        for p in flow.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return flow.double()


def test_flow_inverse_is_exact():
    flow = _perturbed_flow()
    z = torch.randn(256, 6, dtype=torch.float64) * 2
    eps, ld_inv = flow.inverse(z)
    z2, ld_fwd = flow.forward(eps)
    assert (eps - z).abs().max() > 1e-2  # the flow is not the identity
    assert torch.allclose(z2, z, atol=1e-5)
    assert torch.allclose(ld_inv + ld_fwd, torch.zeros(256, dtype=torch.float64), atol=1e-5)
    # float32, as the model runs (latent size and weights of the shipped model's scale)
    torch.manual_seed(0)
    flow32 = FlowPrior(16, 4, 64)
    with torch.no_grad():
        for p in flow32.parameters():
            p.add_(0.1 * torch.randn_like(p))
    z32 = torch.randn(4096, 16)
    eps32 = flow32.inverse(z32)[0]
    assert (eps32 - z32).abs().max() > 0.5
    assert (flow32.forward(eps32)[0] - z32).abs().max() < 1e-5


def test_flow_log_prob_is_change_of_variables():
    flow = _perturbed_flow(dim=4, layers=3, seed=1)
    z = torch.randn(5, 4, dtype=torch.float64)
    for zi in z:
        jac = torch.autograd.functional.jacobian(lambda x: flow.inverse(x[None])[0][0], zi)
        eps = flow.inverse(zi[None])[0][0]
        expected = -0.5 * (eps @ eps).detach() - 2 * math.log(2 * math.pi) + torch.linalg.slogdet(jac)[1]
        assert float(flow.log_prob(zi[None])[0].detach()) == pytest.approx(float(expected), abs=1e-8)


def test_monte_carlo_kl_matches_closed_form_for_identity_flow():
    model = LineageVAE(VAEConfig(kind="geometry", latent=3)).double()  # zero-initialised flow = N(0, I)
    mu = torch.tensor([[0.5, -1.0, 2.0]], dtype=torch.float64).expand(40000, 3)
    logvar = torch.tensor([[0.2, -0.7, 0.0]], dtype=torch.float64).expand(40000, 3)
    gen = torch.Generator().manual_seed(0)
    z = mu + (0.5 * logvar).exp() * torch.randn(mu.shape, generator=gen, dtype=torch.float64)
    mc = model.kl(mu, logvar, z).mean().detach()
    exact = 0.5 * (mu[0] ** 2 + logvar[0].exp() - 1 - logvar[0]).sum()
    assert float(mc) == pytest.approx(float(exact), abs=0.05)


def test_cyclic_annealing():
    assert [cyclic_beta(t, 0.25, 8) for t in range(10)] == [0, 0.25, 0.5, 0.75, 1, 1, 1, 1, 0, 0.25]


def test_matching_is_optimal():
    rng = np.random.default_rng(0)
    cost = rng.uniform(size=(300, 4, 3))
    mask = rng.uniform(size=(300, 3)) < 0.7
    fast = match_slots(torch.from_numpy(cost), torch.from_numpy(mask)).numpy()
    ref = match_slots_reference(cost, mask)
    total = lambda a: (np.take_along_axis(cost, a[:, None, :], 1)[:, 0] * mask).sum(1)  # noqa: E731
    np.testing.assert_allclose(total(fast), total(ref), atol=1e-12)
    for i in range(len(mask)):  # a slot is used by at most one child
        used = fast[i][mask[i]]
        assert len(set(used.tolist())) == len(used)


def _degenerate_lineages():
    """One node; all zero; far from the origin; extreme log-scales and opacities; non-finite."""
    g = np.zeros((6, 3, 11), np.float32)
    a = np.zeros((6, 3, 50), np.float32)
    g[1, :, 0:3] = 1e7
    g[2, :, 7:10] = [-40.0, 30.0, 0.0]
    g[2, :, 3] = 1.0
    a[2, :, 48] = 1e4
    g[3, :, 0:3] = np.nan
    a[3, :, 45:48] = np.inf
    g[4] = np.random.default_rng(0).normal(0, 1e3, (3, 11))
    a[5, :, :] = -1e9
    return g, a


def test_kl_and_predictions_finite_on_degenerate_lineages():
    model = GaussianVAE.create(seed=0)
    g, a = _degenerate_lineages()
    for t in (1, 3):  # one-node lineages and three-node ones
        cg, ca, p, flags = model.predict(g[:, -t:], a[:, -t:])
        assert torch.isfinite(cg).all() and torch.isfinite(ca).all() and torch.isfinite(p).all()
        assert flags.dtype == torch.bool and flags.shape == (len(g),)
        assert torch.allclose(cg[..., 3:7].norm(dim=-1), torch.ones(()), atol=1e-5)
        assert ((p >= 0) & (p <= 1)).all()
        for vae, nodes in ((model.geometry, g), (model.appearance, a)):
            pred, mu, logvar, z = vae(torch.from_numpy(nodes[:, -t:]))
            assert torch.isfinite(vae.kl(mu, logvar, z)).all()


def test_loss_decreases_on_synthetic_lineages():
    data = synthetic_transitions(96, 3, seed=1)
    model = GaussianVAE.create(seed=0)
    before = evaluate(model, data)
    result = fit(data, FitConfig(steps=40, batch=48, lr=3e-3, seed=0), model=model)
    after = evaluate(result.model, data)
    assert all(math.isfinite(r["total"]) for r in result.history)
    assert after["total"] < 0.7 * before["total"]
    assert after["mse"] < before["mse"] and after["state"] < before["state"]


def test_save_load_round_trip(tmp_path):
    model = GaussianVAE.create(seed=3)
    model.meta = {"note": "test"}
    save_model(model, tmp_path / "m")
    loaded = load_model(tmp_path / "m")
    g, a = _degenerate_lineages()
    flags = np.arange(len(g)) % 2 == 0
    torch.testing.assert_close(model.predict(g, a, flags, sample=False)[0],
                               loaded.predict(g, a, flags, sample=False)[0])
    assert loaded.meta == {"note": "test"}
    assert json.loads((tmp_path / "m" / "config.json").read_text())["geometry"]["kind"] == "geometry"


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        load_model(tmp_path)
    save_model(GaussianVAE.create(), tmp_path / "m")
    (tmp_path / "m" / "appearance.safetensors").write_bytes(b"not weights")
    with pytest.raises(ValueError, match="appearance.safetensors"):
        load_model(tmp_path / "m")


def test_transitions_from_a_real_lineage_train():
    rng = np.random.default_rng(0)

    def cloud(n):
        return GaussianCloud(means=rng.normal(size=(n, 3)).astype(np.float32),
                             scales=np.full((n, 3), -3.0, np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
                             opacities=np.zeros(n, np.float32), sh_dc=rng.normal(size=(n, 3)).astype(np.float32),
                             sh_rest=np.zeros((n, 3, 3), np.float32))

    lin = Lineage(np.zeros(3), 1.0)
    lin.add_stage(cloud(20), np.arange(20), np.full(20, -1), 50)
    lin.add_stage(cloud(30), np.arange(30), np.r_[np.arange(20), np.arange(10)], 75)
    data = lineage_transitions(lin, max_children=4)
    assert len(data) == 1 and data[0].history_geometry.shape == (20, 1, 11)
    assert data[0].child_mask.sum() == 30
    assert isinstance(data[0], Transition)
    result = fit(data, FitConfig(steps=3, batch=16))
    assert all(math.isfinite(r["total"]) for r in result.history)


def test_bundled_model_loads_and_is_small():
    directory = default_model_dir()
    if not (directory / "config.json").is_file():
        pytest.skip(f"no bundled model in {directory} (run `make train-model`)")
    model = load_model(directory)
    total = sum(p.stat().st_size for p in directory.iterdir() if p.is_file())
    assert total <= 2 * 1024 * 1024
    g, a = _degenerate_lineages()
    assert torch.isfinite(model.predict(g, a)[0]).all()


def test_attention_matches_the_fused_reference_kernel():
    """The block's written-out attention (and its one-node shortcut) against torch's fused
    scaled_dot_product_attention."""
    torch.manual_seed(0)
    block = EncoderBlock(16, 4, 32)
    for t in (1, 2, 5):
        h = torch.randn(7, t, 16)
        m, _, d = h.shape
        q, k, v = (x.view(m, t, 4, 4).transpose(1, 2) for x in block.qkv(block.norm1(h)).chunk(3, -1))
        full = torch.nn.functional.scaled_dot_product_attention(q, k, v)
        x = h + block.out(full.transpose(1, 2).reshape(m, t, d))
        torch.testing.assert_close(block(h), x + block.mlp(block.norm2(x)))
    # and a lineage's encoding does not depend on batch neighbours
    h3 = torch.randn(5, 3, 16)
    torch.testing.assert_close(block(h3)[:2], block(h3[:2]))


def test_copy_parent_baseline_is_zero_for_identical_children():
    t = synthetic_transitions(32, 2, seed=0)[0]
    t.child_geometry[:] = t.history_geometry[:, -1:]
    t.child_appearance[:] = t.history_appearance[:, -1:]
    t.child_mask[:] = [True, False]
    base = copy_parent_baseline([t])
    assert base["position_rmse"] == pytest.approx(0.0, abs=1e-6)
    assert base["mse"] == pytest.approx(0.0, abs=1e-10) and base["count_error"] == 0.0
    t.child_mask[:] = True
    assert copy_parent_baseline([t])["count_error"] == 1.0


def test_existence_source_follows_meta():
    model = GaussianVAE.create(seed=2)
    g, a = _degenerate_lineages()
    flags = np.ones(len(g), bool)
    cg, ca, p, _ = model.predict(g, a, flags, sample=False)
    torch.testing.assert_close(p, cg[..., 10])
    model.meta["existence"] = "appearance"
    torch.testing.assert_close(model.predict(g, a, flags, sample=False)[2], ca[..., 49])
    model.meta["existence"] = "combined"
    torch.testing.assert_close(model.predict(g, a, flags, sample=False)[2], 0.5 * (cg[..., 10] + ca[..., 49]))


def test_densify_flag_conditions_the_slots():
    data = synthetic_transitions(64, 3, seed=4)
    model = fit(data, FitConfig(steps=60, batch=64, lr=3e-3, seed=0)).model
    g, a = data[1].history_geometry, data[1].history_appearance
    _, _, p_no, f_no = model.predict(g, a, np.zeros(len(g), bool), sample=False)
    _, _, p_yes, f_yes = model.predict(g, a, np.ones(len(g), bool), sample=False)
    assert not f_no.any() and f_yes.all()
    # densifying Gaussians are predicted to have more children than the others
    assert float(p_yes.sum(1).mean()) > float(p_no.sum(1).mean()) + 0.3
    # without flags the model draws them from its own probability (seeded)
    f1 = model.predict(g, a, generator=torch.Generator().manual_seed(1))[3]
    f2 = model.predict(g, a, generator=torch.Generator().manual_seed(1))[3]
    assert torch.equal(f1, f2) and 0 < int(f1.sum()) < len(g)
    with pytest.raises(ValueError, match="flags"):
        model.predict(g, a, np.ones(3, bool))


def test_geometry_model_is_rotation_equivariant():
    model = GaussianVAE.create(seed=5)
    data = synthetic_transitions(16, 3, seed=2)[1]
    g = torch.from_numpy(data.history_geometry.copy())
    q_rot = torch.tensor(rotmat_to_quat(quat_to_rotmat(np.array([0.3, -0.5, 0.7, 0.2]) / np.linalg.norm(
        [0.3, -0.5, 0.7, 0.2]))), dtype=torch.float32).reshape(4)
    rot = torch.from_numpy(quat_to_rotmat(q_rot.double().numpy())).float()
    turned = g.clone()
    turned[..., 0:3] = g[..., 0:3] @ rot.T
    turned[..., 3:7] = quat_multiply(q_rot.expand_as(g[..., 3:7]), g[..., 3:7])
    flags = torch.ones(len(g), dtype=torch.bool)
    a = model.geometry(g, flags, sample=False)[0].children
    b = model.geometry(turned, flags, sample=False)[0].children
    torch.testing.assert_close(b[..., 0:3], a[..., 0:3] @ rot.T, atol=2e-5, rtol=1e-4)
    expect = quat_multiply(q_rot.expand_as(a[..., 3:7]), a[..., 3:7])
    dot = (expect * b[..., 3:7]).sum(-1).abs()   # q and -q are the same rotation
    torch.testing.assert_close(dot, torch.ones_like(dot), atol=1e-5, rtol=0)
    torch.testing.assert_close(b[..., 7:], a[..., 7:], atol=1e-5, rtol=1e-4)


def test_densified_label_from_lineage_transitions():
    rng = np.random.default_rng(0)

    def mk(n):
        return GaussianCloud(means=rng.normal(size=(n, 3)).astype(np.float32), scales=np.full((n, 3), -3.0, np.float32),
                             quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.zeros(n, np.float32),
                             sh_dc=np.zeros((n, 3), np.float32))

    lin = Lineage(np.zeros(3), 1.0)
    lin.add_stage(mk(4), np.arange(4), np.full(4, -1), 50)
    # 0 survives alone, 1 survives and clones (id 4), 2 is split (ids 5, 6), 3 is pruned
    lin.add_stage(mk(5), np.array([0, 1, 4, 5, 6]), np.array([0, 1, 1, 2, 2]), 75)
    t = lineage_transitions(lin)[0]
    assert t.densified.tolist() == [False, True, True, False]
    assert t.child_mask.sum(1).tolist() == [1, 2, 2, 0]


def test_sampled_child_offsets_follow_the_predicted_spread():
    model = GaussianVAE.create(seed=6)
    data = synthetic_transitions(8, 2, seed=3)[0]
    g = torch.from_numpy(np.repeat(data.history_geometry[:1], 4000, 0))
    nodes = model.geometry._prepare(g)
    mu, _, _ = model.geometry.encode(nodes)
    flags = torch.ones(len(g), dtype=torch.bool)
    mean = model.geometry.decode(mu, nodes, flags)
    drawn = model.geometry.decode(mu, nodes, flags, torch.Generator().manual_seed(0), sample_offsets=True)
    frame = ParentFrame.of(nodes[:, -1])
    frame_local = torch.einsum("mji,mcj->mci", frame.rot, drawn.children[..., 0:3] - nodes[:, -1, None, 0:3])
    frame_local = frame_local / frame.sigma[:, None]
    torch.testing.assert_close(frame_local.mean(0), mean.local_mean[0], atol=0.05, rtol=0)
    torch.testing.assert_close(frame_local.std(0), mean.local_spread[0], atol=0.05, rtol=0.05)
    # without sampling the centres are the means, whatever the generator
    again = model.geometry.decode(mu, nodes, flags, torch.Generator().manual_seed(1))
    torch.testing.assert_close(again.children, mean.children)
