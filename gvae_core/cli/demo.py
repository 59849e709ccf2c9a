"""`gvae demo`: refine the bundled trained scene two ways, without its images (refine's default: the
detail model, with the fidelity check) and with them (`refine(images=...)`: the changes fitted to
its training images), and show, at twice its training resolution, the unrefined cloud, both refined
ones and the ground truth side by side, with zoomed crops and PSNRs; and the PSNR at the training
resolution, which both refinements keep."""

from __future__ import annotations

import argparse
from pathlib import Path

from . import progress_lines

#: A scene the project trained itself, held out of the bundled model's training: the last training
#: stage, its training images and ground-truth test views at twice its resolution.
TRAINED_EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "trained"
#: Each crop is this fraction of the image side, drawn this many times larger.
CROP, ZOOM = 0.3, 3


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the main job on the bundled example",
                              description="Refine the bundled trained scene (a chair the model never saw) without "
                              "and with its training images and write the refined PLYs and a comparison at twice the "
                              "training resolution: the unrefined cloud, the two refined ones and the ground truth, "
                              "with crops and PSNRs. "
                              "Without the bundled example or model: write an example cloud and describe it.")
    p.add_argument("--out", type=Path, default=Path("examples/example.ply"),
                   help="where the fallback example PLY goes (default: %(default)s)")
    p.add_argument("--steps", type=int, default=1, help="octaves the refinement covers (default: 1)")
    p.add_argument("--results", type=Path, default=Path("out/demo"),
                   help="where the refined PLYs and the comparison go (default: %(default)s)")
    p.add_argument("--fit-steps", type=int, default=None, metavar="N",
                   help="optimiser steps per octave of the fit to the images (default: superres.SuperResConfig's)")
    p.set_defaults(func=run)


def trained_example() -> Path | None:
    """The bundled trained example folder, when it and the bundled model are both present."""
    from ..detail import default_detail_dir
    from ..detail.persistence import CONFIG

    if (TRAINED_EXAMPLE / "scene.ply").is_file() and (default_detail_dir() / CONFIG).is_file():
        return TRAINED_EXAMPLE
    return None


