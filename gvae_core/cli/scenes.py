"""`gvae make-scene` and `gvae list-scenes`: the Blender-made benchmark scenes."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def register(subparsers) -> None:
    from ..scenes import PROFILES

    p = subparsers.add_parser(
        "make-scene", help="render a benchmark scene with Blender (NeRF-Synthetic format, cached)",
        description="Render procedural benchmark scenes with Blender's Cycles into NeRF-Synthetic folders "
                    "(transforms_train/test.json, RGBA PNGs, mesh.ply, gt_points.npy). Results are cached by "
                    "name, profile and seed; a second call returns at once. Needs bpy (pip install bpy==5.0.1).")
    p.add_argument("names", nargs="+", metavar="NAME", help="scene name(s) from `gvae list-scenes`, or 'all'")
    p.add_argument("--out", type=Path, default=None,
                   help="write the scene here (with several names: one sub-folder per scene); "
                        "default: print the cache folder")
    p.add_argument("--profile", default="tiny", choices=list(PROFILES),
                   help="tiny: 64 px, 8+4 views; default: 400 px, 60+20; full: 800 px, 100+200 (default: tiny)")
    p.add_argument("--seed", type=int, default=0, help="scene and camera seed (default 0)")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="cache folder (default: $GVAE_CACHE_DIR or ~/.cache/gvae)")
    p.add_argument("--threads", type=int, default=None, help="Cycles threads (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no per-view progress")
    p.set_defaults(func=_make)

    q = subparsers.add_parser("list-scenes", help="list the benchmark scenes and what each one stresses")
    q.add_argument("--json", action="store_true", help="machine-readable output")
    q.set_defaults(func=_list)


def _make(args: argparse.Namespace) -> int:
    from ..scenes import BlenderNotAvailable, list_scenes, make_scene

    names = list_scenes() if args.names == ["all"] else list(dict.fromkeys(args.names))
    for name in names:
        if name not in list_scenes():
            raise ValueError(f"unknown scene {name!r}; available: {', '.join(list_scenes())} (or 'all')")
    for name in names:
        out = None if args.out is None else (args.out if len(names) == 1 else args.out / name)
        start = time.perf_counter()
        try:
            path = make_scene(name, out, profile=args.profile, seed=args.seed, cache=args.cache_dir,
                              threads=args.threads, verbose=not args.quiet)
        except BlenderNotAvailable as exc:
            print(f"gvae make-scene: error: {exc}", file=sys.stderr)
            return 2
        except RuntimeError as exc:
            print(f"gvae make-scene: error: {exc}", file=sys.stderr)
            return 1
        print(f"{name}: {path} ({time.perf_counter() - start:.1f} s)")
    return 0


def _list(args: argparse.Namespace) -> int:
    from ..scenes import describe_scenes

    scenes = describe_scenes()
    if args.json:
        print(json.dumps(scenes, indent=2))
    else:
        width = max(map(len, scenes))
        for name, what in scenes.items():
            print(f"{name:<{width}}  {what}")
    return 0
