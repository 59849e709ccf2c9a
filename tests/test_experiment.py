"""The experiment and the report, end to end on a tiny scene rendered by our own renderer (no
Blender): every method and step is evaluated, the baselines come from the real higher-resolution
stages, the controls use Ours-∇²'s budget, and the report has its tables and plots."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from gvae_core import GaussianCloud
from gvae_core.camera import orbit
from gvae_core.experiment import (BASELINE, OURS, OURS_H, OURS_H_MODEL_APP, RANDOM, SCALES, SPLIT, SWEEP, Protocol,
                                  SceneRun, run_scene)
from gvae_core.report import write_report
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
    from gvae_core.rendering import render
    from gvae_core.scenes.build import write_mesh_ply

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
    from gvae_core.train import train_progressive

    tmp = tmp_path_factory.mktemp("experiment")
    scene = _scene(tmp / "ball")
    protocol = Protocol("test", scene_profile="none", scenes=("ball",), resolutions=(16, 24), iterations=(40, 30),
                        higher=(36, 48), higher_iterations=(20, 20),
                        train_overrides=dict(init_count=300, max_gaussians=3000, sh_degree=1), steps=2,
                        sweep=(0.1, 1.0), test_views=2, hessian_views=2, hessian_probes=1)
    run_dir = tmp / "run"
    train_progressive(scene, protocol.train_config(), out_dir=run_dir, progress=False)
    run = SceneRun("ball", scene, run_dir, protocol, {"scene": 0.0, "train": 0.0})
    model = GaussianVAE.create(seed=0)
    model.meta = {"train_scenes": ["other"], "held_out_scenes": ["ball"]}
    rows = run_scene(run, model, say=lambda msg: None)
    doc = {"protocol": {"name": "test", "resolutions": [16, 24], "higher": [36, 48], "steps": 2, "budget": "auto",
                        "scene_profile": "none"},
           "model": {"dir": None, "sizes": model.sizes(), "train_scenes": ["other"], "held_out_scenes": ["ball"]},
           "started": "now", "seconds": 1.0, "rows": rows,
           "scenes": {"ball": {"log": run.log(), "seconds": {}}}}
    return run, rows, doc, tmp


def test_every_method_and_step_is_scored(experiment):
    run, rows, _, _ = experiment
    by = {(r["method"], r.get("step"), r.get("scale"), r.get("budget")) for r in rows}
    for s in SCALES:
        assert (BASELINE, 0, s, None) in by
    for method in (OURS, OURS_H, OURS_H_MODEL_APP, RANDOM, SPLIT):
        assert {k for m, k, _, _ in by if m == method} == {1, 2}
    assert {b for m, _, _, b in by if m == SWEEP} == {"0.1", "1.0"}
    for r in rows:
        if r["method"] == "render":
            assert r["render_error"] < 1e-4 and r["render_s"] > 0
            continue
        assert np.isfinite(r["chamfer"]) and r["chamfer"] == pytest.approx(0.5 * (r["accuracy"] + r["completeness"]))
        assert np.isfinite(r["psnr_2x"]) and 0 < r["ssim_2x"] <= 1
    # the baselines are the real training stages at 1x, 1.5x and 2x
    log = run.log()
    for i, s in enumerate(SCALES):
        r = next(r for r in rows if r["method"] == BASELINE and r["scale"] == s)
        assert r["resolution"] == log[1 + i]["resolution"] and r["n_gaussians"] == log[1 + i]["n_gaussians"]


def test_controls_use_the_hessian_budget(experiment):
    _, rows, _, _ = experiment
    pick = lambda m, k: next(r for r in rows if r["method"] == m and r["step"] == k)  # noqa: E731
    n = pick(OURS_H, 1)["selected"]
    assert pick(RANDOM, 1)["selected"] == n and pick(SPLIT, 1)["selected"] == n
    assert pick(SPLIT, 1)["added"] == n and pick(SPLIT, 2)["added"] == 3 * n  # 2 then 4 children per root
    base = next(r for r in rows if r["method"] == BASELINE and r["scale"] == "1x")
    assert pick(OURS, 1)["selected"] == base["n_gaussians"]


def test_report_has_the_tables_and_plots(experiment):
    _, _, doc, tmp = experiment
    out = tmp / "report"
    path = write_report(doc, out, command="gvae report --profile test")
    text = path.read_text()
    for heading in ("Table 1: Chamfer", "Table 2: NIQE", "Table 3: PSNR", "Ablation", "budget sweep",
                    "Speed against error", "Memory against training resolution", "Where Ours-∇² loses"):
        assert heading in text
    assert "ball" in text and "gvae report --profile test" in text
    for png in ("refine_time_vs_chamfer.png", "render_time.png", "train_time_vs_psnr.png", "memory_vs_resolution.png"):
        assert (out / png).stat().st_size > 1000 and png in text
    data = json.loads((out / "results.json").read_text())
    assert len(data["rows"]) == len(doc["rows"])
