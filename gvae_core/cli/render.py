"""`gvae render FILE.ply --out DIR [--cameras CAPTURE | --orbit K] [--height H] [--background R,G,B]
[--antialias MODE] [--train-cameras CAPTURE] [--train-resolution H] [--trained classic|mip]`:
render a 3DGS PLY on the CPU and write one PNG per camera, over the background the cloud was
trained over (stored with it) unless told otherwise."""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

from ..antialias import (ANTIALIAS_MODES, DEFAULT_ANTIALIAS, DILATION_KEY, FILTER_KEY, cameras_at_height,
                         with_training_cameras)
from ..atomic import atomic_write
from ..camera import Camera, orbit
from ..capture import load_cameras, read_capture
from . import DEVICE_HELP
from .sfm import prepare_capture


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="render a 3DGS PLY to PNG images (CPU)",
        description="Render a 3DGS PLY with the project's differentiable splatting renderer and "
        "write one PNG per camera: the cameras of a capture (a transforms*.json, a COLMAP model, a "
        "NeRF-Synthetic folder; lens distortion undone), or K cameras orbiting the cloud (z up). "
        "Drawn over the background the cloud was trained over (stored in PLYs gvae trains) unless "
        "--background says otherwise.")
    p.add_argument("file", type=Path, help="the .ply file")
    p.add_argument("--out", type=Path, required=True, help="folder for the PNGs (created if missing)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--cameras", "--transforms", type=Path, dest="cameras", metavar="CAPTURE",
                     help="the cameras of a capture: a transforms*.json, a COLMAP model or capture folder, a "
                          "NeRF-Synthetic folder (every frame; default: --orbit)")
    src.add_argument("--orbit", type=int, metavar="K", help="K cameras on a circle around the cloud (default 8)")
    p.add_argument("--height", type=int, help="image height in pixels (default: the transforms' image "
                   "size, or 400 for --orbit); the width keeps the aspect ratio")
    p.add_argument("--background", default=None,
                   help="background colour r,g,b in [0,1] (default: the one the cloud was trained over, stored "
                        "with it; black for a cloud that does not say)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3), help="SH bands to use (default: all)")
    p.add_argument("--elevation", type=float, default=30.0, help="--orbit elevation in degrees (default 30)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.add_argument("--sanitize", action="store_true", help="drop Gaussians with non-finite values")
    p.add_argument("--antialias", choices=ANTIALIAS_MODES, default=None,
                   help="classic: +0.3 px² in the rendered image's pixels (the reference 3DGS); matched: that "
                   "dilation held in world units at the training sampling (the PLY's gvae_dilation_3D); mip: "
                   "Mip-Splatting's 3D filter (the PLY's filter_3D) and 2D Mip filter; auto: mip with filter_3D, "
                   f"else matched with gvae_dilation_3D, else classic (default: {DEFAULT_ANTIALIAS})")
    p.add_argument("--train-cameras", type=Path, metavar="CAPTURE",
                   help="the capture the cloud was trained from (a transforms JSON, a COLMAP model): its cameras set "
                   "the size --trained calls for (replacing one in the file), for a PLY from a tool that does not "
                   "store it (default: none)")
    p.add_argument("--train-resolution", type=int, metavar="H",
                   help="the image height the cloud was trained at: the --train-cameras scaled to it, or "
                   "without --train-cameras the rendering cameras at that height stand in for the training ones "
                   "(default: none: the --train-cameras as they are)")
    p.add_argument("--trained", choices=("classic", "mip"), default="classic",
                   help="with --train-cameras/--train-resolution: how the cloud was trained, classic (the "
                   "reference 3DGS: sets gvae_dilation_3D) or mip (Mip-Splatting: sets filter_3D); default classic")
    p.set_defaults(func=run)


def _parse_background(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"--background must be three numbers r,g,b, got {text!r}")
    return values  # type: ignore[return-value]


def orbit_cameras(means: np.ndarray, k: int, height: int, elevation_deg: float) -> list[Camera]:
    """`k` cameras looking at the cloud's median, far enough to see 95% of it with a 50° lens."""
    if k <= 0:
        raise ValueError(f"--orbit needs a positive number of cameras, got {k}")
    if len(means):
        center = np.median(means, 0)
        reach = float(np.percentile(np.linalg.norm(means - center, axis=1), 95))
    else:
        center, reach = np.zeros(3), 1.0
    radius = max(reach, 1e-6) / math.sin(math.radians(25.0)) * 1.1
    return orbit(k, radius, math.radians(elevation_deg), target=center, width=height, height=height,
                 fov_x=math.radians(50.0))


def run(args: argparse.Namespace) -> int:
    # Idle OpenMP threads should yield rather than spin: on a shared machine spinning threads
    # stall each other. Only effective when torch is not imported yet (the usual CLI case).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from ..ply import read_ply
    from ..rendering import RenderSettings, render, resolve_device

    if args.height is not None and args.height <= 0:
        raise ValueError(f"--height must be positive, got {args.height}")
    if args.train_resolution is not None and args.train_resolution <= 0:
        raise ValueError(f"--train-resolution must be a positive image height, got {args.train_resolution}")
    for capture_path in (args.cameras, args.train_cameras):  # a folder of photos: its cameras by SfM first
        prepare_capture(capture_path)
    train_cams = load_cameras(args.train_cameras) if args.train_cameras is not None else None
    device = resolve_device(args.device)
    cloud = read_ply(args.file, sanitize=args.sanitize)
    if args.background is not None:
        background = _parse_background(args.background)
    else:
        background = cloud.background or (0.0, 0.0, 0.0)
        print(f"background {','.join(f'{v:g}' for v in background)} ("
              + ("the one the cloud was trained over)" if cloud.background else "the file does not say; black)"))
    cams, names = _cameras(args, cloud)
    if train_cams is not None or args.train_resolution is not None:
        train_cams = cameras_at_height(cams if train_cams is None else train_cams, args.train_resolution)
        cloud = with_training_cameras(cloud, train_cams, trained=args.trained)
        key = FILTER_KEY if args.trained == "mip" else DILATION_KEY
        print(f"{key} from {len(train_cams)} training camera(s) at {train_cams[0].width}x{train_cams[0].height}")
    settings = RenderSettings() if args.antialias is None else RenderSettings(antialias=args.antialias)
    if device.type == "cpu":  # (on a GPU its own memory is the limit, which torch reports)
        check_views_memory(cloud, cams, settings, args.sh_degree)
    cloud = cloud.to_torch(device=device)
    from PIL import Image

    args.out.mkdir(parents=True, exist_ok=True)
    width = max(3, len(str(len(cams) - 1)))
    for i, (cam, name) in enumerate(zip(cams, names)):
        start = time.perf_counter()
        out = render(cloud, cam, background=background, sh_degree=args.sh_degree, settings=settings)
        pixels = (out.image.clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        del out
        target = args.out / f"{i:0{width}d}_{Path(name).stem}.png"
        atomic_write(target, lambda f, p=pixels: Image.fromarray(p).save(f, format="PNG"))
        print(f"{target} ({cam.width}x{cam.height}, {time.perf_counter() - start:.2f} s)")
    return 0


def _cameras(args: argparse.Namespace, cloud) -> tuple[list[Camera], list[str]]:
    """The cameras to render and their names: the capture's (--cameras; at --height), else --orbit's."""
    if args.cameras is not None:
        capture = read_capture(args.cameras, images=False)
        cams, names = capture.cameras, capture.names
        if args.height:
            cams = [c.scaled(args.height) for c in cams]
        return cams, names
    cams = orbit_cameras(np.asarray(cloud.means, np.float64), 8 if args.orbit is None else args.orbit,
                         args.height or 400, args.elevation)
    return cams, [f"orbit_{i:03d}" for i in range(len(cams))]


#: The heights of the two small renders whose tile pairs say how many pairs a larger one makes.
PROBE_HEIGHTS = (512, 1024)


def check_views_memory(cloud, cams: list[Camera], settings, sh_degree: int | None = None) -> None:
    """Refuse (`resources.NotEnoughMemoryError`, saying the largest height that fits) views too
    large to render in the memory available now, before any is drawn: each size once, estimated
    for a dense cloud, and where that does not fit, again with the pairs this cloud makes."""
    from ..rendering.compiled import use_compiled
    from ..resources import NotEnoughMemoryError, check_render_memory

    degree = cloud.sh_degree if sh_degree is None else min(int(sh_degree), cloud.sh_degree)
    extra = sum(int(np.prod(np.shape(v)[1:], dtype=np.int64)) for v in cloud.extra.values())
    sizes = {(c.height, c.width): c for c in cams}
    how = {"extra_values": extra, "compiled": use_compiled(settings.kernels, "cpu", settings.dtype)}
    for (h, w), cam in sorted(sizes.items(), key=lambda kv: -kv[0][0] * kv[0][1]):
        try:
            check_render_memory(len(cloud), h, w, degree, **how)
        except NotEnoughMemoryError:
            check_render_memory(len(cloud), h, w, degree, pairs_per_pixel=_pairs_per_pixel(cloud, cam, settings,
                                                                                            sh_degree), **how)


def _pairs_per_pixel(cloud, cam: Camera, settings, sh_degree: int | None) -> float:
    """Gaussian-tile pairs per pixel that `cloud` makes seen through `cam`, from the pairs of two
    small renders (binned, not drawn): the rise in pairs per pixel between them, which falls as
    the image grows, carried to `cam`'s size (so an overestimate beyond them)."""
    from ..rendering import prepare_view

    counts = []
    for height in PROBE_HEIGHTS:
        view = cam.scaled(height)
        counts.append((view.width * view.height, prepare_view(cloud, view, settings, sh_degree=sh_degree)[1].num_pairs))
    (px1, p1), (px2, p2) = counts
    rise = max(p2 - p1, 0) / max(px2 - px1, 1)
    pixels = cam.width * cam.height
    return max(p2 + rise * (pixels - px2) - len(cloud), 0.0) / pixels
