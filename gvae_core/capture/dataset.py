"""`Capture`: what every reader returns, and the one door every command reads a capture through.

`read_capture(path)` finds the format (as nerfstudio's dataparsers do: one small reader each) and
returns a `Capture`: per frame its pinhole camera (lens distortion undone, `capture.lens`), its
image file, name and split, and the capture's SfM points when it has them. Formats:

- a NeRF-Synthetic folder (`transforms_train.json`, `transforms_test.json`, `transforms_val.json`:
  their frames are the splits) or one `transforms*.json` file (instant-ngp, nerfstudio: all its
  frames train), `capture.transforms`;
- a COLMAP capture (`sparse/0` and `images/` as the reference 3DGS, gsplat and nerfstudio read it,
  or the model folder or one of its files), `capture.colmap`;
- the reference 3DGS's `cameras.json` (or its model folder holding one): cameras without photos,
  `capture.gs_cameras`.

Frames whose image is missing are dropped, and counted (`Capture.skipped`, with a warning); an
image whose size differs from its camera's is read as a scaled copy when its aspect agrees (an
`images_4` folder beside a full-size model), else refused. `held_out(every)` marks every
`every`-th frame by image name as a test view (the LLFF / Mip-NeRF 360 convention, 8).
`Capture.load(split, height)` reads the images: straight RGBA (alpha 1 for photos), undistorted
into the frame's pinhole, area-averaged to `height` in premultiplied space (`datasets`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..camera import Camera
from ..datasets import DatasetError, Views, every_nth, premultiplied, read_rgba, resize_rgba
from .colmap import ColmapModel, SfMPoints, colmap_files, read_colmap
from .gs_cameras import GS_CAMERAS, is_gs_cameras, read_gs_cameras
from .lens import Lens, undistort_image, undistorted_camera
from .transforms import read_transforms

__all__ = ["Capture", "read_capture", "find_capture", "find_photos", "triangulated_folder", "SPLITS", "TEST_EVERY",
           "PHOTO_SUFFIXES", "TRIANGULATED"]

#: NeRF-Synthetic's split files, in the order their frames are listed.
SPLITS = ("train", "test", "val")
#: The LLFF / Mip-NeRF 360 convention: every 8th image, sorted by name, is held out.
TEST_EVERY = 8
#: Folders under a capture where the COLMAP model may be (the first found is read).
_MODEL_FOLDERS = ("sparse/0", "sparse", "colmap/sparse/0", "distorted/sparse/0")
#: Photos a folder of photos is made of (case-insensitive): what COLMAP reads.
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
#: The folder, beside a capture with poses and no points, that its triangulated points are kept in
#: (`capture.sfm.triangulate`).
TRIANGULATED = "triangulated"


@dataclass
class Capture:
    """Posed images of one scene (module docstring). Per frame: `cameras` (pinhole, OpenCV
    convention, at the size of its image as stored, distortion undone), `files` (None: a frame
    read for its camera only names no image), `names`,
    `splits` ("train", "test" or "val"), `lenses` (the distortion its photo was taken through) and
    `photo_cameras` (the pinhole part of that camera, at the stored size). `points`: the SfM points
    (None without); `skipped`: frames dropped because their image is missing; `sfm_report`: what
    structure from motion did when the call that read it ran it (`capture.sfm.SfMReport`)."""

    source: Path
    kind: str
    cameras: list[Camera]
    files: list[Path | None]
    names: list[str]
    splits: list[str]
    lenses: list[Lens]
    photo_cameras: list[Camera]
    points: SfMPoints | None = None
    skipped: list[str] = dataclasses.field(default_factory=list)
    sfm_report: object | None = None

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def distorted(self) -> int:
        """How many frames were taken through a distorting lens (undone on load)."""
        return sum(not lens.is_pinhole for lens in self.lenses)

    def indices(self, split: str = "train") -> np.ndarray:
        """Frames of a split, in capture order."""
        return np.array([i for i, s in enumerate(self.splits) if s == split], np.int64)

    def split_cameras(self, split: str = "train") -> list[Camera]:
        return [self.cameras[i] for i in self.indices(split)]

    def held_out(self, every: int | None) -> Capture:
        """The same frames with every `every`-th one by image name (`datasets.every_nth`, from the
        first) a test view and the rest training views (None: as read). A NeRF-Synthetic folder has
        its own test split."""
        if every is None:
            return self
        every = int(every)
        if every < 2:
            raise ValueError(f"{self.source}: --test-every must be 2 or more, got {every}")
        if self.kind == "nerf-synthetic":
            raise ValueError(f"{self.source}: a NeRF-Synthetic folder has its own test split "
                             f"(transforms_test.json); --test-every is for captures with one set of images")
        keys = [f.name if f is not None else name for f, name in zip(self.files, self.names)]
        splits = ["train"] * len(self)
        for i in every_nth(keys, every):
            splits[i] = "test"
        if "train" not in splits:
            raise ValueError(f"{self.source}: holding out every {every}th of {len(self)} images leaves none to "
                             f"train on")
        return dataclasses.replace(self, splits=splits)

    def load(self, split: str = "train", height: int | None = None) -> Views:
        """The images of a split with their cameras, scaled to `height` pixels high (None: as
        stored), undistorted first where the photo was taken through a lens."""
        if height is not None and int(height) <= 0:
            raise ValueError(f"{self.source}: the image height must be positive, got {height}")
        pick = self.indices(split)
        if len(pick) == 0:
            raise DatasetError(f"{self.source}: no {split!r} views")
        images = alphas = None  # allocated once the first image gives the size (no list + stack copy)
        cams, names = [], []
        for k, i in enumerate(pick):
            rgba = self.frame_image(i)
            cam = self.cameras[i]
            if height is not None and int(height) != cam.height:
                cam = cam.scaled(int(height))
                rgba = resize_rgba(rgba, cam.height, cam.width)
            if images is None:
                images = np.empty((len(pick), cam.height, cam.width, 3), np.float32)
                alphas = np.empty((len(pick), cam.height, cam.width), np.float32)
            elif rgba.shape[:2] != images.shape[1:3]:
                raise DatasetError(f"{self.files[i]}: {rgba.shape[1]}x{rgba.shape[0]} differs from the "
                                   f"{images.shape[2]}x{images.shape[1]} of the first {split} image (one image size "
                                   f"per capture)")
            images[k], alphas[k] = rgba[..., :3], rgba[..., 3]
            cams.append(cam)
            names.append(self.names[i])
        return Views(cams, images, alphas, names)

    def frame_image(self, i: int) -> np.ndarray:
        """Frame `i`'s image as stored, straight RGBA float32, undistorted into its pinhole
        (`cameras[i]`) where the photo was taken through a lens."""
        if self.files[i] is None:
            raise DatasetError(f"{self.source}: frame {self.names[i]!r} names no image")
        rgba = read_rgba(self.files[i])
        if not self.lenses[i].is_pinhole:
            rgba = _undistort_rgba(rgba, self.photo_cameras[i], self.lenses[i], self.cameras[i])
        return rgba

    def opaque(self) -> bool:
        """Whether the first image has no transparent pixel (photos; an object over a transparent
        background has)."""
        first = next((f for f in self.files if f is not None), None)
        return first is not None and bool((read_rgba(first)[..., 3] >= 0.999).all())

    def summary(self) -> str:
        """One line: format, frames per split, size, distortion, points, skipped frames."""
        counts = ", ".join(f"{len(self.indices(s))} {s}" for s in SPLITS if len(self.indices(s)))
        cam = self.cameras[0]
        parts = [f"{self.kind} capture {self.source}: {counts} views of {cam.width}x{cam.height}"]
        if self.distorted:
            parts.append(f"lens distortion of {self.distorted} undone on load")
        parts.append(f"{len(self.points)} {self.points.source}" if self.points is not None else "no SfM points")
        if self.skipped:
            parts.append(f"{len(self.skipped)} frame(s) skipped: image missing")
        return "; ".join(parts)


def find_photos(path) -> tuple[Path, list[str]]:
    """(the folder the photos are in, their names sorted) for a capture folder: its `images/`
    when that holds photos, else the folder itself; no photos: (folder, [])."""
    folder = Path(path)
    for d in (folder / "images", folder):
        if d.is_dir():
            names = sorted(p.name for p in d.iterdir()
                           if p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith(".") and p.is_file())
            if names:
                return d, names
    return folder, []


def find_capture(path: Path) -> tuple[str, Path | tuple[Path, Path]]:
    """What `path` names: ("nerf-synthetic", folder), ("transforms", file), ("colmap", (cameras
    file, images file)) or ("3dgs-cameras", file); DatasetError when it is none of them."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder (expected a capture: a COLMAP sparse model with its "
                           f"images, a transforms*.json file, or a NeRF-Synthetic folder)")
    if path.is_file() and path.suffix.lower() == ".json":
        return ("3dgs-cameras" if is_gs_cameras(path) else "transforms"), path
    folder = path if path.is_dir() else path.parent
    if path.is_dir() and not colmap_files(folder):
        if (folder / "transforms_train.json").is_file():
            return "nerf-synthetic", folder
        if (folder / "transforms.json").is_file():
            return "transforms", folder / "transforms.json"
        for sub in _MODEL_FOLDERS:
            if colmap_files(folder / sub):
                folder = folder / sub
                break
        else:
            found = sorted(folder.glob("transforms*.json"))
            if len(found) == 1:
                return "transforms", found[0]
            if is_gs_cameras(folder / GS_CAMERAS):  # the reference 3DGS's model folder
                return "3dgs-cameras", folder / GS_CAMERAS
            photos, names = find_photos(folder)
            if names:
                raise DatasetError(f"{path}: {len(names)} photos in {photos} and no cameras (no COLMAP model, no "
                                   f"transforms*.json): make them by structure from motion with `gvae sfm {path}` "
                                   f"(gvae train, render, refine and compact do it themselves; from Python "
                                   f"gvae_core.capture.open_capture)")
            raise DatasetError(f"{path}: no cameras found (no transforms*.json, no COLMAP cameras/images "
                               f".bin or .txt, no 3DGS cameras.json) and no photos")
    files = colmap_files(folder)
    if not files:
        raise DatasetError(f"{path}: not a COLMAP sparse model (needs cameras.bin and images.bin, or cameras.txt "
                           f"and images.txt, in {folder})")
    return "colmap", files


