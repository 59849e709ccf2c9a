"""Structure from motion on the CPU (pycolmap): a folder of photos becomes a COLMAP capture, and a
capture with poses but no points gets its points.

Nothing here is hand-written geometry: pycolmap (COLMAP's bindings, BSD-3, pinned) extracts SIFT
features, matches them and maps incrementally; this module chooses its options, runs its stages
with progress and cancellation, checks what came out and writes it where every 3DGS tool looks.

- `run_sfm(folder)`: the photos in `folder` (or in its `images/`) -> `folder/sparse/0` (cameras,
  images, points3D, binary) and `folder/database.db`, COLMAP's own layout, so the next run, COLMAP's
  GUI, gsplat and nerfstudio read it (the reference 3DGS's train.py wants undistorted PINHOLE
  cameras: `colmap image_undistorter` first; this project undistorts on load, `capture.lens`).
  Matching: exhaustive up to `EXHAUSTIVE_UP_TO` photos, else each photo with the `RETRIEVED` most
  like it by a vocabulary tree built from the photos' own descriptors (no download);
  `sequential` for the frames of a video in name order. Mapping: incremental, or global (GLOMAP).
  One shared camera when the photos share a size and lens (EXIF make, model, focal length), one
  per photo otherwise or when asked. The model with the most photos is kept; fewer than all
  registered is a warning naming the rest (training then uses the registered ones); fewer than
  `MIN_REGISTERED`, or several models of which none holds most photos, is an `SfMError` that says
  what to try. Everything is written to a hidden folder beside the photos and moved into place at
  the end: a failed or cancelled run leaves the folder as it was.
- `triangulate(capture)`: a capture with poses and no points (a transforms.json without
  `ply_file_path`, a COLMAP model without points3D): its photos (undistorted, `capture.lens`)
  matched in pairs that the poses say overlap, points triangulated with the given cameras
  (pycolmap's point triangulation, the poses held fixed), written as a COLMAP model in
  `triangulated/` beside the capture; `read_capture` takes its points from there while the poses
  agree.
- `ensure_capture(path)`: what every command calls first: SfM when `path` is a folder of photos
  with no model (and, with `points`, triangulation when it has poses and no points); nothing when
  there is nothing to do (the model is reused, not redone). `pending_work(path)` says which, before.

Progress: `progress(stage, fraction, message)` during every stage; `cancel()` is polled a few
times a second and stops pycolmap inside a stage (`SfMCancelled`). pycolmap is imported only when
SfM runs (`gvae info` and friends start without it).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..camera import look_target
from ..datasets import DatasetError, resize_rgba
from .dataset import PHOTO_SUFFIXES, TRIANGULATED, find_capture, find_photos, read_capture, triangulated_folder

__all__ = ["SfMOptions", "SfMReport", "SfMError", "SfMCancelled", "MATCHERS", "MAPPERS", "CAMERA_MODES",
           "EXHAUSTIVE_UP_TO", "RETRIEVED", "MIN_REGISTERED", "SFM_IMAGE_SIZE", "TRIANGULATED", "needs_sfm",
           "needs_points", "pending_work", "run_sfm", "ensure_capture", "triangulate", "pose_pairs",
           "PYCOLMAP_VERSION"]

#: The pycolmap release this module is written and tested against (pyproject pins it).
PYCOLMAP_VERSION = "4.2.1"
#: What `--matcher` takes: auto (exhaustive up to EXHAUSTIVE_UP_TO photos, vocabtree beyond).
MATCHERS = ("auto", "exhaustive", "sequential", "vocabtree")
#: What `--mapper` takes: COLMAP's incremental mapping, or global mapping (GLOMAP: rotation
#: averaging, then all positions at once; one bundle adjustment instead of one per added photo).
MAPPERS = ("incremental", "global")
#: What `--camera` takes: auto (one shared camera when the photos share size and lens), single, per-image.
CAMERA_MODES = ("auto", "single", "per-image")
#: `auto` matches every pair up to this many photos (1,225 pairs at 50, ~5k at 100, ~45k at 300)...
EXHAUSTIVE_UP_TO = 50
#: ... and beyond, each photo with the `RETRIEVED` photos most like it by a vocabulary tree (pairs
#: growing with the photos, not their square; docs/benchmarks/training.md measures the cameras).
RETRIEVED = 25
#: Features are found on photos scaled to at most this many pixels on the long side: plenty for the
#: poses of a splat trained at a quarter of a phone photo or less, and 2-4x faster to match than at
#: COLMAP's own 3200 (photos larger than that for SIFT give more features than the matcher needs).
SFM_IMAGE_SIZE = 1000
#: A principal point found further than this share of the image's size from its centre is not
#: believed (the model keeps the centre).
PRINCIPAL_POINT_LIMIT = 0.15
#: ... and one that lowers the mean reprojection error by less than this share is not either.
PRINCIPAL_POINT_GAIN = 0.02
#: Fewer registered photos than this is no capture.
MIN_REGISTERED = 3
#: What to try when SfM does not register the photos (said in every such error).
SFM_HINTS = ("photos that overlap more (each part of the scene in several photos, from nearby viewpoints), "
             "`--matcher sequential` for the frames of a video, or a larger `--sfm-image-size`")

Progress = Callable[[str, float, str], None]


class SfMError(DatasetError):
    """Structure from motion could not make a capture of these photos (the message says what to try)."""


class SfMCancelled(RuntimeError):
    """`cancel()` asked to stop; nothing was written."""


@dataclass
class SfMOptions:
    """How SfM runs. `matcher`: one of MATCHERS; `mapper`: one of MAPPERS; `camera`: one of
    CAMERA_MODES; `retrieved`: photos matched with each by the vocabulary tree; `max_image_size`:
    features are found at most this many pixels on the long side (the photo is scaled down for
    them; the model keeps the photo's size); `max_features` per photo; `threads` (None: all
    cores); `seed`: pycolmap's random seed (the same photos give the same model)."""

    matcher: str = "auto"
    mapper: str = "incremental"
    camera: str = "auto"
    retrieved: int = RETRIEVED
    max_image_size: int = SFM_IMAGE_SIZE
    max_features: int = 8192
    threads: int | None = None
    seed: int = 0

    def __post_init__(self):
        if self.matcher not in MATCHERS:
            raise ValueError(f"SfM matcher must be one of {', '.join(MATCHERS)}, got {self.matcher!r}")
        if self.mapper not in MAPPERS:
            raise ValueError(f"SfM mapper must be one of {', '.join(MAPPERS)}, got {self.mapper!r}")
        if self.camera not in CAMERA_MODES:
            raise ValueError(f"SfM camera mode must be one of {', '.join(CAMERA_MODES)}, got {self.camera!r}")
        if int(self.retrieved) < 2:
            raise ValueError(f"SfM retrieval needs at least 2 photos per photo, got {self.retrieved}")
        if int(self.max_image_size) < 64:
            raise ValueError(f"SfM image size must be at least 64 px, got {self.max_image_size}")


