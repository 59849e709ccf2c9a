"""Blender 5.3's own Gaussian splats (point clouds of type Gaussian Splat, made by its PLY importer) through
the add-on's Refine and Compact jobs, and a refined one drawn by Cycles: its changes per octave follow the
camera through the add-on's modifier (`gvae_addon.nodes.add_native_modifier`). Skipped, saying why, on
Blender versions without such point clouds (`make test-blender-versions` runs it with bpy 5.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from gvae_core import render
from gvae_core.antialias import DILATION_KEY, with_dilation_3d
from gvae_core.camera import orbit
from gvae_core.octaves import LIMIT_KEY, stored_keys
from gvae_core.ply import read_ply, write_ply
from gvae_core.rendering import RenderSettings
from tests.blender.conftest import ROOT, blender_versions, run_scenario
from tests.blender.test_display import VIEWS, png_over_white, psnr, refined, view_camera
from tests.conftest import requires_bpy

pytestmark = requires_bpy


def test_refine_and_compact_blenders_own_splat(extension_zip, tmp_path):
    """A splat imported by Blender's own PLY importer (extras as plain attributes, no modifier): Refine
    (a stand-in returning a refined cloud whose changes per octave touch only the Gaussians left of the
    view's centre) gives a Blender splat with the refined count, every change per octave and the
    `gvae_step` marks, and the modifier; at 100% Cycles draws it exactly as with Refinement off, at 200%
    it differs from that only where the changed Gaussians are drawn, and matches gvae_core.render of the
    refined cloud at 200%; Compact gives a Blender splat of the kept rows with the same attributes."""
    version = blender_versions()[1]
    if version < (5, 3):
        pytest.skip(f"Blender {'.'.join(map(str, version))} has no Gaussian-splat point clouds (5.3 and later); "
                    "make test-blender-versions runs this with bpy 5.3")
    cam = view_camera("materials")
    cam2 = cam.scaled(2 * cam.height)
    train = [cam] + orbit(8, float(np.linalg.norm(cam.center)), math.radians(35.0), width=cam.width,
                          height=cam.height, fov_x=cam.fov_x)
    cloud = with_dilation_3d(read_ply(ROOT / VIEWS["materials"]["ply"]), train)
    n, kids = len(cloud), len(cloud) // 10
    out = refined(cloud, 7, children=kids, limit=1.0)
    # changes only left of the view's centre (in the camera's x): elsewhere the 2x render stays the 1x one
    x = (np.c_[out.means, np.ones(len(out))] @ np.asarray(cam.world_to_cam).T)[:, 0]
    changed = x < 0
    extra = dict(out.extra)
    for key in stored_keys(out):
        if key != LIMIT_KEY:
            extra[key] = np.where(changed, extra[key], 0.0).astype(np.float32)
    out = out.replace(extra=extra)
    write_ply(cloud, tmp_path / "in.ply")
    write_ply(out, tmp_path / "refined.ply")
    res = run_scenario("native_jobs", tmp_path, extension_zip, ply=str(tmp_path / "in.ply"),
                       refined=str(tmp_path / "refined.ply"), export=str(tmp_path / "export.ply"), samples=64,
                       c2w=cam.to_blender_c2w().tolist(), fov_x=cam.fov_x, width=cam.width, height=cam.height,
                       timeout=600)

    assert res["imported"]["data_type"] == "GAUSSIAN_SPLAT" and res["imported"]["modifier"] is None
    assert res["draw_as_gvae"] == ["FINISHED"] and res["drawn"]
    assert res["received"] == {"n": n, "extra": [DILATION_KEY]}  # Blender's importer kept it as an attribute
    assert res["refine_info"] == {"before": n, "after": n + kids, "added": kids}
    r = res["refined"]
    assert (r["type"], r["data_type"], r["points"]) == ("POINTCLOUD", "GAUSSIAN_SPLAT", n + kids)
    assert r["modifier"] == "GaussianVAE Native Splats (SH 3)"
    assert any(label.endswith(f": {n + kids:,} Gaussians (Blender's own splat)") for label in res["panels"])
    assert "order (further from gvae render than the" in res["panels"]  # what it cannot show, said in Display
    got = np.load(tmp_path / "native_jobs.json.refined.npz")
    assert set(stored_keys(out)) | {DILATION_KEY, "gvae_step", "position", "scale", "rotation",
                                    "radiance__base"} <= set(got.files)
    np.testing.assert_array_equal(got["gvae_step"], [0] * n + [1] * kids)
    for key in stored_keys(out):
        np.testing.assert_array_equal(got[key], out.extra[key], err_msg=key)
    back = read_ply(tmp_path / "export.ply")  # Export keeps the changes per octave
    assert set(stored_keys(out)) <= set(back.extra) and len(back) == n + kids

    images = {name: png_over_white(tmp_path / f"native_{name}.png") for name in ("200_1", "200_0", "100_1", "100_0")}
    assert res["focal"] == pytest.approx(cam.fx, rel=1e-5)  # (the last render's: 100%)
    np.testing.assert_array_equal(images["100_1"][0], images["100_0"][0])  # 1x: the refinement draws nothing
    np.testing.assert_array_equal(images["100_1"][1], images["100_0"][1])
    (on, on_alpha), (off, _) = images["200_1"], images["200_0"]
    # where the changed Gaussians are drawn at 2x (the core's alpha of them alone, either way)
    where = np.zeros(on_alpha.shape, bool)
    for cl in (out, out.replace(extra={k: v for k, v in out.extra.items() if k not in stored_keys(out)})):
        part = cl.select(np.flatnonzero(changed))
        where |= render(part, cam2, settings=RenderSettings(antialias="matched")).alpha.numpy() > 0.5 / 255
    diff = np.abs(on - off).max(2)
    # Blender draws each Gaussian's tail beyond the reference's 1/255 cut-off: a few pixels more, faintly
    ring = ndimage.binary_dilation(where, iterations=4) & ~where
    assert diff[~where & ~ring].max() == 0.0, "the refinement changed pixels no changed Gaussian reaches"
    assert diff[ring].max() <= 4 / 255
    assert (diff[where] > 4 / 255).mean() > 0.3, "the refinement does not show at 2x"
    ref2 = render(out, cam2, background=(1.0, 1.0, 1.0)).image.numpy().clip(0.0, 1.0)
    unrefined2 = render(cloud, cam2, background=(1.0, 1.0, 1.0)).image.numpy().clip(0.0, 1.0)
    p_on, p_off = psnr(on, ref2), psnr(off, ref2)
    print(f"Blender's splat refined at 200%: {p_on:.2f} dB against gvae_core.render of the refined cloud "
          f"(Refinement off: {p_off:.2f} dB; the unrefined cloud in the core: {psnr(unrefined2, ref2):.2f} dB)")
    assert p_on >= 30.0 and p_on > p_off + 1.0

    assert res["compact_info"] == {"before": n + kids, "after": (n + kids + 1) // 2}
    c = res["compacted"]
    assert (c["data_type"], c["points"], c["modifier"]) == ("GAUSSIAN_SPLAT", (n + kids + 1) // 2, r["modifier"])
    kept = np.load(tmp_path / "native_jobs.json.compacted.npz")
    assert set(kept.files) == set(got.files)
    for key in ("gvae_step", "position", DILATION_KEY, "gvae_octave_opacity"):
        np.testing.assert_array_equal(kept[key], got[key][::2], err_msg=key)
    assert res["native_poll"] == [True, True] and res["is_native"]