def read_capture(path, test_every: int | None = None, *, splits: Sequence[str] | None = None,
                 kind: str | None = None, images: bool = True) -> Capture:
    """The capture at `path` (module docstring), with every `test_every`-th image held out when
    given. `splits`: for a NeRF-Synthetic folder, which split files to read (default all there are;
    a split asked for whose file is missing is an error). `kind` "nerf-synthetic" reads `path` as
    such a folder without looking for other formats. `images` False: the cameras only, every frame
    whether its image is there or not (nothing can be loaded)."""
    kind, found = ("nerf-synthetic", Path(path)) if kind == "nerf-synthetic" else find_capture(Path(path))
    if kind == "colmap":
        cameras_file, images_file = found
        model = read_colmap(cameras_file, images_file)
        folder = _images_folder(images_file, model.names[0]) if images else images_file.parent
        if images:
            _warn_unregistered(folder, model.names)
        frames = [(model, [folder / n for n in model.names], ["train"] * len(model.names))]
        source = images_file.parent
    elif kind == "transforms":
        t = read_transforms(found)
        frames = [(t, t.files, ["train"] * len(t.files))]
        source = found
    elif kind == "3dgs-cameras":
        if images:
            raise DatasetError(f"{found}: the reference 3DGS's cameras.json holds cameras without photos; give the "
                               f"capture the splat was trained from (its COLMAP folder) for its images")
        t = read_gs_cameras(found)
        frames = [(t, [None] * len(t.cameras), ["train"] * len(t.cameras))]
        source = found
    else:
        frames = []
        for split in splits or SPLITS:
            file = found / f"transforms_{split}.json"
            if not file.is_file():
                if splits is not None:
                    raise DatasetError(f"{file}: missing (no {split!r} split in {found})")
                continue
            t = read_transforms(file)
            frames.append((t, t.files, [split] * len(t.files)))
        source = found
    capture = _assemble(Path(path), source, kind, frames, images)
    if capture.points is None and kind in ("colmap", "transforms"):
        capture = dataclasses.replace(capture, points=_triangulated_points(capture))
    return capture.held_out(test_every)


