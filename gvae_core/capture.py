"""The cameras a capture was made from: NeRF-style `transforms*.json` and COLMAP sparse models.

`load_cameras(path)` reads either, as `Camera`s in the OpenCV convention of DESIGN.md, in the
capture's world frame (the frame of a 3DGS cloud trained from it). numpy only, no images read
beyond the size of one when a JSON file does not state it.

- `transforms*.json` (NeRF-Synthetic, Instant-NGP, nerfstudio): camera-to-world matrices in the
  Blender/OpenGL convention (y up, looking along -z), flipped as `load_nerf_synthetic` does.
  Intrinsics from `fl_x`/`fl_y`/`cx`/`cy`/`w`/`h` (per frame or for all) or `camera_angle_x`
  (and `camera_angle_y`), with the image size from the JSON or from the first frame's image.
- COLMAP sparse model (a folder holding `cameras.bin` + `images.bin`, or `cameras.txt` +
  `images.txt`, or one of those files): world-to-camera rotation (quaternion w, x, y, z) and
  translation per image, OpenCV convention already, pixel centres at +0.5 like ours. Camera
  models SIMPLE_PINHOLE and PINHOLE are read as they are; SIMPLE_RADIAL, RADIAL, OPENCV and
  FULL_OPENCV as pinholes with their distortion ignored (a warning says so: fine for choosing
  views to score with, not for reprojecting pixels); fisheye models are refused.

Files that cannot be read raise `DatasetError` (a ValueError) naming the file and the problem.

The views the Hessian (`gvae_core.hessian`) is computed from come from here too: `scoring_views`
picks a few of a capture's cameras, `placed_views` / `default_views` place cameras when there are
none: outside an object, all around it, below too (a closed shell is an object), or inside a scene
that surrounds its centre, only when the evidence is strong (`surround`: its far shell is coarser
than what it surrounds, as training from inside makes it), with extra views that look at what the
scoring ones cannot (`PlacedViews.extra`, for what is dropped as unseen).
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .antialias import DILATION_KEY, FILTER_KEY
from .camera import Camera
from .cloud import GaussianCloud
from .conventions import LOG_SCALE_RANGE
from .datasets import DatasetError, Views, load_nerf_synthetic, read_transforms, resize_area

__all__ = ["load_cameras", "load_capture_cameras", "load_capture_images", "read_colmap_cameras", "COLMAP_MODELS",
           "scoring_views", "default_views", "placed_views", "PlacedViews", "outside_views", "inside_views",
           "surround", "surround_radius", "Surround", "DEFAULT_VIEWS", "DEFAULT_RESOLUTION"]

#: COLMAP camera models: id -> (name, number of parameters).
COLMAP_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                 4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                 8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
                 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
_MODEL_IDS = {name: (i, count) for i, (name, count) in COLMAP_MODELS.items()}
#: Models read as pinholes: (index of fx, of fy (None: same as fx), of cx, of cy) in the parameters.
_PINHOLE_LIKE = {"SIMPLE_PINHOLE": (0, None, 1, 2), "PINHOLE": (0, 1, 2, 3), "SIMPLE_RADIAL": (0, None, 1, 2),
                 "RADIAL": (0, None, 1, 2), "OPENCV": (0, 1, 2, 3), "FULL_OPENCV": (0, 1, 2, 3)}
#: Views the Hessian is computed from by default, and their height in pixels (`scoring_views`,
#: `default_views`).
DEFAULT_VIEWS = 4
DEFAULT_RESOLUTION = 256
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".webp", ".JPG", ".PNG", ".JPEG")


def load_cameras(path) -> list[Camera]:
    """The capture's cameras from a `transforms*.json` file, a COLMAP sparse model folder (binary
    or text) or one of its files; see the module docstring."""
    kind, found = _find_capture(Path(path))
    if kind == "json":
        return _load_transforms(found)
    return _colmap_images(found[1], read_colmap_cameras(found[0]))[0]


def _find_capture(path: Path):
    """("json", the transforms file) or ("colmap", (cameras file, images file)) that `path` names."""
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder (expected a transforms*.json file or a COLMAP "
                           f"sparse model)")
    if path.is_file() and path.suffix.lower() == ".json":
        return "json", path
    folder = path if path.is_dir() else path.parent
    if path.is_dir() and not _colmap_files(folder):
        for sub in ("sparse/0", "sparse", "colmap/sparse/0", "distorted/sparse/0"):
            if _colmap_files(folder / sub):
                folder = folder / sub
                break
        else:
            found = sorted(folder.glob("transforms*.json"))
            if len(found) == 1 or (folder / "transforms.json").is_file():
                return "json", (folder / "transforms.json" if (folder / "transforms.json").is_file() else found[0])
            raise DatasetError(f"{path}: no cameras found (no transforms*.json and no COLMAP cameras/images "
                               f".bin or .txt)")
    files = _colmap_files(folder)
    if not files:
        raise DatasetError(f"{path}: not a COLMAP sparse model (needs cameras.bin and images.bin, or cameras.txt "
                           f"and images.txt, in {folder})")
    return "colmap", files


def load_capture_cameras(path) -> list[Camera]:
    """The cameras of the images `load_capture_images(path)` reads (the training split of a
    NeRF-Synthetic folder), without reading the images."""
    path = Path(path)
    if path.is_dir() and (path / "transforms_train.json").is_file():
        return load_cameras(path / "transforms_train.json")
    return load_cameras(path)


def load_capture_images(path, resolution: int | None = None) -> Views:
    """A capture's training images with their cameras, for fine-tuning a cloud trained from it:
    a NeRF-Synthetic folder (`transforms_train.json` and its images, `datasets.load_nerf_synthetic`)
    or a COLMAP capture (its sparse model, as `load_cameras` finds it, and the images it names in
    the `images` folder beside the model, read as RGB with alpha 1), scaled to `resolution` pixels
    high (None: as stored; never up for COLMAP images, whose cameras are scaled to each image's
    size first). Raises DatasetError naming the file that is missing or unreadable."""
    path = Path(path)
    if resolution is not None and int(resolution) <= 0:
        raise ValueError(f"capture images: resolution must be a positive height, got {resolution}")
    if path.is_dir() and (path / "transforms_train.json").is_file():
        return load_nerf_synthetic(path, "train", resolution)
    if path.is_file() and path.name.startswith("transforms_") and path.suffix == ".json":
        return load_nerf_synthetic(path.parent, path.stem[len("transforms_"):], resolution)
    kind, found = _find_capture(path)
    if kind == "json":
        raise DatasetError(f"{found}: images are read from NeRF-Synthetic folders (transforms_train.json) or "
                           f"COLMAP captures")
    cams, names = _colmap_images(found[1], read_colmap_cameras(found[0]))
    folder = next((d / "images" for d in (found[0].parent, *found[0].parents[:3]) if (d / "images").is_dir()), None)
    if folder is None:
        raise DatasetError(f"{found[0].parent}: no 'images' folder beside the COLMAP model")
    images, out_cams = [], []
    for cam, name in zip(cams, names):
        file = folder / name
        if not file.is_file():
            raise DatasetError(f"{file}: image not found (named in {found[1]})")
        try:
            with Image.open(file) as im:
                rgb = np.asarray(im.convert("RGB"), np.float32) / 255.0
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            raise DatasetError(f"{file}: cannot read image: {exc}") from None
        if rgb.shape[:2] != (cam.height, cam.width):  # a downscaled copy of the images: scale the camera
            cam = cam.scaled(rgb.shape[0])
        height = cam.height if resolution is None else min(int(resolution), cam.height)
        if height != cam.height:
            cam = cam.scaled(height)
            rgb = resize_area(rgb, cam.height, cam.width)
        if images and rgb.shape != images[0].shape:
            raise DatasetError(f"{file}: size {rgb.shape[1]}x{rgb.shape[0]} differs from the first image's "
                               f"{images[0].shape[1]}x{images[0].shape[0]} (one camera size per capture)")
        images.append(rgb)
        out_cams.append(cam)
    return Views(out_cams, np.stack(images), None, [Path(n).stem for n in names])


def _colmap_files(folder: Path):
    for ext in (".bin", ".txt"):
        c, i = folder / f"cameras{ext}", folder / f"images{ext}"
        if c.is_file() and i.is_file():
            return c, i
    return None


# ------------------------------------------------------------------------ scoring views


#: Direction cells (a Fibonacci lattice around the centre) that `surround` counts.
SURROUND_CELLS = 64
#: A scene surrounds its centre (`surround`) when the farthest quarter of its Gaussians from the
#: centre is at least this much coarser than the nearest half: in the median size of a training
#: pixel where the cloud stores it (`_pixel_sizes`), else of the Gaussians along their surface
#: (texture makes those vary more: the project's objects measure 0.84-1.11 and 0.87-1.31). A cloud
#: trained from cameras inside it samples its far shell more coarsely than what stands near the
#: cameras, while one trained from outside (a closed object: a head, a box) samples its surface at
#: least as finely as anything inside it. A closed shell without that evidence is an object. ...
SURROUND_COARSER = 1.5
SURROUND_COARSER_SIZES = 2.0
#: ... and its shell (the Gaussians coarser than midway, in log size, between the two) lies in at
#: least this share of the directions (SURROUND_CELLS cells) around what it surrounds (the finer
#: ones, from their median point: an object whose coarse parts are on one side, a plate with its
#: fine detail underneath, measures 0.55-0.58, a room 0.78-1.0) ...
SURROUND_ENCLOSED = 0.7
#: ... and what it surrounds is at least this share of the cloud.
SURROUND_CONTENT = 0.1
#: Field of view of views placed inside a scene, and of views placed around an object.
INSIDE_FOV = math.radians(70.0)
OUTSIDE_FOV = math.radians(50.0)


@dataclass(frozen=True)
class Surround:
    """A scene that surrounds its centre (`surround`): the radius within which what it surrounds
    lies (`inner`: 95% of it) and where the shell begins (`outer`: beyond 5% of it), the evidence
    (`enclosed`: share of the directions around what it surrounds its shell lies in; `coarser`:
    how much coarser it is than the nearest half; `content`: share of the Gaussians the shell
    surrounds), and where cameras can stand (`positions` (K, 3), world frame, one per direction
    with free space: nearest the distance that frames what the shell surrounds)."""

    inner: float
    outer: float
    enclosed: float
    coarser: float
    content: float
    positions: np.ndarray


def _lattice(cells: int) -> np.ndarray:
    """(cells, 3) unit vectors, a Fibonacci lattice: about evenly spread over the sphere."""
    k = np.arange(cells) + 0.5
    z = 1.0 - 2.0 * k / cells
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)


def _pixel_sizes(cloud: GaussianCloud) -> tuple[np.ndarray, float]:
    """Per Gaussian, how coarsely its training sampled it, and the SURROUND_COARSER* threshold
    that goes with it: the stored size of a training pixel (`filter_3D` or `gvae_dilation_3D`,
    world units) where the cloud has one, else the Gaussian's size along its surface (the geometric
    mean of its two largest scales)."""
    for key in (FILTER_KEY, DILATION_KEY):
        if key in cloud.extra and np.ndim(cloud.extra[key]) == 1:
            return np.asarray(cloud.extra[key], np.float64), SURROUND_COARSER
    log_scales = np.sort(np.clip(np.asarray(cloud.scales, np.float64), *LOG_SCALE_RANGE), axis=1)
    return np.exp(0.5 * (log_scales[:, 1] + log_scales[:, 2])), SURROUND_COARSER_SIZES


def _around(src: GaussianCloud, center: np.ndarray, sample: int):
    """(rows, centres, centres - `center`, their distances): of at most `sample` finite Gaussians of
    `src` (a fixed random subsample decides as well as all of them)."""
    p = np.asarray(src.means, np.float64)
    ok = np.flatnonzero(np.isfinite(p).all(1))
    if len(ok) > sample:
        ok = np.sort(np.random.default_rng(0).choice(ok, sample, replace=False))
    rel = p[ok] - center
    return ok, p[ok], rel, np.linalg.norm(rel, axis=1)


def surround(cloud: GaussianCloud, normalization=None, *, sample: int = 200_000) -> Surround | None:
    """Whether `cloud` is a scene around its robust centre, seen from inside (a capture with its
    background, a room), and where cameras can stand in it; None for an object. A scene when the
    farthest quarter of the Gaussians from the centre is SURROUND_COARSER coarser than the nearest
    half (`_pixel_sizes`), the finer ones (what the coarser shell surrounds) are SURROUND_CONTENT
    of them, and the coarser ones lie in SURROUND_ENCLOSED of the directions around them. A
    closed shell without that evidence (a head with a few floaters inside, a box) is an object. At
    most `sample` Gaussians are looked at (a subsample decides as well)."""
    src = cloud.numpy()
    center, _ = normalization or src.normalization()
    ok, p, rel, r = _around(src, center, sample)
    if len(ok) < 64:
        return None
    near_half, far_quarter = r <= np.median(r), r >= np.percentile(r, 75.0)
    size, threshold = _pixel_sizes(src)
    size = np.maximum(size[ok], 1e-30)
    fine, coarse = float(np.median(size[near_half])), float(np.median(size[far_quarter]))
    coarser = coarse / fine
    if not coarser >= threshold:
        return None
    content = size < math.sqrt(fine * coarse)
    if content.mean() < SURROUND_CONTENT:
        return None
    lattice = _lattice(SURROUND_CELLS)
    around = p[~content] - np.median(p[content], axis=0)
    enclosed = len(np.unique(np.argmax(around @ lattice.T, axis=1))) / SURROUND_CELLS
    if enclosed < SURROUND_ENCLOSED:
        return None
    inner, outer = float(np.percentile(r[content], 95.0)), float(np.percentile(r[~content], 5.0))
    shell_cell = np.argmax(rel[~content] @ lattice.T, axis=1)
    reach = np.zeros(SURROUND_CELLS)  # per direction, where its shell begins
    for k in np.unique(shell_cell):
        reach[k] = np.percentile(r[~content][shell_cell == k], 5.0)
    positions = _free_positions(src.select(ok), center, lattice, reach, inner)
    if len(positions) == 0:
        return None
    return Surround(inner, outer, enclosed, coarser, float(content.mean()), positions)


def _free_positions(cloud: GaussianCloud, center: np.ndarray, lattice: np.ndarray, reach: np.ndarray,
                    inner: float) -> np.ndarray:
    """Where cameras can stand inside a scene, one per direction from the centre that has room:
    the point along direction k, short of where its shell begins (`reach[k]`), nearest the distance
    from which what the shell surrounds fills a view of INSIDE_FOV (1.2 times its radius `inner`
    across), that is free (its nearest Gaussian farther than its own largest standard deviation,
    than 1% of the scene's size and than a tenth of the way to the centre) and sees the centre over
    free space for the first half of the way; the freest first."""
    from scipy.spatial import cKDTree  # noqa: PLC0415 - scipy is slow to import

    p = np.asarray(cloud.means, np.float64)
    size = np.exp(np.clip(np.asarray(cloud.scales, np.float64), *LOG_SCALE_RANGE).max(1))
    tree = cKDTree(p)
    margin = 0.01 * float(np.linalg.norm(np.ptp(p, axis=0)))

    def free(points: np.ndarray, room) -> tuple[np.ndarray, np.ndarray]:
        dist, nearest = tree.query(points)
        return (dist > size[nearest]) & (dist > room), dist

    frame = 1.2 * inner / math.sin(0.5 * INSIDE_FOV)
    way = np.linspace(0.0, 0.5, 8)  # the first half of the way to the centre
    found, clearance = [], []
    for d, limit in zip(lattice, reach):
        if limit <= 0:
            continue
        radii = np.geomspace(0.05, 0.9, 32) * limit
        radii = radii[np.argsort(np.abs(np.log(radii / frame)), kind="stable")]  # nearest the framing distance first
        ok, dist = free(center + radii[:, None] * d, np.maximum(0.1 * radii, margin))
        for i in np.flatnonzero(ok):
            sight = center + (radii[i] * (1.0 - way))[:, None] * d
            if free(sight, 0.0)[0].all():
                found.append(center + radii[i] * d)
                clearance.append(dist[i])
                break
    if not found:
        return np.zeros((0, 3))
    return np.asarray(found)[np.argsort(clearance, kind="stable")[::-1]]


def surround_radius(cloud: GaussianCloud, normalization=None) -> tuple[float, float] | None:
    """(`Surround.inner`, `Surround.outer`) of a scene that surrounds its centre, else None."""
    found = surround(cloud, normalization)
    return None if found is None else (found.inner, found.outer)


def _spread(directions: np.ndarray, count: int) -> list[int]:
    """`count` indices of `directions` spread out by farthest-point sampling (from the first)."""
    pick = [0]
    dist = np.linalg.norm(directions - directions[0], axis=1)
    while len(pick) < min(count, len(directions)):
        nxt = int(np.argmax(dist))
        pick.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(directions - directions[nxt], axis=1))
    return pick


def outside_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  fov_x: float = OUTSIDE_FOV, normalization=None) -> list[Camera]:
    """`views` cameras all around the cloud's robust centre, below it as well as above (a
    Fibonacci lattice over the whole sphere, z up), each from where a sphere of 1.4 half-extents
    just fits its view, all looking at the centre."""
    center, half = normalization or cloud.normalization()
    radius = 1.4 * half / math.sin(0.5 * fov_x)
    return [Camera.look_at(center + radius * d, center, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=fov_x) for d in _lattice(max(int(views), 1))]


@dataclass
class PlacedViews:
    """Views placed to look at a cloud without its capture's cameras (`placed_views`): `scoring`,
    the views to score and compare pictures from; `extra`, views that look at what those cannot
    (only which Gaussians they see counts: none for an object); `surround`: the evidence that the
    cloud is a scene seen from inside, or None for an object."""

    scoring: list[Camera]
    extra: list[Camera]
    surround: Surround | None


def placed_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                 fov_x: float = OUTSIDE_FOV, normalization=None) -> PlacedViews:
    """Views that see what is there, without the capture's cameras. An object (every cloud without
    strong evidence of the opposite, `surround`; a closed shell is an object) is scored from
    `views` views outside it, all around, below too (`outside_views`); they need no extra views.
    A scene that surrounds its centre is scored from `views` views inside it, in its free space
    (`Surround.positions`, spread out over the directions around the centre), looking at its
    centre with a field of view of INSIDE_FOV; its extra views are the six faces of a cube around
    its freest point (every direction from inside) and `views` views all around it from outside
    (what only they see, the far side of its walls, is then not taken for unseen either)."""
    normalization = normalization or cloud.normalization()
    found = surround(cloud, normalization)
    if found is None:
        return PlacedViews(outside_views(cloud, views, resolution, fov_x, normalization), [], None)
    inside = _looking_at(found.positions, normalization[0], views, resolution)
    eye = found.positions[0]
    cube = [Camera.look_at(eye, eye + d, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=math.radians(90.0)) for d in np.concatenate([np.eye(3), -np.eye(3)])]
    return PlacedViews(inside, cube + outside_views(cloud, views, resolution, normalization=normalization), found)


def inside_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                 normalization=None, *, sample: int = 200_000) -> list[Camera]:
    """Up to `views` cameras in the free space inside a cloud, whatever it was taken for, looking at
    its robust centre with a field of view of INSIDE_FOV, each along another direction from it
    (`_free_positions`, short of the far side of the cloud in that direction, framing its nearer
    half): what views from outside cannot see of a scene taken for an object (a room whose far
    walls its training sampled hardly more coarsely than its furniture). None where there is no
    free space."""
    src = cloud.numpy()
    center, _ = normalization or src.normalization()
    ok, _, rel, r = _around(src, center, sample)
    if len(ok) < 64:
        return []
    lattice = _lattice(SURROUND_CELLS)
    cell = np.argmax(rel @ lattice.T, axis=1)
    reach = np.zeros(SURROUND_CELLS)  # per direction, the far side of the cloud
    for k in np.unique(cell):
        reach[k] = np.percentile(r[cell == k], 95.0)
    positions = _free_positions(src.select(ok), center, lattice, reach, float(np.median(r)))
    if len(positions) == 0:
        return []
    return _looking_at(positions, center, views, resolution)


def _looking_at(positions: np.ndarray, center: np.ndarray, views: int, resolution: int) -> list[Camera]:
    """`views` cameras at `positions` (the first, then spread out over their directions from
    `center`), looking at `center` with a field of view of INSIDE_FOV."""
    rel = positions - center
    directions = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-30)
    return [Camera.look_at(positions[i], center, (0.0, 0.0, 1.0), width=resolution, height=resolution,
                           fov_x=INSIDE_FOV) for i in _spread(directions, max(int(views), 1))]


def default_views(cloud: GaussianCloud, views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  fov_x: float = OUTSIDE_FOV, normalization=None) -> list[Camera]:
    """The views to score a cloud from without its capture's cameras: `placed_views(...).scoring`
    (outside an object, all around; inside a scene that surrounds its centre). `normalization`:
    the cloud's (centre, scale) when known (`GaussianCloud.normalization`)."""
    return placed_views(cloud, views, resolution, fov_x, normalization).scoring


