"""The Blender Refine job: the work runs in a worker thread while Blender stays responsive, with
progress, cancel (Esc), and the object written once on success and untouched otherwise. Driven
without a window (`RefineJob.start/poll/cancel/finish`), as the modal operator drives it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from gvae_core.ply import write_ply
from tests.blender.conftest import requires_blender_torch, run_scenario
from tests.blender.test_extension import make_cloud
from tests.conftest import requires_bpy

pytestmark = requires_bpy


def test_refine_job_progress_cancel_failure_and_modal_events(extension_zip, tmp_path):
    pytest.importorskip("torch", reason="the real refine needs PyTorch (an optional runtime in Blender)")
    requires_blender_torch()
    from gvae_core.vae import GaussianVAE, save_model  # noqa: PLC0415 - after the check for torch

    n = 48
    src = tmp_path / "in.ply"
    write_ply(make_cloud(n, degree=1), src)
    model = save_model(GaussianVAE.create(seed=0), tmp_path / "model")  # untrained: the data path, not the model
    res = run_scenario("refine_job", tmp_path, extension_zip, ply=str(src), model=str(model))
    k = n // 4
    # success: progress rose while the main thread kept working; the object changed only at finish
    assert res["polls"] >= 20 and res["fractions_rise"] and res["untouched_while_running"]
    assert "stand-in" in res["messages"]
    assert res["info"] == {"before": n, "after": n + k, "added": k} and res["after_success"] == n + k
    steps = np.load(tmp_path / "refine_job.json.success.npz")["gvae_step"]
    np.testing.assert_array_equal(steps, [0] * n + [1] * k)
    # cancel and failure: reported, nothing changed
    assert res["cancel_flag"] and res["cancel"]["error"] == "Refine cancelled" and res["cancel"]["unchanged"]
    assert res["cancel_state_same"]
    assert res["fail"]["error"] == "stand-in failure" and res["fail_state_same"]
    # the mesh was replaced meanwhile: not overwritten
    assert "changed while it was being refined" in res["changed"]["error"] and res["changed_vertices"] == 1
    # the real refine: cancelled at its first progress report, then run through
    assert res["real_available"]
    assert res["real_cancel"]["error"] == "Refine cancelled" and res["real_cancel_state_same"]
    assert any("Hessian" in m for m in res["real_messages"]), res["real_messages"]
    info = res["real_info"]
    assert info["before"] == n + k and info["after"] == res["real_after"] == info["before"] + info["added"]
    # the modal operator: events pass through while it runs, Esc cancels, status bar cleared
    assert res["poll_while_running"] is False
    m = res["modal_cancel"]
    assert m["results"] == ["CANCELLED"] and m["passed_through"] >= 10 and m["status_progress"]
    assert m["status_cleared"] and m["running_cleared"] and m["state_same"]
    assert m["reports"] == [[["WARNING"], "Refine cancelled; the object is unchanged"]]
    f = res["modal_finish"]
    assert f["result"] == ["FINISHED"] and f["reports"][0][0] == ["INFO"] and "Refine:" in f["reports"][0][1]
    assert f["vertices"] > res["real_after"]
    # invoke without a window runs to the end, like execute
    assert res["invoke"] == ["FINISHED"] and res["invoke_vertices"] > f["vertices"]
    assert res["checked_vertices"] == res["invoke_vertices"]  # the fidelity check, tolerance 0: all put back
    before, after, undone, redone = res["undo"]
    assert after > before and undone == before and redone == after  # one undo step


def test_compact_job_batch_button_and_undo(extension_zip, tmp_path):
    """Compact runs through the same job as Refine: cancel and a bad count leave the object as it
    was; a run keeps every attribute (the input's values where nothing was merged) and one undo
    step takes it back."""
    pytest.importorskip("torch", reason="Compact needs PyTorch (an optional runtime in Blender)")
    requires_blender_torch()  # (the Python that runs Blender, not this one: none for Blender 5.1+ here)
    n = 60
    cloud = make_cloud(n, degree=1)
    src = tmp_path / "in.ply"
    write_ply(cloud, src)
    res = run_scenario("compact_job", tmp_path, extension_zip, ply=str(src))
    assert res["available"]
    assert res["cancel"]["error"] == "Compact cancelled" and res["cancel_same"]
    assert "count must be between 1 and the input's 60" in res["bad"]["error"] and res["bad_same"]
    assert res["info"]["before"] == n and res["info"]["after"] == n // 2 and res["info"]["psnr"] > 10
    assert res["info"]["warnings"] == []  # (the views see it all; the operator reports each warning there is)
    # progress while it ran (which parts a 50 ms poll catches depends on the machine), the summary last
    assert res["messages"] and set(res["messages"]) <= {"starting", "scoring", "Hessian", "removing", "merging:",
                                                        "comparing"}, res["messages"]
    assert "60 Gaussians in, 30 out" in res["last_message"], res["last_message"]
    got = np.load(tmp_path / "compact_job.json.job.npz")
    assert len(got["position"]) == n // 2 and {"f_dc_0", "f_rest_8", "label", "big", "weight"} <= set(got.files)
    ids = np.ascontiguousarray(got["big"]).view(np.int64).ravel()  # (int64 is stored as two int32s)
    assert set(ids.tolist()) <= set(cloud.extra["big"].tolist())  # a kept Gaussian carries its own extras
    assert res["batch"] == ["FINISHED"] and res["batch_vertices"] == n // 4 and "gvae_dilation_3D" in res["batch_attrs"]
    assert res["invoke"] == ["FINISHED"] and res["invoke_vertices"] == 5
    before, after, undone, redone = res["undo"]
    assert (before, after, undone, redone) == (5, 2, 5, 2)


def test_refine_with_the_captures_images(extension_zip, tmp_path):
    """The panel's Images folder reaches the core's fit through the same job: another scene's images
    are refused with the object unchanged; the capture's are fitted, reported with what the fit
    measured on them, and undone in one step."""
    pytest.importorskip("torch", reason="the real refine needs PyTorch (an optional runtime in Blender)")
    requires_blender_torch()
    from tests.test_superres import _capture, _write_capture  # noqa: PLC0415 - the synthetic capture

    _, trained, views = _capture(n_views=4, n=150)
    src = tmp_path / "in.ply"
    write_ply(trained, src)
    folder = _write_capture(views, tmp_path / "capture")
    _, _, others = _capture(n_views=4, n=150, seed=5)
    wrong = _write_capture(type(others)(others.cameras, 1.0 - others.images), tmp_path / "other")
    res = run_scenario("refine_images", tmp_path, extension_zip, ply=str(src), images=str(folder), wrong=str(wrong))
    assert res["available"]
    assert "not the images the cloud was trained on" in res["wrong"]["error"], res["wrong"]
    assert res["wrong"]["unchanged"] and res["wrong_same"]
    report = res["_output"].split("--- refine with the capture's images")[1]
    assert "Refine: fitted to 4 training images (24 px" in report and " dB (" in report, report
    before, after, undone, redone = res["undo"]
    assert after >= before and undone == before and redone == after
    assert {"gvae_octave_limit", "gvae_octave_opacity", "gvae_octave_scale_0"} <= set(res["octave_attrs"])
    assert res["settings"] == ["images", "image_height"] and res["job_fields"]


def test_compact_scores_from_the_cameras_found_beside_the_imported_file(extension_zip, tmp_path):
    """An import remembers its file; Compact hands the core the training cameras found beside it (the
    reference 3DGS's MODEL/cameras.json two folders up), none with Training Cameras off, the Cameras
    path's when one is given, saying which; with Photos, the capture's images at the height the splat
    was trained at and the core's default removal, and the report carries the fine-tuning's figures."""
    requires_blender_torch()  # (gvae_core.capture, in Blender's Python)
    from gvae_core import Camera  # noqa: PLC0415
    from gvae_core.capture.gs_cameras import write_gs_cameras  # noqa: PLC0415

    cloud = make_cloud(40, degree=1)
    model = tmp_path / "model"
    (model / "point_cloud" / "iteration_7").mkdir(parents=True)
    src = write_ply(cloud, model / "point_cloud" / "iteration_7" / "point_cloud.ply")
    centre = np.asarray(cloud.means, np.float64).mean(0)
    cams = [Camera.look_at(centre + 4.0 * np.array(d), centre, width=64, height=48)
            for d in ((1, 0, 0.3), (0, 1, 0.3), (-1, 0, 0.3))]
    write_gs_cameras(cams, ["a", "b", "c"], model / "cameras.json")
    write_gs_cameras(cams[:2], ["a", "b"], tmp_path / "two.json")
    photos = tmp_path / "photos"  # the capture's photos: a transforms_train.json and its four images
    photos.mkdir()
    frames = []
    for i, cam in enumerate(cams + [Camera.look_at(centre + (0.0, -4.0, 1.2), centre, width=64, height=48)]):
        Image.new("RGB", (cam.width, cam.height), (90, 120, 150)).save(photos / f"r_{i}.png")
        frames.append({"file_path": f"r_{i}", "transform_matrix": cam.to_blender_c2w().tolist()})
    (photos / "transforms_train.json").write_text(json.dumps({"camera_angle_x": cams[0].fov_x, "frames": frames}))
    res = run_scenario("compact_cameras", tmp_path, extension_zip, ply=str(src), cameras=str(tmp_path / "two.json"),
                       images=str(photos))
    assert res["source"] == str(src)
    assert res["got"] == [[3, None, "merge"], [None, None, "merge"], [2, None, "merge"], [None, 4, None]]
    assert "scoring from 3 training cameras from" in res["notes"][0][-1] and res["notes"][1] == []
    assert res["notes"][2] == [f"scoring from 2 cameras of {tmp_path / 'two.json'}"]
    assert res["notes"][3][0].startswith(f"fine-tuning on 4 photos of {photos} at ")
    assert res["tuned"][:3] == [[], [], []] and res["tuned"][3][0]["psnr_after"] == 21.5
