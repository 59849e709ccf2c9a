"""`gvae convert IN OUT`: a splat file in any format the project reads, written in the one OUT's name asks for."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "convert", help="convert a splat file between .ply, compressed PLY, .spz, .splat, .sog and .glb",
        description="Read IN (3DGS or compressed PLY, .splat, .spz, .sog, a SOG meta.json or its folder, a glTF "
        ".glb or .gltf; the format found from the content) and write OUT in the format its name asks for: .ply "
        "(3DGS), .compressed.ply (SuperSplat), .spz (Niantic), .splat, .sog (PlayCanvas bundle), meta.json (SOG "
        "images beside it), .glb or .gltf (KHR_gaussian_splatting; .gltf with its .bin). An OUT name it cannot "
        "write is refused before anything is read.")
    p.add_argument("input", type=Path, help="the splat file to read")
    p.add_argument("output", type=Path, help="the file to write (its name picks the format)")
    p.add_argument("--sh-degree", type=int, choices=(0, 1, 2, 3),
                   help="drop the SH bands above this degree (default: keep what IN has)")
    p.add_argument("--spz-version", type=int, choices=(2, 3, 4),
                   help="the .spz version to write (default 3; 4 needs the zstandard package)")
    p.add_argument("--sanitize", action="store_true",
                   help="drop Gaussians with NaN or infinite values instead of failing on them")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..formats import FORMATS, detect_format, output_format, read_splat_file, write_splat_file
    from ..formats.spz import WRITE_VERSION

    out_fmt = output_format(args.output)
    if args.spz_version is not None and out_fmt != "spz":
        raise ValueError(f"--spz-version applies to .spz output, not to {args.output} ({FORMATS[out_fmt]})")
    start = time.perf_counter()
    in_fmt = detect_format(args.input)
    cloud = read_splat_file(args.input, sanitize=args.sanitize)
    degree = cloud.sh_degree
    if args.sh_degree is not None and args.sh_degree < degree:
        cloud = cloud.with_sh_degree(args.sh_degree)
    write_splat_file(cloud, args.output, spz_version=args.spz_version or WRITE_VERSION)
    kept = f"SH degree {cloud.sh_degree}" + (f" (of {degree})" if cloud.sh_degree != degree else "")
    print(f"{args.input} ({FORMATS[in_fmt]}) -> {args.output} ({FORMATS[out_fmt]}): {len(cloud)} Gaussians, "
          f"{kept}, in {time.perf_counter() - start:.2f} s")
    return 0