def _images_folder(images_file: Path, first: str | None = None) -> Path:
    """The folder of a COLMAP model's images: `images` beside the model or up to three folders up
    (`input` for the distorted model of the reference 3DGS's layout), else the folder holding
    `sparse/` when the photos are in it (a folder of photos after `gvae sfm`)."""
    model = images_file.parent
    names = ("input", "images") if model.parts[-3:-1] == ("distorted", "sparse") else ("images",)
    for d in (model, *model.parents[:3]):
        for name in names:
            if (d / name).is_dir():
                return d / name
    root = model.parent.parent if model.parent.name == "sparse" else model.parent
    if first is not None and (root / first).is_file():
        return root
    raise DatasetError(f"{model}: no 'images' folder beside the COLMAP model")


def triangulated_folder(capture: Capture) -> Path:
    """Where the triangulated points of a capture with poses and no points are kept:
    `TRIANGULATED/` in the folder of its transforms file, or in the folder holding its COLMAP
    model's `sparse/`."""
    source = Path(capture.source)
    if capture.kind == "colmap":
        return (source.parent.parent if source.parent.name == "sparse" else source.parent) / TRIANGULATED
    return (source.parent if source.suffix == ".json" else source) / TRIANGULATED


def _triangulated_points(capture: Capture) -> SfMPoints | None:
    """The points `capture.sfm.triangulate` made for this capture, while its poses are the
    capture's (the same names, cameras within 1e-6 of the scene's size); else None."""
    folder = triangulated_folder(capture)
    files = colmap_files(folder)
    if files is None or not (folder / "points3D.bin").is_file():
        return None
    try:
        model = read_colmap(*files)
    except DatasetError:
        return None
    poses = {Path(name).stem: cam.world_to_cam for name, cam in zip(model.names, model.cameras)}
    centers = np.stack([c.center for c in capture.cameras])
    tol = 1e-6 * max(float(np.ptp(centers, axis=0).max()), 1.0)
    for name, cam in zip(capture.names, capture.cameras):
        w2c = poses.get(name)
        if w2c is None or not np.allclose(w2c[:3, :3], cam.world_to_cam[:3, :3], atol=1e-6) \
                or not np.allclose(w2c[:3, 3], cam.world_to_cam[:3, 3], atol=tol):
            return None
    return dataclasses.replace(model.points, source=f"points triangulated with its poses ({folder})")


