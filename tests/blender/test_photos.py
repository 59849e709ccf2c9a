"""Sidebar > GaussianVAE > New from Photos (`gvae_addon.photos_ops`): a small posed capture made here becomes a
splat object through the background job, as `gvae train` trains it; cancel before and during the training
leaves the scene as it was and keeps the run folder; without PyTorch the job is refused before it starts,
saying so; with a stand-in for the training, Blender 5.3 gets a Blender splat."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gvae_core.ply import write_ply
from tests.blender.conftest import blender_versions, requires_blender_torch, run_scenario
from tests.conftest import requires_bpy

pytestmark = requires_bpy


def photo_capture(folder: Path, views: int = 9) -> tuple:
    """A small capture of photos with their poses: an object over a transparent background (so training
    starts from the masks' hull, as `gvae train` does for one, with no points to triangulate) drawn by
    gvae_core.render from `views` cameras around it, 24 px, in a transforms.json (one set of photos: with
    held-out photos 2 of 9 set aside)."""
    from PIL import Image  # noqa: PLC0415

    from gvae_core import render  # noqa: PLC0415 - needs torch
    from gvae_core.examples import example_cloud  # noqa: PLC0415
    from tests.test_superres import _cameras  # noqa: PLC0415

    truth = example_cloud(300, seed=0).with_sh_degree(1)
    folder.mkdir()
    frames = []
    for i, cam in enumerate(_cameras(views)):
        out = render(truth, cam, background=(0.0, 0.0, 0.0))
        alpha = out.alpha.numpy()[..., None]
        rgb = np.where(alpha > 0, out.image.numpy() / np.maximum(alpha, 1e-6), 0.0)  # straight colour
        rgba = np.concatenate([rgb, alpha], -1).clip(0.0, 1.0)
        Image.fromarray((rgba * 255).round().astype(np.uint8), "RGBA").save(folder / f"r_{i}.png")
        frames.append({"file_path": f"r_{i}.png", "transform_matrix": cam.to_blender_c2w().tolist()})
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": cam.fov_x, "frames": frames}))
    return truth, folder


def test_new_from_photos_job(extension_zip, tmp_path):
    """Where Blender has no PyTorch (here: Blender 5.1 and later), the real training is skipped after the
    rest, saying why; the Blender side runs everywhere (with a stand-in for the training: on 5.3 it gives
    a Blender splat)."""
    pytest.importorskip("torch", reason="the test's capture is rendered with gvae_core.render (PyTorch)")
    from gvae_core.cli import main  # noqa: PLC0415 - after the check for torch

    truth, folder = photo_capture(tmp_path / "photos")
    write_ply(truth, tmp_path / "stand_in.ply")
    options = {"height": 16, "iterations": 10}
    res = run_scenario("photos", tmp_path, extension_zip, folder=str(folder), run=str(tmp_path / "run"),
                       run_cancel=str(tmp_path / "run_cancel"), cloud=str(tmp_path / "stand_in.ply"), timeout=600,
                       **options)

    assert res["missing"] == ["PyTorch (training)"]  # (a posed capture: no structure from motion to install)
    assert "New from Photos needs PyTorch (training)" in res["refused"]["error"] and res["refused_same"]
    assert res["stand_in_heldout"] == 20.0  # (what the panel shows while it runs)
    assert res["stand_in_cancel"]["error"] == "New from Photos cancelled" and res["stand_in_cancel_same"]
    native = blender_versions()[1] >= (5, 3)
    s = res["stand_in"]
    assert s["native"] == native and s["type"] == ("POINTCLOUD" if native else "MESH") and s["count"] == len(truth)
    assert s["modifier"] == [f"GaussianVAE {'Native ' if native else ''}Splats (SH 1)"]
    assert s["cameras"] == 9 and s["heldout"] == 21.5 and s["rotation"] == [0.0, 0.0, 0.0]
    requires_blender_torch()

    print(f"seconds in the scenario: {res['seconds']}")
    assert res["cancel"]["error"] == "New from Photos cancelled" and res["cancel_same"]
    assert res["cancel_later"]["error"] == "New from Photos cancelled" and res["cancel_later_same"]
    assert any(m.startswith("stage 2/3") for m in res["cancel_later_messages"]), res["cancel_later_messages"]
    assert {"stage_0.ply", "run.json", "log.json"} <= set(res["kept"]) and "stage_2.ply" not in res["kept"]

    assert res["batch"] == ["FINISHED"] and res["again"] == ["FINISHED"]
    obj = res["object"]
    assert obj["name"] == "photos" and obj["type"] == "MESH" and obj["count"] > 100 and obj["modifiers"] == ["NODES"]
    assert obj["rotation"] == [0.0, 0.0, 0.0]  # (a transforms.json capture: its axes as stored)
    assert len(res["cameras"]) == 9 and sum("(held out)" in c for c in res["cameras"]) == 2
    assert res["camera_parent"] == ["photos"]
    assert {"stage_2.ply", "run.json", "log.json", "lineage.npz"} <= set(res["run"])
    assert res["after"]["view"] == "Standard" and res["after"]["camera"] == "Camera"  # (the scene had a camera)
    assert res["again_count"] == obj["count"]  # resumed: every stage was done
    report = res["_output"].split("New from Photos: photos, ")[1]
    assert "Gaussians trained at 16 px" in report and "held-out photos" in report and " dB PSNR" in report

    # `gvae train` with the same options gives the same held-out figure
    cli = tmp_path / "cli"
    assert main(["train", str(folder), "--out", str(cli), "--image-height", "16", "--profile", "tiny",
                 "--iterations", "10", "--test-every", "8", "--quiet"]) == 0
    ours, theirs = (json.loads((p / "log.json").read_text())[-1]["test_psnr"] for p in (tmp_path / "run", cli))
    assert abs(ours - theirs) <= 0.1, (ours, theirs)
    shutil.rmtree(cli)
    assert np.isfinite(ours)