@dataclass
class SfMReport:
    """What SfM did (`summary()` says it in a few lines): the photos it was given (names), those
    in the model, the model's points, mean reprojection error (px), cameras, seconds per stage,
    where the model is, which matcher ran, and whether an existing model was reused."""

    folder: Path
    photos: list[str]
    registered: list[str]
    points: int
    reprojection_error: float
    cameras: int
    model: Path
    matcher: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    reused: bool = False

    @property
    def left_out(self) -> list[str]:
        """The photos SfM could not register (not in the model)."""
        registered = set(self.registered)
        return [p for p in self.photos if p not in registered]

    def summary(self) -> str:
        head = "reused the model" if self.reused else "structure from motion"
        lines = [f"{head} {self.model}: {len(self.registered)} of {len(self.photos)} photos registered, "
                 f"{self.points} points, mean reprojection error {self.reprojection_error:.2f} px, "
                 f"{self.cameras} camera(s)"]
        if self.seconds:
            lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in self.seconds.items())
                         + f" ({sum(self.seconds.values()):.1f} in all" + (f"; {self.matcher} matching)"
                                                                              if self.matcher else ")"))
        if self.left_out:
            lines.append(f"left out (not registered): {_names(self.left_out)}")
        return "\n".join(lines)


def _names(names: list[str], shown: int = 8) -> str:
    return ", ".join(names[:shown]) + (f", ... ({len(names) - shown} more)" if len(names) > shown else "")


# ------------------------------------------------------------------ what a folder holds

