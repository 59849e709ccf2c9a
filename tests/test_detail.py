"""The detail model (gvae_core.detail): inputs, an untrained model changes nothing, training through
the renderer learns a known change, the oracle, saving and loading."""

import numpy as np
import pytest
import torch

from gvae_core import Camera, render
from gvae_core.antialias import with_dilation_3d
from gvae_core.datasets import Views
from gvae_core.detail import (DetailConfig, DetailModel, Example, FitConfig, detail_inputs, fit_changes, fit_model,
                              load_detail, save_detail)
from gvae_core.detail import kernels
from gvae_core.detail.features import (_CHANGE, _LOG_SCALE, _OPACITY, AXIS, NODE, SHARED, detail_inputs_reference,
                                       lineage_nodes)
from gvae_core.examples import example_cloud
from gvae_core.lineage import Lineage
from gvae_core.octaves import with_octaves


def _cameras(height, n=3):
    return [Camera.look_at((3.2 * np.cos(a), 3.2 * np.sin(a), 1.6), width=height, height=height,
                           fov_x=np.radians(45)) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def _cloud(n=600):
    return with_dilation_3d(example_cloud(n, seed=1), _cameras(32))


def test_inputs_are_finite_for_degenerate_gaussians():
    c = _cloud(50)
    s, o, q, m = c.scales.copy(), c.opacities.copy(), c.quats.copy(), c.means.copy()
    s[0], s[1] = -30.0, 20.0
    o[2], o[3] = -50.0, 50.0
    q[4] = 0.0
    m[5] = m[6]  # two Gaussians at one point
    m[7] = 1e6
    inputs = detail_inputs(c.replace(scales=s, opacities=o, quats=q, means=m), None)
    assert inputs.shared.shape == (50, len(SHARED)) and inputs.axis.shape == (50, 3, len(AXIS))
    assert np.isfinite(inputs.shared).all() and np.isfinite(inputs.axis).all()
    with pytest.raises(ValueError, match="anti-aliasing size"):
        detail_inputs(example_cloud(10), None)


def test_lineage_nodes_read_the_last_changes():
    c = example_cloud(20, seed=2)
    lin = Lineage()
    ids = np.arange(20)
    for stage, (res, shift) in enumerate([(50, 0.0), (75, -0.2), (100, -0.5)]):
        lin.add_stage(c.replace(scales=c.scales + shift, opacities=c.opacities + 2 * shift), ids,
                      np.full(20, -1) if stage == 0 else ids, res)
    lin.set_normalization(*c.normalization())
    last = c.replace(scales=c.scales - 0.5, opacities=c.opacities - 1.0, extra={"gvae_id": ids[::-1].copy()})
    scales, opac, exist, octaves = lineage_nodes(last.select(np.arange(20)[::-1]), lin)
    np.testing.assert_allclose(scales[:, 1], (c.scales - 0.2).astype(np.float64), atol=1e-5)
    np.testing.assert_allclose(opac[:, 0], c.opacities, atol=1e-5)
    np.testing.assert_allclose(octaves, [np.log2(1.5), np.log2(4 / 3)])
    assert (exist == 1).all()
    with pytest.raises(ValueError, match="not alive"):
        lineage_nodes(last.replace(extra={"gvae_id": ids + 100}), lin)


def test_an_untrained_model_changes_nothing():
    c = _cloud(300)
    changes = DetailModel().changes(detail_inputs(c))
    assert all(np.all(v == 0) for v in changes.values())
    cam = _cameras(64, 1)[0]
    assert torch.equal(render(c, cam).image, render(with_octaves(c, changes), cam).image)


def _example(truth):
    """The cloud, and views at 2x of what it should be: the cloud with `truth` changes."""
    c = _cloud(400)
    cams = _cameras(64, 4)
    target = with_octaves(c, {k: np.full(np.shape(getattr(c, k)), v, np.float32) for k, v in truth.items()})
    with torch.no_grad():
        images = np.stack([render(target, cam, background=(1, 1, 1)).image.numpy() for cam in cams])
    views = Views(cams, images, np.ones(images.shape[:3], np.float32))
    return Example(c, detail_inputs(c), {"2x": views})


def test_training_through_the_renderer_learns_a_known_change():
    example = _example({"scales": -0.4})
    model = DetailModel(DetailConfig(hidden=16))
    history = fit_model(model, [example], FitConfig(steps=40, lr=8e-3, patch=0, scales=("2x",)))
    losses = history["losses"]
    assert np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10])
    assert model.changes(example.inputs)["scales"].mean() < -0.1