def _warn_unregistered(folder: Path, names: list[str]) -> None:
    """Warn about photos beside a COLMAP model that it leaves out (SfM did not register them)."""
    _, photos = find_photos(folder)
    known = set(names)
    missing = [p for p in photos if p not in known]
    if missing:
        shown = ", ".join(missing[:8]) + (f", ... ({len(missing) - 8} more)" if len(missing) > 8 else "")
        warnings.warn(f"{folder}: {len(missing)} of {len(photos)} photos are not in the COLMAP model (structure from "
                      f"motion did not register them) and are left out: {shown}", stacklevel=4)


def _assemble(path: Path, source: Path, kind: str, parts, images: bool) -> Capture:
    """A Capture from (reader output, image files, splits) parts: missing images dropped and
    counted, cameras scaled to images stored at another size (`images` False: every frame as the
    model states it), lens distortion undone."""
    cams, files, names, splits, lenses, photo = [], [], [], [], [], []
    skipped, missing = [], []
    points = None
    for model, paths, labels in parts:
        points = points if model.points is None else model.points
        for cam, lens, file, name, label in zip(model.cameras, model.lenses, paths, model.names, labels):
            if images and (file is None or not file.is_file()):
                skipped.append(name)
                missing.append(file)
                continue
            if images:
                cam = _at_image_size(cam, file, model)
            cams.append(undistorted_camera(cam, lens))
            files.append(file)
            names.append(Path(name).stem)
            splits.append(label)
            lenses.append(lens)
            photo.append(cam)
    if not cams:
        first = next((m for m in missing if m is not None), None)
        raise DatasetError(f"{first or path}: image not found; none of the {len(skipped)} frames of {source} has "
                           f"its image")
    if skipped:
        shown = ", ".join(str(m) for m in missing[:3] if m is not None)
        warnings.warn(f"{source}: {len(skipped)} of {len(skipped) + len(cams)} frames skipped: image missing"
                      + (f" ({shown}{', ...' if len(missing) > 3 else ''})" if shown else ""), stacklevel=3)
    return Capture(source, kind, cams, files, names, splits, lenses, photo, points, skipped)


def _at_image_size(cam: Camera, file: Path, model) -> Camera:
    """`cam` scaled to the size its image is stored at, where the model states a size and the
    image is a scaled copy (a downscaled copy of the images); other sizes are refused by name."""
    try:
        with Image.open(file) as im:
            width, height = im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise DatasetError(f"{file}: cannot read image: {exc}") from None
    if (width, height) == (cam.width, cam.height):
        return cam
    sx, sy = width / cam.width, height / cam.height
    if isinstance(model, ColmapModel):
        of = f"the model {model.images_file.with_name('cameras' + model.images_file.suffix)}"
    else:
        of = "its frame in the transforms file" if model.stated_size else "the first image"
    # A copy scaled by one factor, each side rounded: within a pixel of that factor on both sides.
    if not model.stated_size or abs(sx * cam.height - height) > 1.0 or abs(sy * cam.width - width) > 1.0:
        raise DatasetError(f"{file}: size {width}x{height} differs from the {cam.width}x{cam.height} of {of} "
                           f"(and is not a scaled copy of it)")
    return Camera(cam.world_to_cam, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy, width, height)


def _undistort_rgba(rgba: np.ndarray, photo: Camera, lens: Lens, target: Camera) -> np.ndarray:
    """Straight RGBA resampled into the pinhole `target`, in premultiplied space (as resizing)."""
    if (rgba[..., 3] == 1).all():
        return undistort_image(rgba, photo, lens, target)
    return premultiplied(rgba, lambda x: undistort_image(x, photo, lens, target))
