"""Structure from motion (pycolmap): a photo set the project renders from known cameras comes back
as a COLMAP capture whose cameras are the true ones up to a similarity (rotations within 1 degree,
centres within 1% of the scene); the same photos with their known cameras and no points get
points on the surface by triangulation; bad input (one photo, an unreadable photo, photos that
share nothing) gets a clear error and a cancelled run leaves the folder as it was."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from gvae_core.capture import read_capture
from gvae_core.capture.dataset import find_photos, triangulated_folder
from gvae_core.capture import sfm
from gvae_core.capture.sfm import (SfMCancelled, SfMError, SfMOptions, ensure_capture, needs_sfm, pending_work,
                                   pose_pairs, run_sfm, sequential_pairs)
from gvae_core.cli import build_parser, main
from gvae_core.cli.sfm import sfm_options
from gvae_core.datasets import DatasetError

from .photo_set import SCENE_SIZE, on_surface, photo_set, relative_rotation_errors, ring_cameras, similarity

#: Small photos: SIFT and matching in seconds.
CAMERAS = ring_cameras(20, 320, 240)
OPTIONS = SfMOptions(threads=2)


def _listing(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    folder = tmp_path_factory.mktemp("photos")
    photo_set(folder, CAMERAS)
    return folder


@pytest.fixture(scope="module")
def solved(photos, tmp_path_factory):
    """The photo set solved by SfM, with the progress it reported."""
    folder = tmp_path_factory.mktemp("solved") / "capture"
    shutil.copytree(photos, folder)  # the photos in the folder itself (not in images/)
    _unrelated(folder / "zz_elsewhere.png", 320, 240)  # a photo of something else: left out, and said
    said = []
    with pytest.warns(UserWarning, match="1 of 21 photos could not be registered and are left out: zz_elsewhere.png"):
        report = run_sfm(folder, OPTIONS, progress=lambda stage, fraction, message: said.append((stage, fraction)))
    return folder, report, said


def _unrelated(path, width, height, seed=3):
    """A photo of a random texture that no other photo shares."""
    small = np.random.default_rng(seed).random((height // 10, width // 10, 3))
    Image.fromarray((np.kron(small, np.ones((10, 10, 1))) * 255).astype(np.uint8)).save(path)


def test_sfm_recovers_the_cameras_up_to_a_similarity(solved):
    folder, report, said = solved
    assert report.registered == [f"view_{k:02d}.png" for k in range(len(CAMERAS))]
    assert report.left_out == ["zz_elsewhere.png"] and "left out (not registered): zz_elsewhere.png" in report.summary()
    assert report.points > 100 and report.reprojection_error < 1.0 and report.cameras == 1
    assert set(report.seconds) == {"features", "matching", "mapping"}
    # COLMAP's own layout beside the photos, nothing else left behind
    assert {p.name for p in (folder / "sparse" / "0").iterdir()} >= {"cameras.bin", "images.bin", "points3D.bin"}
    assert (folder / "database.db").is_file() and not list(folder.glob(".gvae-*"))
    # progress per stage, in order, each reaching its end
    stages = [s for k, (s, _) in enumerate(said) if k == 0 or said[k - 1][0] != s]
    assert stages == ["features", "matching", "mapping"]
    assert all(max(f for s, f in said if s == stage) == 1.0 for stage in stages)

    with pytest.warns(UserWarning, match="1 of 21 photos are not in the COLMAP model .* zz_elsewhere.png"):
        capture = read_capture(folder)  # training then uses the registered ones
    assert capture.kind == "colmap" and len(capture) == len(CAMERAS)
    assert capture.points is not None and len(capture.points) == report.points
    true = {f"view_{k:02d}": cam for k, cam in enumerate(CAMERAS)}
    got = np.stack([c.center for c in capture.cameras])
    want = np.stack([true[n].center for n in capture.names])
    s, r, t = similarity(got, want)
    centre_error = np.linalg.norm(s * got @ r.T + t - want, axis=1) / SCENE_SIZE
    assert centre_error.max() < 0.01, centre_error
    for cam, name in zip(capture.cameras, capture.names):
        rel = true[name].rotation @ (cam.rotation @ r.T).T
        assert math.degrees(math.acos(np.clip((np.trace(rel) - 1) / 2, -1, 1))) < 1.0, name
    assert abs(capture.cameras[0].fx / CAMERAS[0].fx - 1) < 0.02  # the focal length found, not the guess


def test_sfm_finds_a_principal_point_off_the_centre(tmp_path):
    """Photos through a lens whose principal point is 19 px right and 10 px up of the centre (320 x 240,
    hand-held tilts): the final bundle adjustment finds it within 1 px, and the relative rotations
    come out within 0.5 degrees (held at the centre, the offset went into them: 3.9 degrees); photos
    through a centred lens keep the centre (`solved`)."""
    cams = ring_cameras(20, 320, 240, roll=25, principal_point=(0.06, -0.04))
    photo_set(tmp_path / "lens", cams)
    run_sfm(tmp_path / "lens", OPTIONS)
    capture = read_capture(tmp_path / "lens", images=False)
    photo = capture.photo_cameras[0]
    assert abs(photo.cx - cams[0].cx) < 1.0 and abs(photo.cy - cams[0].cy) < 1.0, (photo.cx, photo.cy)
    errors = relative_rotation_errors(capture, {f"view_{k:02d}": c for k, c in enumerate(cams)})
    assert np.median(errors) < 0.5, np.median(errors)


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_past_a_few_dozen_photos_retrieval_matches_fewer_pairs_for_the_same_cameras(mapper, photos, tmp_path,
                                                                                    monkeypatch):
    """Above EXHAUSTIVE_UP_TO photos `auto` matches each photo only with those a vocabulary tree of
    the photos' own features retrieves (here the 6 most alike of 20, where every pair is 190): every
    photo still registered and the cameras the true ones, by either mapper."""
    import pycolmap  # noqa: PLC0415 - SfM's own dependency, for the database it wrote

    monkeypatch.setattr(sfm, "EXHAUSTIVE_UP_TO", 10)
    folder = tmp_path / "retrieved"
    shutil.copytree(photos, folder)
    report = run_sfm(folder, SfMOptions(threads=2, mapper=mapper, retrieved=6))
    assert report.matcher == "vocabtree" and len(report.registered) == len(CAMERAS)
    with pycolmap.Database.open(folder / "database.db") as db:
        pairs = db.num_matched_image_pairs()
    assert len(CAMERAS) <= pairs <= 6 * len(CAMERAS) < len(CAMERAS) * (len(CAMERAS) - 1) // 2
    errors = relative_rotation_errors(read_capture(folder, images=False),
                                      {f"view_{k:02d}": c for k, c in enumerate(CAMERAS)})
    assert np.median(errors) < 1.0, np.median(errors)


def test_a_centred_lens_keeps_its_centre(solved):
    folder, _, _ = solved
    photo = read_capture(folder, images=False).photo_cameras[0]
    assert (photo.cx, photo.cy) == (160.0, 120.0)


def test_pending_work_says_what_ensure_capture_would_run(photos, tmp_path):
    """Photos without cameras: structure from motion; posed photos over a transparent background
    (an object that starts from its masks' hull) need no points; neither imports pycolmap."""
    assert pending_work(photos) == "structure from motion" == pending_work(photos, points=False)
    folder = tmp_path / "object"
    folder.mkdir()
    cam = CAMERAS[0]
    rgba = np.zeros((cam.height, cam.width, 4), np.uint8)
    rgba[40:80, 40:80] = 200  # an opaque square on a transparent background
    Image.fromarray(rgba, "RGBA").save(folder / "a.png")
    meta = {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
            "frames": [{"file_path": "a.png", "transform_matrix": cam.to_blender_c2w().tolist()}]}
    (folder / "transforms.json").write_text(json.dumps(meta))
    assert pending_work(folder) is None
    with pytest.raises(DatasetError):
        pending_work(tmp_path / "missing")


def test_a_solved_folder_is_reused_not_redone(solved):
    folder, report, _ = solved
    before = {p: p.stat().st_mtime_ns for p in folder.rglob("*")}
    assert not needs_sfm(folder) and ensure_capture(folder) is None
    with pytest.warns(UserWarning, match="zz_elsewhere.png"):  # (reading the capture says what SfM left out)
        assert pending_work(folder) is None
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*")} == before
    with pytest.raises(DatasetError, match="already"):
        run_sfm(folder)


def test_triangulation_with_known_cameras_puts_the_points_on_the_surface(photos, tmp_path):
    """A transforms.json with the true cameras and no points: points triangulated with them lie on
    the scene's surfaces, and the capture then reads them (until its poses change)."""
    folder = tmp_path / "posed"
    (folder / "images").mkdir(parents=True)
    frames = []
    for k, cam in list(enumerate(CAMERAS))[::2]:  # every other photo: with the poses known, that is enough
        shutil.copy(photos / f"view_{k:02d}.png", folder / "images")
        frames.append({"file_path": f"images/view_{k:02d}.png", "transform_matrix": cam.to_blender_c2w().tolist()})
    cam = CAMERAS[0]
    meta = {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
            "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    assert read_capture(folder).points is None
    assert pending_work(folder) == "triangulation" and pending_work(folder, points=False) is None
    assert ensure_capture(folder, OPTIONS, points=True) is None
    assert pending_work(folder) is None
    points = read_capture(folder).points
    assert points is not None and len(points) > 50
    # Within a few tenths of a percent of the scene: the splats' texture itself sits that far off the
    # surface (a nearer splat covers its neighbours' edges, a shift away from each camera).
    d = on_surface(points.xyz) / SCENE_SIZE
    assert np.median(d) < 0.0025 and np.percentile(d, 90) < 0.005, (np.median(d), np.percentile(d, 90))
    assert triangulated_folder(read_capture(folder)) == folder / "triangulated"
    # other poses (the scene moved): the points are not these cameras' any more
    for f in frames:
        f["transform_matrix"][0][3] += 0.5
    (folder / "transforms.json").write_text(json.dumps(meta))
    assert read_capture(folder).points is None


def test_pose_pairs_are_the_cameras_that_look_at_the_same_place():
    cams = ring_cameras(24)
    names = [f"v{k}" for k in range(24)]
    pairs = pose_pairs(cams, names, neighbours=6)
    steps = {min((int(b[1:]) - int(a[1:])) % 24, (int(a[1:]) - int(b[1:])) % 24) for a, b in pairs}
    assert {1, 2, 3} <= steps and max(steps) <= 6  # neighbours on the ring; never across it
    assert all(sum(name in p for p in pairs) >= 6 for name in names)
    assert len(pose_pairs(cams[:5], names[:5])) == 10  # few photos: every pair
    seq = sequential_pairs([f"f{k:03d}" for k in range(40)], overlap=5)
    assert ("f000", "f005") in seq and ("f000", "f006") not in seq and ("f000", "f008") in seq


def test_bad_photo_sets_get_clear_errors_and_leave_the_folder_as_it_was(photos, tmp_path):
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(photos / "view_00.png", one)
    with pytest.raises(SfMError, match="at least 3"):
        run_sfm(one, OPTIONS)

    broken = tmp_path / "broken"
    shutil.copytree(photos, broken)
    (broken / "view_05.png").write_bytes(b"not a picture at all")
    with pytest.raises(DatasetError, match="view_05.png: cannot read this photo"):
        run_sfm(broken, OPTIONS)

    unrelated = tmp_path / "unrelated"
    unrelated.mkdir()
    for k in range(4):  # four different textures: no two photos of one scene
        _unrelated(unrelated / f"p{k}.png", 160, 120, seed=k)
    before = _listing(unrelated)
    with pytest.raises(SfMError, match="registered|separate models") as err:
        run_sfm(unrelated, OPTIONS)
    assert "overlap" in str(err.value)
    assert _listing(unrelated) == before

    # a photo folder read without SfM says what makes cameras
    with pytest.raises(DatasetError, match="gvae sfm"):
        read_capture(unrelated)


def test_cancelled_sfm_leaves_the_folder_as_it_was(photos, tmp_path):
    folder = tmp_path / "cancel"
    shutil.copytree(photos, folder)
    before = _listing(folder)
    stages = []
    with pytest.raises(SfMCancelled):
        run_sfm(folder, OPTIONS, progress=lambda stage, fraction, message: stages.append(stage),
                cancel=lambda: "matching" in stages)
    assert _listing(folder) == before and needs_sfm(folder)
    assert find_photos(folder)[1] == [f"view_{k:02d}.png" for k in range(len(CAMERAS))]


def test_gvae_train_takes_a_folder_of_photos(solved, photos, tmp_path, capsys, monkeypatch):
    """`gvae train PHOTOS`: structure from motion first when the folder has no cameras (the options
    passed on), then training from its SfM points; a solved folder is trained as it is."""
    folder, report, _ = solved
    run = tmp_path / "run"
    with pytest.warns(UserWarning, match="zz_elsewhere.png"):  # trained on the registered photos, the rest named
        assert main(["train", str(folder), "--out", str(run), "--resolutions", "24", "--iterations", "20",
                     "--init-count", "300", "--threads", "1", "--quiet", "--test-every", "5"]) == 0
    log = json.loads((run / "log.json").read_text())
    assert f"{report.points} SfM points" in log[0]["start"] and log[-1]["test_psnr"] is not None
    assert "structure from motion" not in capsys.readouterr().out  # reused, not redone

    calls = []

    def fake_sfm(path, options=None, **kwargs):
        calls.append((Path(path), options))
        raise SfMCancelled("stop here")

    monkeypatch.setattr(sfm, "run_sfm", fake_sfm)
    unsolved = tmp_path / "unsolved"
    shutil.copytree(photos, unsolved / "images")
    with pytest.raises(SfMCancelled):
        main(["train", str(unsolved), "--out", str(tmp_path / "run2"), "--matcher", "sequential", "--camera",
              "per-image", "--sfm-image-size", "800"])
    assert calls == [(unsolved, SfMOptions(matcher="sequential", camera="per-image", max_image_size=800))]
    assert sfm_options(build_parser("sfm").parse_args(["sfm", "photos"])) == SfMOptions()  # the same defaults


@pytest.mark.parametrize("command", [["render", "in.ply", "--out", "o", "--cameras"],
                                     ["refine", "in.ply", "out.ply", "--images"],
                                     ["compact", "in.ply", "out.ply", "--keep", "0.5", "--images"],
                                     ["compact", "in.ply", "out.ply", "--keep", "0.5", "--cameras"]])
def test_every_command_that_takes_a_capture_runs_sfm_on_a_folder_of_photos(command, photos, tmp_path, monkeypatch):
    calls = []

    def fake_sfm(path, options=None, **kwargs):
        calls.append(Path(path))
        raise SfMCancelled("stop here")

    monkeypatch.setattr(sfm, "run_sfm", fake_sfm)
    with pytest.raises(SfMCancelled):
        main([str(tmp_path / a) if a.endswith(".ply") else a for a in command] + [str(photos)])
    assert calls == [photos]
