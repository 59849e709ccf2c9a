"""Render one scene into a folder: `python -m gvae_core.scenes.build NAME OUT [--profile P]
[--seed S] [--threads N]`. Meant to run in its own process (Blender's state is per process);
`gvae_core.scenes.make_scene` calls it and moves the finished folder into the cache. Progress
goes to stderr; Blender's own render log is silenced."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from ..camera import Camera
from . import GENERATOR_VERSION, MARKER, PROFILES, blender, cameras, scene_key
from . import geometry as g
from .library import SCENES


@contextlib.contextmanager
def _quiet():
    """Send file descriptors 1 and 2 (where Blender logs every render and saved file) to
    /dev/null; our own progress goes to a duplicate of the original stderr."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _frames(c2ws: np.ndarray, split: str) -> list[dict]:
    return [{"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": c2w.tolist()}
            for i, c2w in enumerate(c2ws)]


def write_mesh_ply(path: Path, verts: np.ndarray, tris: np.ndarray) -> None:
    """Binary little-endian PLY with float32 vertices and int32 triangle faces."""
    v = np.empty(len(verts), [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    v["x"], v["y"], v["z"] = verts.T
    f = np.empty(len(tris), [("vertex_indices", "i4", (3,))])
    f["vertex_indices"] = tris
    faces = PlyElement.describe(f, "face", len_types={"vertex_indices": "u1"}, val_types={"vertex_indices": "i4"})
    PlyData([PlyElement.describe(v, "vertex"), faces]).write(str(path))


def generate(name: str, out: Path, profile: str = "tiny", seed: int = 0, threads: int | None = None,
             log=lambda msg: print(msg, file=sys.stderr, flush=True), render: bool = True,
             limit_views: int | None = None) -> dict:
    """Build, render and export one scene into the folder `out`; returns the metadata written to
    scene.json. With `render=False` only the scene, cameras and ground truth are made;
    `limit_views` keeps only the first views of each split (timing probes)."""
    prof = PROFILES[profile]
    threads = int(threads or os.cpu_count() or 1)
    # OpenImageDenoise pins its threads to cores by default, which stalls it badly when other
    # processes share the cores; read when Cycles creates the denoiser.
    os.environ.setdefault("OIDN_SET_AFFINITY", "0")
    os.environ.setdefault("OIDN_NUM_THREADS", str(threads))
    out = Path(out)
    t0 = time.perf_counter()
    blender.reset()
    rng = np.random.default_rng([seed, 0])
    SCENES[name].build(rng)
    blender.fit_in_sphere(cameras.OBJECT_RADIUS)
    cam_obj = blender.setup_render(prof.resolution, prof.samples, seed, threads, cameras.CAMERA_ANGLE_X)
    splits = {"train": cameras.train_views(prof.n_train, seed), "test": cameras.test_views(prof.n_test, seed)}
    if limit_views is not None:
        splits = {k: v[:limit_views] for k, v in splits.items()}
    timings = {"build": time.perf_counter() - t0}

    t1 = time.perf_counter()
    frame_s, frame_cpu_s = [], []  # wall and CPU (all threads) seconds per view
    for split, c2ws in splits.items():
        (out / split).mkdir(parents=True, exist_ok=True)
        if render:
            for i, c2w in enumerate(c2ws):
                tf, cf = time.perf_counter(), time.process_time()
                with _quiet():
                    blender.render_view(cam_obj, c2w, out / split / f"r_{i}.png")
                frame_s.append(time.perf_counter() - tf)
                frame_cpu_s.append(time.process_time() - cf)
                log(f"{name}: rendered {split} {i + 1}/{len(c2ws)} ({time.perf_counter() - t1:.1f} s)")
        doc = {"camera_angle_x": cameras.CAMERA_ANGLE_X, "frames": _frames(c2ws, split)}
        (out / f"transforms_{split}.json").write_text(json.dumps(doc, indent=2))
    timings["render"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    verts, tris = blender.world_triangles()
    write_mesh_ply(out / "mesh.ply", verts, tris)
    test_cams = [Camera.from_blender_c2w(c, cameras.CAMERA_ANGLE_X, prof.resolution, prof.resolution)
                 for c in splits["test"]]
    pts, _ = g.sample_surface(verts, tris, prof.gt_candidates, np.random.default_rng([seed, 3]))
    seen = blender.visible_points(pts, verts, tris, test_cams)
    np.save(out / "gt_points.npy", pts[seen].astype(np.float32))
    timings["ground_truth"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    log(f"{name}: mesh {len(tris)} triangles, {int(seen.sum())}/{len(pts)} sampled points visible to test views")

    import bpy

    meta = {"name": name, "profile": profile, "seed": seed, "key": scene_key(name, profile, seed),
            "generator_version": GENERATOR_VERSION, "blender": bpy.app.version_string,
            "resolution": prof.resolution, "n_train": len(splits["train"]), "n_test": len(splits["test"]),
            "samples": prof.samples, "complete": limit_views is None and render,
            "threads": threads, "rendered": render, "stresses": SCENES[name].stresses,
            "triangles": int(len(tris)), "gt_points": int(seen.sum()),
            "bounds": [verts.min(0).tolist(), verts.max(0).tolist()],
            "timings_s": {k: round(v, 3) for k, v in timings.items()},
            "frame_s": [round(v, 3) for v in frame_s], "frame_cpu_s": [round(v, 3) for v in frame_cpu_s]}
    (out / MARKER).write_text(json.dumps(meta, indent=2))
    return meta


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m gvae_core.scenes.build", description=__doc__.splitlines()[0])
    p.add_argument("name", choices=sorted(SCENES))
    p.add_argument("out", type=Path)
    p.add_argument("--profile", default="tiny", choices=sorted(PROFILES))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--no-render", action="store_true", help="build the scene and ground truth, skip the images")
    p.add_argument("--limit-views", type=int, default=None, metavar="N",
                   help="only the first N views of each split (for timing probes; not a complete scene)")
    args = p.parse_args(argv)
    generate(args.name, args.out, args.profile, args.seed, args.threads, render=not args.no_render,
             limit_views=args.limit_views)
    return 0


if __name__ == "__main__":
    sys.exit(main())