def scoring_views(cameras: Sequence[Camera], views: int = DEFAULT_VIEWS, resolution: int = DEFAULT_RESOLUTION,
                  cloud: GaussianCloud | None = None) -> list[Camera]:
    """`views` of the capture's `cameras` to compute the Hessian from: those that see the cloud
    (when given: at least 1% of its centres in the image, in front of the camera), spread out by
    farthest-point sampling on camera centre and viewing direction (from the camera that sees the
    most), each scaled to `resolution` pixels high when it is larger (a capture's full-size images
    cost time and add little to the score). All of them when `views` is 0 or covers them all.
    Raises ValueError when no camera sees the cloud (cameras of another frame, say)."""
    cams = list(cameras)
    if not cams:
        raise ValueError("scoring views: no cameras")
    seen = np.ones(len(cams))
    if cloud is not None and len(cloud):
        p = np.asarray(cloud.numpy().means, np.float64)
        p = p[np.isfinite(p).all(1)]
        if len(p) > 20_000:
            p = p[np.random.default_rng(0).choice(len(p), 20_000, replace=False)]
        for i, cam in enumerate(cams):
            uv, z = cam.project(p)
            with np.errstate(invalid="ignore"):
                inside = (z > 0.01) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) \
                    & (uv[:, 1] <= cam.height)
            seen[i] = inside.mean() if len(p) else 0.0
        keep = np.flatnonzero(seen >= 0.01)
        if len(keep) == 0:
            raise ValueError(f"none of the {len(cams)} cameras sees the cloud (are they in the cloud's frame? a "
                             f"COLMAP model or transforms.json of the capture the cloud was trained from)")
        cams, seen = [cams[i] for i in keep], seen[keep]
    if 0 < views < len(cams):
        centres = np.stack([c.center for c in cams])
        dirs = np.stack([c.rotation[2] for c in cams])
        extent = max(float(np.ptp(centres, axis=0).max()), 1e-12)
        feats = np.concatenate([centres / extent, 0.5 * dirs], 1)
        first = int(np.argmax(seen))
        pick = [first]
        dist = np.linalg.norm(feats - feats[first], axis=1)
        while len(pick) < views:
            nxt = int(np.argmax(dist))
            pick.append(nxt)
            dist = np.minimum(dist, np.linalg.norm(feats - feats[nxt], axis=1))
        cams = [cams[i] for i in sorted(pick)]
    return [c.scaled(resolution) if c.height > resolution else c for c in cams]