def needs_sfm(path) -> bool:
    """Whether `path` is a folder of photos (in it or its `images/`) with no cameras: no COLMAP
    model and no transforms file."""
    folder = Path(path)
    if not folder.is_dir() or not find_photos(folder)[1]:
        return False
    try:
        find_capture(folder)
        return False
    except DatasetError:
        return True


def _check_photos(folder: Path, names: list[str]) -> tuple[list[tuple[int, int]], list[tuple]]:
    """Each photo's size and its lens (EXIF make, model, focal length); DatasetError naming a photo
    that cannot be read."""
    sizes, lenses = [], []
    for name in names:
        path = folder / name
        try:
            with Image.open(path) as im:
                im.verify()
            with Image.open(path) as im:
                size = im.size
                exif = im.getexif()
                focal = exif.get_ifd(0x8769).get(0x920A) if exif else None
                lenses.append((exif.get(0x010F), exif.get(0x0110), None if focal is None else float(focal)))
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
            raise DatasetError(f"{path}: cannot read this photo ({exc}); remove it or convert it to JPEG or "
                               f"PNG") from None
        sizes.append(size)
    return sizes, lenses


# ------------------------------------------------------------------ running pycolmap stages

def _pycolmap():
    try:
        import pycolmap  # noqa: PLC0415 - only SfM needs it, and it is large
    except ImportError:
        raise DatasetError(f"structure from motion needs pycolmap: pip install pycolmap=={PYCOLMAP_VERSION}") from None
    pycolmap.logging.minloglevel = 2  # errors only: pycolmap's progress is ours to say
    pycolmap.logging.stderrthreshold = 2
    return pycolmap


def _stage(name: str, work: Callable, cancel: Callable[[], bool] | None, poll: Callable[[], None] | None = None):
    """Run `work(token)` (a pycolmap call given a CancellationToken) in a thread, polling
    `cancel()` (and calling `poll()`, for progress) a few times a second: SfMCancelled once
    cancelled (pycolmap stopped first), pycolmap's exception re-raised."""
    pycolmap = _pycolmap()
    token = pycolmap.CancellationToken()
    out: dict = {}

    def target():
        try:
            out["result"] = work(token)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            out["error"] = exc

    if cancel is not None and cancel():
        raise SfMCancelled(f"cancelled before {name}")
    thread = threading.Thread(target=target, name=f"sfm-{name}", daemon=True)
    thread.start()
    while thread.is_alive():
        try:
            thread.join(0.25)
            stop = cancel is not None and cancel()
        except KeyboardInterrupt:  # Ctrl-C: stop pycolmap before its work folder goes
            stop = True
        if stop:
            token.cancel()
            thread.join()
            raise SfMCancelled(f"cancelled during {name}")
        if poll is not None:
            poll()
    if "error" in out:
        raise out["error"]
    if token.is_cancelled:
        raise SfMCancelled(f"cancelled during {name}")
    return out.get("result")


def _work_folder(parent: Path, kind: str) -> Path:
    """A hidden folder in `parent` for one run's files (moved into place at the end), named for this
    process; those of runs whose process is gone (killed before they could clean up) are removed."""
    for old in parent.glob(f".gvae-{kind}-*"):
        try:
            pid = int(old.name.split("-")[2])
            os.kill(pid, 0)
        except (IndexError, ValueError, ProcessLookupError):
            shutil.rmtree(old, ignore_errors=True)
        except PermissionError:  # another user's live process
            pass
    try:
        return Path(tempfile.mkdtemp(prefix=f".gvae-{kind}-{os.getpid()}-", dir=parent))
    except OSError as exc:
        raise DatasetError(f"{parent}: cannot write there ({exc}); copy the photos to a folder you can write "
                           f"to") from None


def _threads(options: SfMOptions) -> int:
    return -1 if options.threads is None else max(1, int(options.threads))


def _chunks(items: list, parts: int = 40, least: int = 1) -> list[list]:
    """`items` in about `parts` consecutive runs (at least `least` each): progress between them."""
    size = max(least, math.ceil(len(items) / parts))
    return [items[k:k + size] for k in range(0, len(items), size)]


