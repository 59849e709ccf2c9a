"""`gvae info FILE`: what a splat file (3DGS or compressed PLY, .splat, .spz, .sog, .glb) holds and if it is sound."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from ..cloud import GaussianCloud
from ..conventions import SH_REST_COUNTS


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="summarise a splat file (.ply, .splat, .spz, .sog, .glb) and validate it",
                              description="Print the format, Gaussian count, SH degree, bounding box, "
                              "opacity and scale statistics, extra properties, what was read as what it "
                              "means (infinite opacities, flat axes) and the validation report of a 3DGS "
                              "PLY, a compressed (SuperSplat) PLY, a .splat, an .spz, a SOG scene (.sog, "
                              "meta.json or its folder) or the splats of a glTF file (.glb, .gltf; what else it "
                              "holds is named); the format is found from the content.")
    p.add_argument("file", type=Path, help="the .ply, .splat, .spz, .sog, .glb or .gltf file (or a SOG meta.json or "
                   "folder)")
    p.add_argument("--sanitize", action="store_true",
                   help="drop Gaussians with non-finite values instead of failing on them")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..formats import FORMATS, detect_format, read_splat_file

    fmt = detect_format(args.file)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_splat_file(args.file, sanitize=args.sanitize)
    print(describe(cloud, title=f"{args.file} ({FORMATS[fmt]})", notes=[str(w.message) for w in caught]))
    return 0


def _stats(label: str, values: np.ndarray, fmt: str = "{:.4g}") -> str:
    if values.size == 0:
        return f"{label}: (none)"
    q = np.percentile(values, [0, 5, 50, 95, 100])
    parts = ", ".join(f"{name} {fmt.format(v)}" for name, v in zip(("min", "p5", "median", "p95", "max"), q))
    return f"{label}: {parts}, mean {fmt.format(values.mean())}"


def describe(cloud: GaussianCloud, title: str = "cloud", notes: list[str] = ()) -> str:
    """A human-readable summary of a cloud (the text `gvae info` prints), with `notes` (what the
    reader said: values read as what they mean, rows dropped) under "read:"."""
    c = cloud.numpy()
    n = len(c)
    lines = [title, *(f"  read: {note}" for note in notes),
             f"  Gaussians: {n}",
             f"  SH degree: {c.sh_degree} ({SH_REST_COUNTS[c.sh_degree]} rest coefficients per channel)"]
    if n:
        lo, hi = c.means.min(0), c.means.max(0)
        fmt = lambda v: "(" + ", ".join(f"{x:.4g}" for x in v) + ")"  # noqa: E731
        lines.append(f"  bounding box: min {fmt(lo)}, max {fmt(hi)}, size {fmt(hi - lo)}")
        opac = c.activated_opacities()
        lines.append("  " + _stats("opacity (sigmoid)", opac, "{:.3f}"))
        lines.append(f"  opacity < 1/255 (invisible): {int((opac < 1 / 255).sum())}")
        scales = c.activated_scales()
        lines.append("  " + _stats("largest scale (exp, world units)", scales.max(1)))
        lines.append("  " + _stats("smallest scale", scales.min(1)))
    if c.extra:
        lines.append("  extra properties: " + ", ".join(f"{k} ({v.dtype})" for k, v in c.extra.items()))
    else:
        lines.append("  extra properties: none")
    lines += ["  " + line for line in str(c.validate()).splitlines()]
    return "\n".join(lines)