# ------------------------------------------------------------------------------ COLMAP

class _Reader:
    """Little-endian binary reads that name the file when it ends too early."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what} (byte {self.pos} of "
                               f"{len(self.data)})")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def count(self, what: str) -> int:
        """A uint64 count of records (`what`: "cameras", "images") that the file could hold."""
        (n,) = self.read("Q", f"the {what[:-1]} count")
        if n > len(self.data):
            raise DatasetError(f"{self.path}: corrupt: {n} {what} in a {len(self.data)}-byte file")
        return n

    def string(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what}")
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{self.path}: corrupt: {what} is not text") from None

    def skip(self, size: int, what: str) -> None:
        if size < 0 or self.pos + size > len(self.data):
            raise DatasetError(f"{self.path}: truncated: the file ends inside {what}")
        self.pos += size


def read_colmap_cameras(path) -> dict[int, tuple[str, int, int, np.ndarray]]:
    """COLMAP `cameras.bin` or `cameras.txt`: camera id -> (model name, width, height, parameters)."""
    path = Path(path)
    out: dict[int, tuple[str, int, int, np.ndarray]] = {}
    if path.suffix == ".bin":
        r = _Reader(path)
        count = r.count("cameras")
        for k in range(count):
            cam_id, model_id, width, height = r.read("iiQQ", f"camera {k}")
            if model_id not in COLMAP_MODELS:
                raise DatasetError(f"{path}: corrupt: camera {cam_id} has unknown model id {model_id}")
            name, n = COLMAP_MODELS[model_id]
            params = np.array(r.read(f"{n}d", f"the parameters of camera {cam_id}"), np.float64)
            out[cam_id] = (name, int(width), int(height), params)
        if r.pos != len(r.data):
            raise DatasetError(f"{path}: corrupt: {len(r.data) - r.pos} bytes after the last of {count} cameras")
    else:
        for lineno, line in _text_lines(path):
            parts = line.split()
            try:
                cam_id, name, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
                params = np.array([float(v) for v in parts[4:]], np.float64)
            except (IndexError, ValueError):
                raise DatasetError(f"{path}: line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got "
                                   f"{line[:80]!r}") from None
            if name not in _MODEL_IDS:
                raise DatasetError(f"{path}: line {lineno}: unknown camera model {name!r}")
            if len(params) != _MODEL_IDS[name][1]:
                raise DatasetError(f"{path}: line {lineno}: a {name} camera has {_MODEL_IDS[name][1]} parameters, "
                                   f"got {len(params)}")
            out[cam_id] = (name, width, height, params)
    if not out:
        raise DatasetError(f"{path}: no cameras")
    return out


def _text_lines(path: Path):
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: corrupt: not a text file") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield lineno, line


def _pinhole(cam_file: Path, cam_id: int, intrinsics: dict, warned: set) -> tuple[float, float, float, float, int, int]:
    if cam_id not in intrinsics:
        raise DatasetError(f"{cam_file}: an image refers to camera {cam_id}, which the cameras file lacks")
    name, width, height, params = intrinsics[cam_id]
    if name not in _PINHOLE_LIKE:
        raise DatasetError(f"{cam_file}: camera {cam_id} uses the {name} model, which is not supported (pinhole "
                           f"and radial models only: {', '.join(_PINHOLE_LIKE)})")
    if name not in ("SIMPLE_PINHOLE", "PINHOLE") and name not in warned:
        warned.add(name)
        warnings.warn(f"{cam_file}: {name} cameras are read as pinholes, their distortion ignored", stacklevel=3)
    ifx, ify, icx, icy = _PINHOLE_LIKE[name]
    fx = params[ifx]
    return fx, params[ify] if ify is not None else fx, params[icx], params[icy], width, height


def _camera(path: Path, what: str, q, t, intr) -> Camera:
    q = np.asarray(q, np.float64)
    t = np.asarray(t, np.float64)
    norm = np.linalg.norm(q)
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or norm < 1e-12:
        raise DatasetError(f"{path}: {what}: non-finite or zero pose")
    w, x, y, z = q / norm
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = t
    fx, fy, cx, cy, width, height = intr
    try:
        return Camera(w2c, fx, fy, cx, cy, width, height)
    except ValueError as exc:
        raise DatasetError(f"{path}: {what}: {exc}") from None


def _colmap_images(path: Path, intrinsics: dict) -> tuple[list[Camera], list[str]]:
    """COLMAP `images.bin` or `images.txt` as cameras, and their image names, in image-id order."""
    cam_file = path.with_name("cameras" + path.suffix)
    warned: set = set()
    found: list[tuple[int, Camera]] = []
    if path.suffix == ".bin":
        r = _Reader(path)
        count = r.count("images")
        for k in range(count):
            image_id, *pose, cam_id = r.read("I7di", f"image {k}")
            name = r.string(f"the name of image {image_id}")
            (points,) = r.read("Q", f"the point count of image {image_id}")
            r.skip(24 * points, f"the points of image {image_id}")
            intr = _pinhole(cam_file, cam_id, intrinsics, warned)
            found.append((image_id, _camera(path, f"image {image_id} ({name})", pose[:4], pose[4:], intr), name))
        if r.pos != len(r.data):
            raise DatasetError(f"{path}: corrupt: {len(r.data) - r.pos} bytes after the last of {count} images")
    else:
        # Two lines an image: the pose, then its 2D points (possibly an empty line). A line that
        # parses as a pose where points are expected is taken as the next pose (some writers drop
        # the empty lines).
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{path}: corrupt: not a text file") from None
        lines = [(n, line.strip()) for n, line in enumerate(text.splitlines(), 1) if not line.startswith("#")]
        i = 0
        while i < len(lines):
            lineno, line = lines[i]
            i += 1
            if not line:
                continue
            parsed = _pose_line(line)
            if parsed is None:
                raise DatasetError(f"{path}: line {lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got "
                                   f"{line[:80]!r}")
            image_id, pose, cam_id, name = parsed
            if i < len(lines) and _pose_line(lines[i][1]) is None:
                i += 1  # its points line
            intr = _pinhole(cam_file, cam_id, intrinsics, warned)
            found.append((image_id, _camera(path, f"line {lineno}", pose[:4], pose[4:], intr), name))
    if not found:
        raise DatasetError(f"{path}: no images")
    found.sort(key=lambda item: item[0])
    return [cam for _, cam, _ in found], [name for _, _, name in found]


def _pose_line(line: str):
    """(image id, 7 pose numbers, camera id, image name) of an images.txt pose line, else None."""
    parts = line.split()
    if len(parts) < 10:
        return None
    try:
        image_id, cam_id = int(parts[0]), int(parts[8])
        pose = [float(v) for v in parts[1:8]]
    except ValueError:
        return None
    name = " ".join(parts[9:])
    try:
        float(name)
        return None  # all numbers: a points line
    except ValueError:
        return image_id, pose, cam_id, name


# ------------------------------------------------------------------------- transforms.json

def _load_transforms(path: Path) -> list[Camera]:
    meta, frames = read_transforms(path)
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if "FISHEYE" in model:
        raise DatasetError(f"{path}: camera_model {model} is not supported (pinhole cameras only)")
    if any(float(meta.get(k, 0.0) or 0.0) != 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")):
        warnings.warn(f"{path}: the cameras' lens distortion is ignored (read as pinholes)", stacklevel=3)
    size = None
    cams = []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{path}: malformed frame {i}: not an object")
        try:
            c2w = np.asarray(frame["transform_matrix"], np.float64)
        except (KeyError, TypeError, ValueError):
            raise DatasetError(f"{path}: malformed frame {i}: needs a numeric 'transform_matrix'") from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise DatasetError(f"{path}: frame {i}: transform_matrix must be a finite 4x4 matrix")

        def get(key, default=None, frame=frame, i=i):
            return _number(path, meta, frame, i, key, default)

        w, h = get("w"), get("h")
        if w is None or h is None:
            if size is None:
                size = _image_size(path, frame, i)
            w, h = size
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None:
            angle = get("camera_angle_x")
            if angle is None:
                raise DatasetError(f"{path}: frame {i}: no focal length ('fl_x' or 'camera_angle_x')")
            if not 0.0 < angle < math.pi:
                raise DatasetError(f"{path}: camera_angle_x {angle} is not in (0, pi)")
            fx = 0.5 * w / math.tan(0.5 * angle)
        if fy is None:
            angle_y = get("camera_angle_y")
            fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None and 0 < angle_y < math.pi else fx
        cx, cy = get("cx", w / 2.0), get("cy", h / 2.0)
        base = Camera.from_blender_c2w(c2w, 2.0 * math.atan(0.5 * w / fx), int(round(w)), int(round(h)))
        try:
            cams.append(Camera(base.world_to_cam, fx, fy, cx, cy, int(round(w)), int(round(h))))
        except ValueError as exc:
            raise DatasetError(f"{path}: frame {i}: {exc}") from None
    return cams


def _number(path: Path, meta: dict, frame: dict, index: int, key: str, default=None) -> float | None:
    """A frame's numeric field, else the file's, else `default`; non-numbers are refused."""
    value = frame.get(key, meta.get(key, default))
    if value is None:
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: frame {index}: {key!r} is not a number") from None
    if not math.isfinite(value):
        raise DatasetError(f"{path}: frame {index}: {key!r} is not finite")
    return value


def _image_size(path: Path, frame: dict, index: int) -> tuple[int, int]:
    """(width, height) of a frame's image (only its header is read)."""
    rel = str(frame.get("file_path", ""))
    base = path.parent / rel
    candidates = ([base] if base.suffix else []) + [base.with_name(base.name + s) for s in _IMAGE_SUFFIXES]
    for c in candidates:
        if rel and c.is_file():
            try:
                with Image.open(c) as im:
                    return im.size
            except (UnidentifiedImageError, OSError) as exc:
                raise DatasetError(f"{c}: cannot read the image size: {exc}") from None
    raise DatasetError(f"{path}: frame {index}: no image size ('w' and 'h') and its image "
                       f"{rel!r} was not found")