def _crop_box(a, b, size: int) -> tuple[int, int]:
    """Top-left corner of the size x size window where images a and b differ most (where the
    models changed the picture), found on a coarse grid."""
    import numpy as np

    diff = np.abs(a - b).sum(-1)
    h, w = diff.shape
    best, corner = -1.0, (0, 0)
    for y in range(0, max(h - size, 0) + 1, max(1, size // 4)):
        for x in range(0, max(w - size, 0) + 1, max(1, size // 4)):
            v = float(diff[y:y + size, x:x + size].sum())
            if v > best:
                best, corner = v, (y, x)
    return corner


def _sheet(rows: list[list]):
    """The images of each row side by side, the rows one under another, on white."""
    from PIL import Image

    width = max(sum(img.width for img in row) for row in rows)
    sheet = Image.new("RGB", (width, sum(max(img.height for img in row) for row in rows)), (255, 255, 255))
    top = 0
    for row in rows:
        left = 0
        for img in row:
            sheet.paste(img, (left, top))
            left += img.width
        top += max(img.height for img in row)
    return sheet


def run_trained(folder: Path, args: argparse.Namespace) -> int:
    """Refine the trained example; write the refined PLY and the comparison, print the PSNRs."""
    import numpy as np
    from PIL import Image, ImageDraw

    from ..capture import load_nerf_synthetic
    from ..losses import psnr
    from ..ply import read_ply, write_ply
    from ..refinement import refine
    from ..rendering import RenderSettings, render

    cloud = read_ply(folder / "scene.ply")
    views = load_nerf_synthetic(folder, "test")
    print(f"trained example {folder}: {len(cloud)} Gaussians, SH degree {cloud.sh_degree}; ground truth: "
          f"{len(views)} test views at {views.cameras[0].height} px")
    print("refine without the images (the detail model):")
    result = refine(cloud, steps=args.steps, progress=lambda f, msg: print(f"  [{f:4.0%}] {msg}"))
    print(f"refine with the training images of {folder}:")
    fit = {} if args.fit_steps is None else {"steps": args.fit_steps}
    fitted = refine(cloud, steps=args.steps, images=folder, fit=fit, progress=progress_lines())
    out: Path = args.results
    out.mkdir(parents=True, exist_ok=True)
    write_ply(result.cloud, out / "refined.ply")
    write_ply(fitted.cloud, out / "refined_with_images.ply")

    settings = RenderSettings(antialias="auto")  # the example carries its filter: the mip render

    def draw(c, cam):
        return render(c, cam, background=(1.0, 1.0, 1.0), settings=settings).image.clamp(0, 1).numpy()

    truth = views.composite((1.0, 1.0, 1.0))
    rows, scores = [], []
    size = int(CROP * views.cameras[0].height)
    for cam, gt in zip(views.cameras, truth):
        images = [draw(c, cam) for c in (cloud, result.cloud, fitted.cloud)]
        scores.append([psnr(img, gt) for img in images])
        y, x = _crop_box(images[0], images[2], size)
        panels = images + [gt]
        crops = [np.kron(p[y:y + size, x:x + size], np.ones((ZOOM, ZOOM, 1))) for p in panels]
        row = [Image.fromarray((p * 255 + 0.5).astype(np.uint8)) for p in panels + crops]
        labels = (f"unrefined {scores[-1][0]:.2f} dB", f"detail model {scores[-1][1]:.2f} dB",
                  f"with the images {scores[-1][2]:.2f} dB", "ground truth")
        for img, label in zip(row[:4], labels):
            ImageDraw.Draw(img).text((3, 2), label, fill=(0, 0, 0))
        ImageDraw.Draw(row[0]).rectangle([x, y, x + size, y + size], outline=(255, 0, 0))
        rows.append(row)
    _sheet(rows).save(out / "comparison.png")
    # the README's picture (docs/demo.png): the first view, its four panels over their crops, in 256 colours
    _sheet([rows[0][:4], rows[0][4:]]).quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(
        out / "demo.png", optimize=True)
    print(f"\nPSNR against the ground truth at {views.cameras[0].height} px (twice the training resolution), "
          f"rendered with the anti-aliasing filter:")
    print("| view | unrefined | detail model (no images) | change | with the images | change |\n"
          "|---|---|---|---|---|---|")
    for i, (b, a, u) in enumerate(scores + [list(np.mean(scores, 0))]):
        print(f"| {i if i < len(scores) else 'mean'} | {b:.2f} dB | {a:.2f} dB | {a - b:+.2f} dB | {u:.2f} dB | "
              f"{u - b:+.2f} dB |")
    low = [cam.scaled(cam.height // 2) for cam in views.cameras]  # the training resolution
    kept = [min(100.0, psnr(draw(c, cam), draw(cloud, cam))) for c in (result.cloud, fitted.cloud) for cam in low]
    print(f"\nAt the training resolution ({low[0].height} px) both refined clouds draw as the unrefined one: PSNR "
          f"between them {min(kept):.1f} dB or more (100: identical).")
    print(f"\nwrote {out / 'refined.ply'} ({len(result.cloud)} Gaussians) and {out / 'refined_with_images.ply'} "
          f"({len(fitted.cloud)}: {len(fitted.added)} added that draw only above the training resolution); each "
          f"carries its Gaussians' changes per octave, drawn by `gvae render` and the Blender add-on (`gvae refine "
          f"--bake 2` writes a plain PLY for other tools); and {out / 'comparison.png'} (per view: unrefined, the "
          f"detail model, with the images, ground truth; then the same four zoomed {ZOOM}x where the images changed "
          f"the picture most, red box), {out / 'demo.png'} (its first view, small: the README's picture)")
    return 0


def run(args: argparse.Namespace) -> int:
    from ..examples import write_example
    from ..ply import read_ply
    from .info import describe

    folder = trained_example()
    if folder is not None:
        return run_trained(folder, args)
    path: Path = args.out
    if path.exists():
        print(f"using the existing example {path}")
    else:
        write_example(path)
        print(f"wrote the example cloud to {path}")
    print(describe(read_ply(path), title=str(path)))
    print(f"\nexample PLY: {path.resolve()}  (inspect any PLY with `gvae info FILE.ply`)")
    return 0
