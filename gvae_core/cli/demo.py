"""`gvae demo`: write the bundled example cloud (if missing) and summarise it."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the main job on the bundled example",
                              description="Write the example PLY (a rainbow torus of Gaussians, "
                              "SH degree 3) if it is missing, then print `gvae info` for it.")
    p.add_argument("--out", type=Path, default=Path("examples/example.ply"),
                   help="where the example PLY lives (default: %(default)s)")
    p.add_argument("--steps", type=int, default=2, help="refinement steps on the trained example (default: 2)")
    p.add_argument("--results", type=Path, default=Path("out/demo"),
                   help="where the refined PLY and the before/after render go (default: %(default)s)")
    p.set_defaults(func=run)


#: A small scene the project trained itself (last stage PLY + its lineage), shipped in the repository.
TRAINED_EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "trained"


def trained_example() -> Path | None:
    """The bundled trained example folder, when it and the bundled model are both present."""
    from ..vae import default_model_dir

    if (TRAINED_EXAMPLE / "scene.ply").is_file() and (default_model_dir() / "config.json").is_file():
        return TRAINED_EXAMPLE
    return None


def run_trained(folder: Path, args: argparse.Namespace) -> int:
    """Refine the trained example `args.steps` steps; write the refined PLY and before/after renders."""
    import numpy as np
    from PIL import Image

    from ..hessian import default_views
    from ..lineage import Lineage
    from ..ply import read_ply, write_ply
    from ..refinement import refine
    from ..rendering import render

    cloud = read_ply(folder / "scene.ply")
    lineage = Lineage.load(folder / "lineage.npz") if (folder / "lineage.npz").is_file() else None
    print(f"trained example {folder}: {len(cloud)} Gaussians, SH degree {cloud.sh_degree}"
          f"{f', lineage of {lineage.n_stages} stages {lineage.resolutions}' if lineage else ''}")
    result = refine(cloud, steps=args.steps, budget="auto", lineage=lineage,
                    progress=lambda f, msg: print(f"  [{f:4.0%}] {msg}"))
    out: Path = args.results
    out.mkdir(parents=True, exist_ok=True)
    write_ply(result.cloud, out / "refined.ply")
    cam = default_views(cloud, 1, resolution=256)[0]
    panels = [render(c, cam, background=(1.0, 1.0, 1.0)).image.detach().clamp(0, 1).numpy()
              for c in (cloud, result.cloud)]
    Image.fromarray((np.concatenate(panels, 1) * 255 + 0.5).astype(np.uint8)).save(out / "before_after.png")
    print(f"wrote {out / 'refined.ply'} and {out / 'before_after.png'} (left: input, right: +{args.steps})")
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