def test_the_oracle_fits_each_gaussian():
    example = _example({"opacities": -1.5})
    changes = fit_changes(example, ["opacities"], FitConfig(steps=40, patch=0, scales=("2x",)))
    assert changes["opacities"].shape == (len(example.cloud),)
    assert np.median(changes["opacities"]) < -0.3


def test_save_and_load(tmp_path):
    model = DetailModel(DetailConfig(hidden=8, context=False, colour=True))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_()
    model.meta = {"note": "x"}
    save_detail(model, tmp_path)
    back = load_detail(tmp_path)
    inputs = detail_inputs(_cloud(30))
    for k, v in model.changes(inputs).items():
        np.testing.assert_array_equal(back.changes(inputs)[k], v)
    assert back.meta == {"note": "x"} and back.config == model.config
    (tmp_path / "detail.safetensors").write_bytes(b"junk")
    with pytest.raises(ValueError, match="detail.safetensors"):
        load_detail(tmp_path)
    with pytest.raises(FileNotFoundError, match="detail.json"):
        load_detail(tmp_path / "missing")


def test_ablation_masks_zero_the_left_out_inputs():
    model = DetailModel(DetailConfig(lineage=False, context=False))
    shared, axis = model.config.masks()
    assert shared[SHARED.index("opacity")] == 1 and shared[SHARED.index("neighbour_contrast")] == 0
    assert shared[SHARED.index("opacity_change")] == 0 and axis[AXIS.index("scale_change")] == 0


def test_the_lineage_encoder_and_its_masked_node_objective():
    model = DetailModel(DetailConfig(hidden=16, encoder="transformer", masked_node=1.0))
    inputs = detail_inputs(_cloud(50))
    assert inputs.nodes.shape == (50, 3, len(NODE))
    assert all(np.all(v == 0) for v in model.changes(inputs).values())  # still starts at no change
    nodes = torch.randn(64, 3, len(NODE))
    aux = model.auxiliary_loss(nodes)
    assert torch.isfinite(aux) and aux > 0
    aux.backward()
    assert model.next_node.weight.grad.abs().sum() > 0
    assert DetailModel(DetailConfig(hidden=16)).auxiliary_loss(nodes) == 0
    with pytest.raises(ValueError, match="encoder"):
        DetailConfig(encoder="lstm")


def test_inputs_of_some_rows_are_those_rows_of_all():
    c = _cloud(120)
    lin = Lineage()
    ids = np.arange(len(c))
    for stage, shift in enumerate((0.0, -0.1, -0.3)):
        lin.add_stage(c.replace(scales=c.scales + shift, extra={}), ids, np.full(len(c), -1) if stage == 0 else ids,
                      50 + 25 * stage)
    rows = np.array([3, 77, 5, 119])
    every, some = detail_inputs(c, lin), detail_inputs(c, lin, rows=rows)
    for a, b in ((every.shared, some.shared), (every.axis, some.axis), (every.nodes, some.nodes)):
        np.testing.assert_allclose(a[rows], b, rtol=1e-6)


