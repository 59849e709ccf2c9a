"""The experiment and the report, end to end on a tiny scene rendered by our own renderer (no
Blender): every method and step is evaluated, the controls match Ours-∇²'s count, the knob and the
extrapolation factor are the best on their scenes, the oracle is above the unrefined cloud, and
the report's tables show the numbers of a known input."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from gvae_core import GaussianCloud
from gvae_core.camera import orbit
from gvae_core.controls import extrapolation_control
from gvae_core.detail import DetailModel
from gvae_core.experiment import (BASELINE, CONTROLS, DEFAULT, DUPLICATE, EXTRAPOLATION, KNOB, ORACLE, OURS, OURS_H,
                                  RANDOM, REAL, SCALES, SPLIT, Protocol, SceneRun, run_scene, tune_knob, IMAGES,
                                  IMAGES_CHILDREN, IMAGES_NO_CHILDREN, FINETUNE, ORACLE_IMAGES, FOUR_X)
from gvae_core.rendering import render
from gvae_core.report import (Results, default_losses, default_table, fault_table, four_x_table, headline_table,
                              images_goals, images_table, losses, mean_ci, methods_table, write_report)
from gvae_core.scenes.build import write_mesh_ply
from gvae_core.train import train_progressive
from gvae_core.vae import GaussianVAE


def _sphere(n_lat=12, n_lon=24, r=0.6):
    lat = np.linspace(0, np.pi, n_lat)
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    verts = np.array([[r * np.sin(a) * np.cos(b), r * np.sin(a) * np.sin(b), r * np.cos(a)] for a in lat for b in lon])
    tris = []
    for i in range(n_lat - 1):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            tris += [(a, b, d), (a, d, c)]
    return verts, np.array(tris)


def _scene(root, size=48):
    """A textured ball of Gaussians on the mesh of a sphere, rendered into a NeRF-Synthetic folder."""
    rng = np.random.default_rng(0)
    verts, tris = _sphere()
    n = 600
    d = rng.normal(size=(n, 3))
    pts = 0.6 * d / np.linalg.norm(d, axis=1, keepdims=True)
    cloud = GaussianCloud(means=pts.astype(np.float32), scales=np.full((n, 3), math.log(0.06), np.float32),
                          quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32), opacities=np.full(n, 3.0, np.float32),
                          sh_dc=(np.sign(pts) * 1.2).astype(np.float32))
    root.mkdir()
    for split, count in (("train", 10), ("test", 3)):
        (root / split).mkdir()
        cams = orbit(count, 2.5, width=size, height=size, fov_x=0.9, elevation=0.4 if split == "train" else 0.7)
        frames = []
        for i, cam in enumerate(cams):
            out = render(cloud.to_torch(), cam)
            rgb = (out.image.clamp(0, 1).numpy() / np.maximum(out.alpha.numpy()[..., None], 1e-6)).clip(0, 1)
            rgba = np.concatenate([rgb, out.alpha.numpy()[..., None]], -1)
            Image.fromarray((rgba * 255 + 0.5).astype(np.uint8)).save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": cam.to_blender_c2w().tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.9, "frames": frames}))
    write_mesh_ply(root / "mesh.ply", verts, tris)
    np.save(root / "gt_points.npy", pts.astype(np.float32))
    return root


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("experiment")
    scene = _scene(tmp / "ball")
    protocol = Protocol("test", scene_profile="none", resolutions=(16, 24), iterations=(40, 30), higher=(36, 48),
                        higher_iterations=(20, 20), scenes=("ball",), seeds=(0,), steps=2,
                        train_overrides=dict(init_count=300, max_gaussians=3000, sh_degree=1), test_views=2,
                        hessian_views=2, knob_factors=(0.5, 1.0), oracle_steps=30, oracle_patch=0,
                        image_fit=dict(steps=40, patch=0, children=0.0, densify_at=(0.5,), max_children=0.1),
                        image_4x=False)
    run_dir = tmp / "run"
    train_progressive(scene, protocol.train_config(0), out_dir=run_dir, progress=False)
    run = SceneRun("ball", 0, scene, run_dir, protocol, {"scene": 0.0, "train": 0.0})
    model = GaussianVAE.create(seed=0)
    rows = run_scene(run, model, 1.1, 0.5, detail=DetailModel(), say=lambda msg: None)
    return run, rows


def _pick(rows, method, step=0, scale=None):
    return next(r for r in rows if r["method"] == method and r.get("step") == step and r.get("scale") == scale)


def test_every_method_and_step_is_scored(experiment):
    run, rows = experiment
    for method in (OURS, OURS_H, *CONTROLS):
        assert sorted(r["step"] for r in rows if r["method"] == method) == [1, 2]
    for r in rows:
        if r["method"] == "render":
            assert r["render_error"] < 1e-4 and r["render_s"] > 0
            continue
        assert r["scene"] == "ball" and r["seed"] == 0
        assert np.isfinite(r["chamfer"]) and r["chamfer"] == pytest.approx(0.5 * (r["accuracy"] + r["completeness"]))
        assert np.isfinite(r["weighted_accuracy"])
        for s in SCALES:
            assert np.isfinite(r[f"psnr_{s}"]) and np.isfinite(r[f"psnr_{s}_classic"]) and 0 < r[f"ssim_{s}"] <= 1
    # the real higher-resolution stages are the REAL rows; the knob scales the unrefined cloud
    log = run.log()
    for i, s in enumerate(SCALES[1:], 2):
        r = _pick(rows, REAL, scale=s)
        assert r["resolution"] == log[i]["resolution"] and r["n_gaussians"] == log[i]["n_gaussians"]
    base = _pick(rows, BASELINE)
    for method in (KNOB, EXTRAPOLATION, DEFAULT, ORACLE):  # at the same count, the training picture kept
        r = _pick(rows, method, 1)
        assert r["n_gaussians"] == base["n_gaussians"] and r["psnr_1x"] == pytest.approx(base["psnr_1x"], abs=0.02)
    assert _pick(rows, KNOB, 1)["factor"] == 1.1 and _pick(rows, EXTRAPOLATION, 1)["factor"] == 0.5
    # an untrained detail model changes nothing; the oracle, fitted to the real views, gains
    assert _pick(rows, DEFAULT, 1)["psnr_2x"] == pytest.approx(base["psnr_2x"], abs=1e-6)
    assert _pick(rows, ORACLE, 1)["psnr_2x"] > base["psnr_2x"]
    # refine with the images: children added, the training picture kept; the same fit to the real 2x
    # images; the same steps of plain training change the 1x picture
    images, bare = _pick(rows, IMAGES, 1), _pick(rows, IMAGES_NO_CHILDREN, 1)
    assert images["n_gaussians"] == base["n_gaussians"] + images["added"] and images["added"] > 0
    assert bare["n_gaussians"] == base["n_gaussians"]
    for r in (images, bare, _pick(rows, ORACLE_IMAGES, 1)):
        assert r["psnr_1x"] == pytest.approx(base["psnr_1x"], abs=0.02) and r["psnr_2x"] != base["psnr_2x"]
    assert images["fit_psnr"][1] > images["fit_psnr"][0]
    tuned = _pick(rows, FINETUNE, 1)
    assert tuned["iterations"] == 40 and tuned["n_gaussians"] == base["n_gaussians"]
    assert tuned["psnr_1x"] != base["psnr_1x"]


def test_controls_match_ours_h_count(experiment):
    _, rows = experiment
    for k in (1, 2):
        target = _pick(rows, OURS_H, k)["added"]
        for method in CONTROLS:
            assert _pick(rows, method, k)["added"] == target, method
        assert _pick(rows, SPLIT, k)["n_gaussians"] == _pick(rows, OURS_H, k)["n_gaussians"]
    assert _pick(rows, OURS, 1)["selected"] == _pick(rows, BASELINE)["n_gaussians"]


def test_knob_and_extrapolation_factor_are_the_best_on_their_scenes(experiment):
    run, _ = experiment
    knob = tune_knob([run], (0.5, 1.0))
    assert knob["factor"] == 1.0 and knob["scenes"] == ["ball"]
    assert knob["psnr_2x"]["1"] > knob["psnr_2x"]["0.5"]  # halving every Gaussian leaves holes
    tuned = tune_knob([run], (0.0, 0.5, 3.0), control=extrapolation_control, with_lineage=True)
    assert tuned["psnr_2x"][f"{tuned['factor']:g}"] == max(tuned["psnr_2x"].values())
    assert tuned["psnr_2x"]["0"] > tuned["psnr_2x"]["3"]


def _known_doc() -> dict:
    """Two scenes x two seeds with round numbers: at +1 Ours-∇² lowers Chamfer by 25% and the split
    by 10%; on scene b seed 1 the split wins PSNR 2x by 0.5 dB."""
    rows = []
    for scene in ("a", "b"):
        for seed in (0, 1):
            base = dict(scene=scene, seed=seed, split="test", chamfer=2.0, accuracy=1.0, weighted_accuracy=1.0,
                        completeness=3.0, n_gaussians=100, **{f"psnr_{s}": 30.0 for s in SCALES},
                        **{f"psnr_{s}_classic": 29.0 for s in SCALES}, **{f"ssim_{s}": 0.9 for s in SCALES})
            rows += [{**base, "method": BASELINE, "step": 0}, {**base, "method": KNOB, "step": 1, "psnr_2x": 30.2},
                     {**base, "method": EXTRAPOLATION, "step": 1, "psnr_2x": 30.3},
                     {**base, "method": DEFAULT, "step": 1, "psnr_2x": 30.1 if scene == "a" else 30.6},
                     {**base, "method": ORACLE, "step": 1, "psnr_2x": 31.0}]
            rows += [{**base, "method": REAL, "step": 0, "scale": s, "psnr_2x": 33.0, "n_gaussians": 200}
                     for s in ("1.5x", "2x")]
            # refine with the images: +1.2 on a, +0.2 on b (20 added, +0.1 of it theirs); 1x training +0.4
            gain = 1.2 if scene == "a" else 0.2
            rows += [{**base, "method": IMAGES, "step": 1, "psnr_2x": 30.0 + gain, "n_gaussians": 120, "added": 20},
                     {**base, "method": IMAGES_NO_CHILDREN, "step": 1, "psnr_2x": 29.9 + gain},
                     {**base, "method": FINETUNE, "step": 1, "psnr_2x": 30.4, "psnr_1x": 30.5},
                     {**base, "method": ORACLE_IMAGES, "step": 1, "psnr_2x": 31.5}]
            four = dict(base, psnr_4x=25.0)
            rows += [{**four, "method": FOUR_X[BASELINE], "step": 0}, {**four, "method": FOUR_X[IMAGES], "step": 2,
                                                                      "psnr_4x": 26.5}]
            for k in (1, 2):
                ours_psnr = 30.0 if (scene, seed) == ("b", 1) else 31.0
                rows.append({**base, "method": OURS_H, "step": k, "chamfer": 1.5, "weighted_accuracy": 0.8,
                             "psnr_2x": ours_psnr, "n_gaussians": 110, "added": 10})
                rows.append({**base, "method": SPLIT, "step": k, "chamfer": 1.8, "psnr_2x": 30.5, "n_gaussians": 110,
                             "added": 10})
                for method in (OURS, RANDOM, DUPLICATE):
                    rows.append({**base, "method": method, "step": k, "chamfer": 2.2, "n_gaussians": 110, "added": 10})
    return {"protocol": {"name": "known", "resolutions": [10, 20], "higher": [30, 40], "steps": 2, "seeds": [0, 1],
                         "budget": "auto", "scene_profile": "none", "antialias": "matched"},
            "model": {"dir": None, "sizes": {"geometry": 1000, "appearance": 2000}, "train_scenes": ["t"]},
            "knob": {"factor": 1.1, "psnr_2x": {"1": 29.0, "1.1": 29.4}, "scenes": ["t"]},
            "extrapolation": {"factor": 0.25, "psnr_2x": {"0": 29.0, "0.25": 29.2}, "scenes": ["t"]}, "split": "test",
            "started": "now", "seconds": 60.0, "rows": rows,
            "fault_rows": [{"scene": sc, "seed": 0, "fault": f, "method": m, "guard": g,
                            "psnr_2x": 28.0 + (0.0 if m == BASELINE else 0.5 + (g == "pose") * 0.3 * (f != "none"))}
                           for sc in ("a", "b") for f in ("none", "pose 0.5 px")
                           for m, g in ((BASELINE, ""), (IMAGES, "none"), (IMAGES, "pose"))],
            "runs": {f"{s}/s{d}": {"scene": s, "seed": d, "log": [{"resolution": 10, "peak_rss_mb": 100.0,
                                                                  "n_gaussians": 50, "seconds": 1.0,
                                                                  "test_psnr": 25.0}]}
                     for s in ("a", "b") for d in (0, 1)}}


def test_mean_ci_is_the_t_interval():
    m, h = mean_ci([1.0, 2.0, 3.0, float("nan")])
    assert m == 2.0 and h == pytest.approx(4.302652729911275 * 1.0 / math.sqrt(3))
    assert math.isnan(mean_ci([5.0])[1]) and math.isnan(mean_ci([])[0])


def test_report_tables_show_the_numbers_of_a_known_input():
    res = Results(_known_doc())
    assert res.pairs == [("a", 0), ("a", 1), ("b", 0), ("b", 1)]
    head = {line.split(" | ")[1].split(" (")[0] + line.split(" | ")[0]: line for line in headline_table(res)[2:]}
    # Chamfer at +1: Ours-∇² -25% on every pair; the best alternative is the split at -10%
    assert head["Chamfer| +1"] == ("| +1 | Chamfer (%, lower is better) | -25.00 ± 0.00 | -10.00 ± 0.00 "
                                   "(plain split) | -15.00 ± 0.00 | 4/4 |")
    # PSNR 2x at +1: +1 dB on three pairs, 0 on one; the split's +0.5 is the best alternative everywhere
    psnr = head["PSNR 2x| +1"].split(" | ")
    assert psnr[2].startswith("+0.75 ± ") and psnr[3].startswith("+0.50 ± 0.00") and psnr[5] == "3/4 |"
    methods = {line.split(" | ")[0][2:] + line.split(" | ")[1]: line for line in methods_table(res)[2:]}
    assert methods["Ours-∇²+2"].split(" | ")[2:4] == ["110", "-25.00 ± 0.00"]
    assert losses(res) == ["- b, seed 1, +1: PSNR 2x -0.50 dB against plain split",
                           "- b, seed 1, +2: PSNR 2x -0.50 dB against plain split"]


def test_report_compares_the_default_with_what_costs_the_same():
    res = Results(_known_doc())
    table = {line.split(" | ")[0][2:]: line.split(" | ") for line in default_table(res)[2:]}
    # default +0.10 on a, +0.60 on b; the extrapolation's +0.30 is the best same-cost alternative
    assert table["PSNR 2x dB"][1].startswith("+0.35 ± ") and table["PSNR 2x dB"][4].startswith("+1.00 ± 0.00")
    assert table["PSNR 2x dB"][5].startswith("+0.05 ± ") and table["PSNR 2x dB"][6] == "2/4 |"
    assert default_losses(res) == [f"- a, seed {d}: PSNR 2x -0.10 dB against global scale knob per octave; -0.20 dB "
                                   f"against linear lineage extrapolation" for d in (0, 1)]


def test_report_tables_of_refine_with_the_images():
    doc = _known_doc()
    res = Results(doc)
    table = {line.split(" | ")[0][2:]: line.split(" | ") for line in images_table(res)[2:7]}
    assert table["PSNR 2x dB"][1].startswith("+0.70 ± ") and table["PSNR 2x dB"][5].startswith("+0.40 ± 0.00")
    assert table["PSNR 2x dB"][6].startswith("+1.50 ± 0.00") and table["PSNR 2x dB"][7].startswith("+3.00")
    assert table["Gaussians added"][1] == "20"
    per_pair = [line for line in images_table(res) if line.startswith("| b | 1 |")]
    assert per_pair == ["| b | 1 | +0.20 | +0.10 | +0.60 | +0.40 | +1.50 | 20 | +5.00 |"]
    # a default fit without children, its children's row beside it: the same gain per child
    swap = {IMAGES: IMAGES_CHILDREN, IMAGES_NO_CHILDREN: IMAGES}
    other = Results({**doc, "rows": [{**r, "method": swap.get(r["method"], r["method"])} for r in doc["rows"]]})
    lines = images_table(other)
    assert "| Gaussians added | 0 | 20 |" in lines[6] and "| with children |" in lines[10]
    assert [line for line in lines if line.startswith("| b | 1 |")] == [
        "| b | 1 | +0.10 | +0.20 | +0.60 | +0.40 | +1.50 | 20 | +5.00 |"]
    goals = images_goals(res)
    assert "+0.70 ± " in goals[0] and "goal +1.0: not met" in goals[0] and "b s0 (+0.20), b s1 (+0.20)" in goals[0]
    assert "+0.30 ± " in goals[1] and "not met" in goals[1] and "worst pair -0.20" in goals[1]
    assert "within 0.01: met" in goals[2]
    assert four_x_table(res)[2].startswith("| PSNR 4x dB | +1.50 ± 0.00 |")
    faults = fault_table(doc)
    assert faults[2] == "| none | 2 | 28.00 | +0.50 ± 0.00 | +0.50 ± 0.00 | +0.50 |"
    assert faults[3] == "| pose 0.5 px | 2 | 28.00 | +0.50 ± 0.00 | +0.80 ± 0.00 | +0.50 |"


def test_report_is_written_with_its_results(tmp_path):
    doc = _known_doc()
    path = write_report(doc, tmp_path, command="gvae report --profile test")
    text = path.read_text()
    assert "\n".join(headline_table(Results(doc))) in text and "\n".join(losses(Results(doc))) in text
    assert "gvae report --profile test" in text and "x1.1" in text and "x0.25" in text
    assert "\n".join(default_table(Results(doc))) in text
    for png in ("geometry_vs_count.png", "training.png"):
        assert png in text and Image.open(tmp_path / png).size[0] > 100
    data = json.loads((tmp_path / "results.json").read_text())
    assert len(data["rows"]) == len(doc["rows"])