def _in_chunks(name: str, chunks: list[list], call: Callable[[list, object], None], what: str,
               progress: Progress | None, cancel) -> float:
    """`call(chunk, token)` for each chunk as one stage: progress after each, cancellable in each."""
    t0 = time.perf_counter()
    total, done = sum(len(c) for c in chunks), 0
    for chunk in chunks:
        _stage(name, lambda token, chunk=chunk: call(chunk, token), cancel)
        done += len(chunk)
        if progress is not None:
            progress(name, done / max(total, 1), f"{name}: {done} of {total} {what}")
    return time.perf_counter() - t0


def _extract(pycolmap, database: Path, folder: Path, names: list[str], camera_mode, camera_model: str,
             options: SfMOptions, progress, cancel) -> float:
    """SIFT features of the photos `names` in `folder`, a few photos a call."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(options.max_image_size)
    extraction.num_threads = _threads(options)
    extraction.sift.max_num_features = int(options.max_features)
    if camera_mode == pycolmap.CameraMode.SINGLE:  # one camera across the calls: the first call's
        def call(chunk, token):
            if reader.existing_camera_id < 0 and database.is_file():
                with pycolmap.Database.open(database) as db:
                    reader.existing_camera_id = db.read_all_cameras()[0].camera_id
            pycolmap.extract_features(database, folder, image_names=chunk, camera_mode=camera_mode,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu, cancellation_token=token)
    else:
        def call(chunk, token):
            pycolmap.extract_features(database, folder, image_names=chunk, camera_mode=camera_mode,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu, cancellation_token=token)
    return _in_chunks("features", _chunks(names, 20, 4), call, "photos", progress, cancel)


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    """Every pair of photos."""
    return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]


def sequential_pairs(names: list[str], overlap: int = 10) -> list[tuple[str, str]]:
    """The frames of a video in name order: each with its next `overlap` frames and with those at
    powers of two beyond (COLMAP's sequential matcher with quadratic overlap)."""
    order = sorted(names)
    pairs = set()
    for i in range(len(order)):
        steps = list(range(1, overlap + 1)) + [2 ** k for k in range(int(math.log2(overlap)) + 1, 31)]
        for step in steps:
            if i + step >= len(order):
                break
            pairs.add((order[i], order[i + step]))
    return sorted(pairs, key=lambda p: (order.index(p[0]), order.index(p[1])))


def _match(pycolmap, database: Path, pairs: list[tuple[str, str]] | None, options: SfMOptions, work: Path,
           progress, cancel) -> float:
    """Match the features of `pairs` of photos (a few hundred pairs a call, with progress), or with
    `pairs` None the pairs a vocabulary tree of the photos' own features retrieves (one call)."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = _threads(options)
    if pairs is None:  # COLMAP's vocab_tree_builder + vocab_tree_matcher, the tree from these photos
        t0 = time.perf_counter()
        vocab = pycolmap.VocabTreePairingOptions()
        vocab.vocab_tree_path = _build_vocab_tree(pycolmap, database, work / "vocab_tree.bin", options)
        vocab.num_images = int(options.retrieved)
        vocab.num_threads = _threads(options)
        if progress is not None:
            progress("matching", 0.0, "matching: the pairs a vocabulary tree of the photos' features retrieves")
        _stage("matching", lambda token: pycolmap.match_vocabtree(
            database, matching_options=matching, pairing_options=vocab, device=pycolmap.Device.cpu,
            cancellation_token=token), cancel)
        if progress is not None:
            progress("matching", 1.0, "matching: done")
        return time.perf_counter() - t0
    pairs_file = work / "pairs.txt"

    def call(chunk, token):
        pairs_file.write_text("".join(f"{a} {b}\n" for a, b in chunk), encoding="utf-8")
        pycolmap.match_image_pairs(database, matching_options=matching,
                                   pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_file),
                                   device=pycolmap.Device.cpu, cancellation_token=token)

    return _in_chunks("matching", _chunks(pairs, 40, 50), call, "pairs", progress, cancel)


def _build_vocab_tree(pycolmap, database: Path, path: Path, options: SfMOptions, sample: int = 100_000) -> Path:
    """A visual-word index of up to `sample` of the photos' own SIFT descriptors (what COLMAP's
    vocab_tree_builder makes; 100 to 200 descriptors a word, 256 to 4,096 words), so retrieval needs
    no downloaded tree. Ten k-means iterations in one round: seconds, where COLMAP's three rounds of
    100 take minutes, and fine enough to rank a few hundred photos."""
    rng = np.random.default_rng(options.seed)
    with pycolmap.Database.open(database) as db:
        images = db.read_all_images()
        per = max(1, sample // max(len(images), 1))
        chunks = []
        for image in images:
            d = np.asarray(db.read_descriptors(image.image_id).data)
            chunks.append(d[rng.choice(len(d), per, replace=False)] if len(d) > per else d)
    descriptors = np.concatenate(chunks).astype(np.float32)
    index = pycolmap.VisualIndex.create(descriptors.shape[1], 64)
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words = int(min(4096, max(256, 2 ** int(math.log2(max(len(descriptors) // 100, 256))))))
    build.num_iterations = 10
    build.num_rounds = 1
    build.num_threads = _threads(options)
    index.build(build, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, descriptors))
    index.write(path)
    return path


def _map(pycolmap, database: Path, folder: Path, out: Path, n: int, options: SfMOptions, progress, cancel):
    """Incremental or global mapping (`options.mapper`); the reconstructions made (id -> Reconstruction)."""
    if options.mapper == "global":
        return _map_global(pycolmap, database, folder, out, n, options, progress, cancel)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = _threads(options)
    mapping.random_seed = int(options.seed)
    mapping.min_model_size = min(mapping.min_model_size, max(MIN_REGISTERED, n // 4))
    registered, said = [0], [-1]

    def next_image():
        registered[0] += 1

    def poll():
        if progress is not None and registered[0] != said[0]:
            said[0] = registered[0]
            progress("mapping", min((registered[0] + 1) / max(n, 1), 0.99), f"mapping: {registered[0] + 1} of {n} "
                     f"photos placed")

    out.mkdir(parents=True, exist_ok=True)
    return _stage("mapping", lambda token: pycolmap.incremental_mapping(
        database, folder, out, mapping, next_image_callback=next_image, cancellation_token=token), cancel, poll)


def _map_global(pycolmap, database: Path, folder: Path, out: Path, n: int, options: SfMOptions, progress, cancel):
    """Global mapping (pycolmap's GLOMAP). It takes no cancellation token: a cancel is seen when it
    returns; in several threads its model is not the same from run to run."""
    mapping = pycolmap.GlobalPipelineOptions()
    mapping.num_threads = mapping.mapper.num_threads = _threads(options)
    mapping.random_seed = mapping.mapper.random_seed = int(options.seed)
    mapping.min_model_size = min(mapping.min_model_size, max(MIN_REGISTERED, n // 4))
    if progress is not None:
        progress("mapping", 0.0, f"mapping: {n} photos at once (global)")
    out.mkdir(parents=True, exist_ok=True)
    return _stage("mapping", lambda token: pycolmap.global_mapping(database, folder, out, mapping), cancel)


# ------------------------------------------------------------------ SfM of a folder of photos

def _camera_mode(pycolmap, options: SfMOptions, sizes, lenses):
    if options.camera == "single":
        return pycolmap.CameraMode.SINGLE
    if options.camera == "per-image":
        return pycolmap.CameraMode.PER_IMAGE
    shared = len(set(sizes)) == 1 and len(set(lenses)) == 1
    return pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE


def run_sfm(path, options: SfMOptions | None = None, *, progress: Progress | None = None,
            cancel: Callable[[], bool] | None = None, overwrite: bool = False) -> SfMReport:
    """Structure from motion of the photos in `path` (or its `images/`): writes `path/sparse/0` and
    `path/database.db` (module docstring) and returns what it did. `overwrite`: replace a model
    that is there already (else that is an error: `ensure_capture` reuses it)."""
    options = options or SfMOptions()
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: no such folder (expected a folder of photos)")
    folder, names = find_photos(root)
    if not names:
        raise DatasetError(f"{root}: no photos (JPEG, PNG or TIFF) in it or in its images/ folder")
    if len(names) < MIN_REGISTERED:
        raise SfMError(f"{folder}: {len(names)} photo(s); structure from motion needs at least {MIN_REGISTERED} "
                       f"photos of the scene from different viewpoints (a few dozen for a good splat)")
    existing = root / "sparse" / "0"
    if existing.exists() and not overwrite:
        raise DatasetError(f"{existing}: a model is there already (use it, or overwrite it)")
    sizes, lenses = _check_photos(folder, names)
    pycolmap = _pycolmap()
    mode = _camera_mode(pycolmap, options, sizes, lenses)
    matcher = options.matcher if options.matcher != "auto" else (
        "exhaustive" if len(names) <= EXHAUSTIVE_UP_TO else "vocabtree")
    work = _work_folder(root, "sfm")
    try:
        database = work / "database.db"
        seconds = {"features": _extract(pycolmap, database, folder, names, mode, "SIMPLE_RADIAL", options, progress,
                                        cancel)}
        pairs = None if matcher == "vocabtree" else (
            sequential_pairs(names) if matcher == "sequential" else exhaustive_pairs(names))
        seconds["matching"] = _match(pycolmap, database, pairs, options, work, progress, cancel)
        t0 = time.perf_counter()
        models = _map(pycolmap, database, folder, work / "sparse", len(names), options, progress, cancel)
        seconds["mapping"] = time.perf_counter() - t0
        rec = _largest(models, folder, names)
        t0 = time.perf_counter()
        rec = refine_intrinsics(pycolmap, rec, options)
        seconds["mapping"] += time.perf_counter() - t0
        if progress is not None:
            progress("mapping", 1.0, f"mapping: {rec.num_reg_images()} of {len(names)} photos placed")
        model = work / "model"
        model.mkdir()
        rec.write_binary(model)
        report = SfMReport(root, names, sorted(img.name for img in rec.images.values() if img.has_pose),
                           rec.num_points3D(), float(rec.compute_mean_reprojection_error()), rec.num_cameras(),
                           existing, matcher, {k: round(v, 2) for k, v in seconds.items()})
        if cancel is not None and cancel():
            raise SfMCancelled("cancelled after mapping")
        _install(model, existing, database, root / "database.db")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if report.left_out:
        warnings.warn(f"{folder}: {len(report.left_out)} of {len(names)} photos could not be registered and are left "
                      f"out: {_names(report.left_out)}", stacklevel=2)
    return report


def refine_intrinsics(pycolmap, rec, options: SfMOptions):
    """`rec` after a final bundle adjustment that also frees every camera's principal point
    (incremental mapping holds it at the image centre, where a phone's is not, and the rotations and
    the distortion then absorb the offset), kept when it lowers the mean reprojection error by
    PRINCIPAL_POINT_GAIN or more (the photos constrain it; a centred one gains almost nothing) and
    every principal point stays within PRINCIPAL_POINT_LIMIT of its image's size from the centre;
    else `rec` as mapped."""
    refined = pycolmap.Reconstruction(rec)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_principal_point = True
    ba.ceres.solver_options.num_threads = _threads(options)
    pycolmap.bundle_adjustment(refined, ba)
    before, after = rec.compute_mean_reprojection_error(), refined.compute_mean_reprojection_error()
    plausible = all(abs(c.principal_point_x / c.width - 0.5) <= PRINCIPAL_POINT_LIMIT
                    and abs(c.principal_point_y / c.height - 0.5) <= PRINCIPAL_POINT_LIMIT
                    for c in refined.cameras.values())
    return refined if plausible and after <= (1.0 - PRINCIPAL_POINT_GAIN) * before else rec


def _largest(models: dict, folder: Path, names: list[str]):
    """The reconstruction with the most photos, or SfMError when it is no capture."""
    recs = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True) if models else []
    best = recs[0].num_reg_images() if recs else 0
    if best < MIN_REGISTERED:
        raise SfMError(f"{folder}: structure from motion registered {best} of {len(names)} photos (no two photos "
                       f"share enough features to start, or the photos share nothing); try {SFM_HINTS}")
    if len(recs) > 1 and 2 * best <= len(names):
        sizes = ", ".join(str(r.num_reg_images()) for r in recs[:6])
        raise SfMError(f"{folder}: the photos fall apart into {len(recs)} separate models ({sizes} photos), none "
                       f"holding most of the {len(names)}: they do not overlap enough to join; try {SFM_HINTS}")
    return recs[0]


def _install(model: Path, target: Path, database: Path, database_target: Path) -> None:
    """Move the finished model and its database into place (replacing those there, with
    `overwrite`): an old model is only removed once the new one is there."""
    target.parent.mkdir(parents=True, exist_ok=True)
    old = None
    if target.exists():
        old = model.with_name("old-model")
        os.replace(target, old)
    try:
        os.replace(model, target)
    except OSError:
        if old is not None:
            os.replace(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    os.replace(database, database_target)


# ------------------------------------------------------------------ poses without points

def pose_pairs(cameras, names: list[str], neighbours: int = 20) -> list[tuple[str, str]]:
    """Pairs of photos whose poses say they overlap: a pair looks at a common point (each camera's
    point along its axis at the distance where the cameras' axes meet, seen inside the other's
    image) with optical axes less than 90 degrees apart; each photo keeps its `neighbours`
    nearest such partners by camera distance. All pairs when that is not more."""
    n = len(cameras)
    if n - 1 <= neighbours:
        return [(names[i], names[j]) for i in range(n) for j in range(i + 1, n)]
    centers = np.stack([c.center for c in cameras])
    axes = np.stack([c.rotation[2] for c in cameras])
    target = look_target(cameras)
    depth = np.maximum(np.linalg.norm(centers - target, axis=1), 1e-9)
    looks = centers + axes * depth[:, None]
    sees = np.zeros((n, n), bool)  # sees[i, j]: camera i sees camera j's look point
    for i, cam in enumerate(cameras):
        uv, z = cam.project(looks)
        sees[i] = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    ok = (sees | sees.T) & (axes @ axes.T > 0.0)
    np.fill_diagonal(ok, False)
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    keep = set()
    for i in range(n):
        partners = np.flatnonzero(ok[i])
        if len(partners) == 0:  # nothing in view by the test: its nearest cameras
            partners = np.argsort(dist[i])[1:neighbours + 1]
        for j in partners[np.argsort(dist[i, partners])[:neighbours]]:
            keep.add((min(i, int(j)), max(i, int(j))))
    return [(names[i], names[j]) for i, j in sorted(keep)]


def triangulate(capture, *, max_image_size: int = SFM_IMAGE_SIZE, threads: int | None = None,
                progress: Progress | None = None, cancel: Callable[[], bool] | None = None) -> Path:
    """Points for a capture with poses and no points (module docstring): its photos, undistorted
    and scaled to at most `max_image_size` on the long side, SIFT, matched in `pose_pairs`,
    triangulated with the capture's cameras held fixed. Writes the model to `TRIANGULATED/` beside
    the capture (`dataset.triangulated_folder`) and returns that folder; SfMError when nothing could be
    triangulated."""
    pycolmap = _pycolmap()
    root = triangulated_folder(capture)
    frames = [i for i, f in enumerate(capture.files) if f is not None]
    if len(frames) < 2:
        raise SfMError(f"{capture.source}: {len(frames)} photo(s) with poses; triangulation needs two or more")
    options = SfMOptions(max_image_size=max_image_size, threads=threads)
    work = _work_folder(root.parent, "triangulate")
    try:
        t0 = time.perf_counter()
        photos, cams, names = _pinhole_photos(capture, frames, work, max_image_size, progress, cancel)
        seconds = {"photos": time.perf_counter() - t0}
        database = work / "database.db"
        seconds["features"] = _extract(pycolmap, database, photos, names, pycolmap.CameraMode.PER_IMAGE, "PINHOLE",
                                       options, progress, cancel)
        pairs = pose_pairs(cams, names)
        seconds["matching"] = _match(pycolmap, database, pairs, options, work, progress, cancel)
        t0 = time.perf_counter()
        rec = _posed_reconstruction(pycolmap, database, cams, names)
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.num_threads = _threads(options)
        out = work / "model"
        out.mkdir()
        if progress is not None:
            progress("triangulation", 0.0, f"triangulation: {len(names)} photos with their poses")
        rec = _stage("triangulation", lambda token: pycolmap.triangulate_points(
            rec, database, photos, out, clear_points=True, options=mapping, refine_intrinsics=False,
            cancellation_token=token), cancel)
        seconds["triangulation"] = time.perf_counter() - t0
        if rec.num_points3D() == 0:
            raise SfMError(f"{capture.source}: no points could be triangulated from the {len(names)} photos with "
                           f"their poses (do the poses belong to these photos?)")
        rec.write_binary(out)
        (out / "seconds.txt").write_text(" ".join(f"{k}={v:.2f}" for k, v in seconds.items()) + "\n")
        if cancel is not None and cancel():
            raise SfMCancelled("cancelled after triangulation")
        if root.exists():
            shutil.rmtree(root)
        os.replace(out, root)
        os.replace(database, root / "database.db")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return root


def _pinhole_photos(capture, frames: list[int], work: Path, max_image_size: int, progress, cancel):
    """(folder, cameras, names) of the frames' photos as pinhole images of at most `max_image_size`
    px: the files themselves when they are (one folder, no lens, small enough), else undistorted
    (`capture.lens`) and scaled copies in `work/images` (JPEG, quality 95)."""
    files = [capture.files[i] for i in frames]
    cams = [capture.cameras[i] for i in frames]
    if (all(capture.lenses[i].is_pinhole for i in frames) and len({f.parent for f in files}) == 1
            and max(max(c.width, c.height) for c in cams) <= max_image_size
            and all(f.suffix.lower() in PHOTO_SUFFIXES for f in files)):
        return files[0].parent, cams, [f.name for f in files]
    photos = work / "images"
    photos.mkdir()
    names = []
    for k, i in enumerate(frames):
        rgba = capture.frame_image(i)
        cam = cams[k]
        scale = min(1.0, max_image_size / max(cam.width, cam.height))
        if scale < 1.0:
            cams[k] = cam = cam.scaled(max(1, round(cam.height * scale)))
            rgba = resize_rgba(rgba, cam.height, cam.width)
        names.append(f"{capture.names[i]}.jpg")  # the frame's name: `read_capture` matches its pose by it
        Image.fromarray((np.clip(rgba[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)).save(photos / names[-1],
                                                                                      quality=95)
        if progress is not None:
            progress("photos", (k + 1) / len(frames), f"undistorting: {k + 1} of {len(frames)} photos")
        if cancel is not None and cancel():
            raise SfMCancelled("cancelled while undistorting the photos")
    return photos, cams, names


def _posed_reconstruction(pycolmap, database: Path, cams, names: list[str]):
    """A reconstruction holding the database's images with the given pinhole cameras and poses."""
    by_name = dict(zip(names, cams))
    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(database) as db:
        for image in db.read_all_images():
            cam = by_name[image.name]
            camera = db.read_camera(image.camera_id)
            camera.model = pycolmap.CameraModelId.PINHOLE
            camera.width, camera.height = cam.width, cam.height
            camera.params = [cam.fx, cam.fy, cam.cx, cam.cy]
            db.update_camera(camera)
            rec.add_camera_with_trivial_rig(camera)
            w2c = cam.world_to_cam
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
            rec.add_image_with_trivial_frame(pycolmap.Image(name=image.name, camera_id=image.camera_id,
                                                            image_id=image.image_id), pose)
    return rec


# ------------------------------------------------------------------ the one call before reading

def needs_points(capture) -> bool:
    """Whether a capture read (`read_capture`) gets its points by triangulation: it has poses and
    photos but no points, and is no NeRF-Synthetic object or other capture with transparency
    (those start from their masks' hull instead)."""
    return capture.points is None and capture.kind != "nerf-synthetic" and capture.opaque()


def pending_work(path, points: bool = True) -> str | None:
    """What `ensure_capture(path, points=points)` would run: "structure from motion" (a folder of
    photos with no cameras), "triangulation" (`needs_points`) or None. Cheap: reads the capture's
    cameras and one photo, imports no pycolmap; an unreadable capture raises as `read_capture` does."""
    if needs_sfm(path):
        return "structure from motion"
    if points and needs_points(read_capture(path)):
        return "triangulation"
    return None


def ensure_capture(path, options: SfMOptions | None = None, *, points: bool = False,
                   progress: Progress | None = None, cancel: Callable[[], bool] | None = None) -> SfMReport | None:
    """Make `path` a capture `read_capture` reads: SfM when it is a folder of photos with no
    cameras (`run_sfm`; the report returned), nothing when it has cameras (None). With `points`,
    a capture that `needs_points` also gets triangulated points (`triangulate`). What it will run
    is `pending_work`."""
    if needs_sfm(path):
        return run_sfm(path, options, progress=progress, cancel=cancel)
    if points:
        capture = read_capture(path)
        if needs_points(capture):
            options = options or SfMOptions()
            triangulate(capture, max_image_size=options.max_image_size, threads=options.threads, progress=progress,
                        cancel=cancel)
    return None