def _hard_cloud(n=400):
    """A cloud with every kind of awkward value the inputs clamp: out-of-range, infinite and NaN
    log-scales and opacity logits, NaN and huge DC colours, NaN and non-positive sizes, a duplicate
    point, a lineage with a stage where some Gaussians did not exist yet."""
    c = _cloud(n)
    s, o, dc, m = c.scales.copy(), c.opacities.copy(), c.sh_dc.copy(), c.means.copy()
    s[0], s[1, 0], s[2, 1], s[3, 2] = -30.0, 20.0, -np.inf, np.nan
    o[4], o[5], o[6], o[7] = -50.0, 50.0, np.inf, np.nan
    dc[8], dc[9, 0], dc[10, 1] = np.nan, 1e30, -np.inf
    m[11] = m[12]
    size = c.extra["gvae_dilation_3D"].copy()
    size[13], size[14], size[15] = np.nan, 0.0, -1.0
    c = c.replace(scales=s, opacities=o, sh_dc=dc, means=m, extra={**c.extra, "gvae_dilation_3D": size})
    lin = Lineage()
    ids = np.arange(n)
    for stage, shift in enumerate((0.0, -0.1, -0.3)):
        lin.add_stage(c.replace(scales=np.nan_to_num(c.scales) + shift, opacities=np.nan_to_num(c.opacities) - shift,
                                extra={}), ids, np.full(n, -1) if stage == 0 else ids, 50 + 25 * stage)
    lin.set_normalization(*c.normalization())
    return c, lin


@pytest.mark.parametrize("with_lineage", [False, True])
@pytest.mark.parametrize("neighbours", [0, 8])
@pytest.mark.parametrize("rows", [None, np.array([3, 77, 5, 0, 399, 12])])
def test_compiled_inputs_are_the_reference(with_lineage, neighbours, rows):
    """The compiled kernel (what refine runs) against the numpy float64 definition: the same float32
    values, up to the last bit of float64 arithmetic (fused multiply-adds)."""
    assert (kernels.LOG_SCALE, kernels.OPACITY, kernels.CHANGE) == (_LOG_SCALE, _OPACITY, _CHANGE)
    c, lin = _hard_cloud()
    lin = lin if with_lineage else None
    fast = detail_inputs(c, lin, neighbours=neighbours, rows=rows)
    ref = detail_inputs_reference(c, lin, neighbours=neighbours, rows=rows)
    for name in ("shared", "axis", "nodes"):
        a, b = getattr(fast, name), getattr(ref, name)
        assert a.dtype == b.dtype == np.float32 and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6, err_msg=name)
    assert np.isfinite(fast.shared).all() and np.isfinite(fast.axis).all() and np.isfinite(fast.nodes).all()
    assert fast.nodes[:, 2, 4].min() == 1.0 and (fast.shared[:, 8] == float(with_lineage)).all()


@pytest.mark.parametrize("config", [DetailConfig(), DetailConfig(colour=True, context=True, lineage=False),
                                    DetailConfig(encoder="transformer", hidden=32)])
def test_changes_are_the_forward_pass(config):
    """`changes` (what refine runs: the compiled kernel for the `features` encoder) against `forward`
    (the torch network training differentiates), with every weight non-zero and inputs that reach
    the tanh bounds; and both against the forward pass in float64."""
    torch.manual_seed(0)
    model = DetailModel(config)
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.5)  # an untrained model's last layers are zero: give every weight a value
    c, lin = _hard_cloud(300)
    inputs = detail_inputs(c, lin, neighbours=config.inputs_neighbours)
    inputs.shared[:7] *= 40.0  # far into GELU's tails and the tanh bounds
    assert model._compiled() == (config.encoder == "features")
    fast = model.changes(inputs)
    args = [torch.from_numpy(a) for a in (inputs.shared, inputs.axis, inputs.nodes)]
    with torch.no_grad():
        ref = model(*args)
        ref64 = model.double()(*(a.double() for a in args))
    assert set(fast) == set(ref) == {"scales", "opacities"} | ({"sh_dc"} if config.colour else set())
    for k in ref:
        assert fast[k].dtype == np.float32 and fast[k].shape == tuple(ref[k].shape)
        assert np.abs(ref[k].numpy()).max() > 0.5  # the heads are not trivially zero
        # (torch's own float32 rounding differs from CPU to CPU by about 1e-5; float64 is the judge)
        np.testing.assert_allclose(fast[k], ref[k].numpy(), rtol=1e-5, atol=3e-5, err_msg=k)
        np.testing.assert_allclose(fast[k], ref64[k].numpy(), rtol=1e-4, atol=1e-4, err_msg=k)
    bounded = np.abs(fast["opacities"]).max()
    assert bounded <= 8.0 and bounded > 7.0
