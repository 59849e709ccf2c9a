"""Anti-aliasing across resolutions: how a cloud trained at H px renders at 1x, 1.5x and
2x H by each anti-aliasing mode, against 3DGS trained on the real 1.5x and 2x images.

Per scene (the six benchmark scenes of `SCENES`; the stages, iterations, render profile and test
views of the experiment's protocols, `gvae_core.experiment.PROTOCOLS`, trained with seed 0 into
the run cache `<cache>/runs/<protocol>-<hash of the configuration>/<scene>`), PSNR/SSIM against
the ground-truth test views and the seconds per rendered view, for:
- the classically trained training-resolution cloud rendered `classic` (today), `matched` (the
  classic dilation held in world units at the training cameras' sampling), with the
  Mip-Splatting filters (`mip`: the 3D filter from the training cameras and the 2D Mip filter),
  and with the 2D Mip filter alone (`mip`, no 3D filter);
- the cloud trained with the filters (`TrainConfig(antialias="mip")`, same stages up to the
  training resolution), rendered `mip` and `classic`;
- 3DGS continued on the real 1.5x and 2x images (the experiment's upper bounds), `classic`.
Training seconds of both runs are printed beside them.

`python -m gvae_core.benchmarks antialias` runs the quick profile on the six scenes (`--quick`: one
scene); `python -m gvae_core.benchmarks.antialias --profile full --jobs 2 --out DIR` the full one
(hours; resumable: runs resume after their last finished stage, and scenes already evaluated
into DIR are read back).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing
import os
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..antialias import DILATION_KEY, FILTER_KEY, dilation_3d, filter_3d
from ..capture import load_cameras, load_nerf_synthetic
from ..experiment import PROTOCOLS
from ..metrics.image import image_scores
from ..ply import read_ply
from ..scenes import cache_dir, make_scene
from ..train import TrainConfig, train_progressive

#: The scenes of the anti-aliasing measurement.
SCENES = ("plant", "crate", "materials", "bricks", "chair", "tableware")
SCALES = ("1x", "1.5x", "2x")

#: (label, which cloud, render mode): the rows of the table, in order.
ROWS = (
    ("3DGS 1x, classic render", "classic", "classic"),
    ("3DGS 1x, matched render", "classic", "matched"),
    ("3DGS 1x + Mip filters (3D + 2D)", "classic_mip", "mip"),
    ("3DGS 1x + 2D Mip filter only", "plain", "mip"),
    ("3DGS 1x trained with filters, mip render", "mip", "mip"),
    ("3DGS 1x trained with filters, classic render", "mip", "classic"),
    ("3DGS on real 1.5x images", "real_1.5x", "classic"),
    ("3DGS on real 2x images", "real_2x", "classic"),
)


@dataclass
class Run:
    """A trained progressive run of one scene: its folder, its scene folder, the heights of 1x,
    1.5x and 2x, the index of the training-resolution stage and how many test views to score."""

    scene: str
    scene_dir: Path
    run_dir: Path
    heights: tuple[int, ...]
    train_stage: int
    test_views: int | None

    def stage_cloud(self, stage: int):
        return read_ply(self.run_dir / f"stage_{stage}.ply")

    def log(self) -> list[dict]:
        return json.loads((self.run_dir / "log.json").read_text())


def train_config(profile: str, antialias: str = "classic") -> TrainConfig:
    """The run of the experiment's protocol `profile` (seed 0): classic through the real 1.5x and
    2x stages, or with `antialias="mip"` trained with the filters up to the training resolution
    only (only that cloud is used)."""
    p = PROTOCOLS[profile]
    if antialias == "classic":
        return TrainConfig.profile("legacy", resolutions=tuple(p.resolutions) + tuple(p.higher),
                                   iterations=tuple(p.iterations) + tuple(p.higher_iterations), seed=0,
                                   **p.train_overrides)
    return TrainConfig.profile("legacy", resolutions=p.resolutions, iterations=p.iterations, seed=0,
                               **{**p.train_overrides, "antialias": antialias})


def prepare(scene: str, profile: str, antialias: str = "classic", cache=None, say=print) -> Run:
    """Render the scene (cached) and train its run (cached under the hash of its configuration,
    resumable after the last finished stage)."""
    p = PROTOCOLS[profile]
    config = train_config(profile, antialias)
    scene_dir = make_scene(scene, profile=p.scene_profile, seed=0, cache=cache)
    blob = json.dumps({"scene_profile": p.scene_profile, "config": config.to_dict()}, sort_keys=True)
    run_dir = cache_dir(cache) / "runs" / f"{p.name}-{hashlib.sha256(blob.encode()).hexdigest()[:12]}" / scene
    try:
        done = int(json.loads((run_dir / "run.json").read_text())["stages_done"])
    except (OSError, ValueError, KeyError):
        done = 0
    if done < len(config.resolutions):
        say(f"[{scene}] training {antialias} {config.resolutions} px ({done} stages done) into {run_dir}")
        train_progressive(scene_dir, config, out_dir=run_dir, progress=False, threads=1)
    heights = tuple(p.resolutions[-1:]) + tuple(p.higher)
    return Run(scene, scene_dir, run_dir, heights, len(p.resolutions) - 1, p.test_views)


def _test_views(run: Run):
    out = {}
    for label, h in zip(SCALES, run.heights):
        v = load_nerf_synthetic(run.scene_dir, "test", resolution=h)
        if run.test_views is not None and run.test_views < len(v):
            pick = np.linspace(0, len(v) - 1, run.test_views).round().astype(int)
            v = type(v)([v.cameras[i] for i in pick], v.images[pick], v.alphas[pick], [v.names[i] for i in pick])
        out[label] = v
    return out


def evaluate_scene(classic: Run, mip: Run, background=(1.0, 1.0, 1.0)) -> dict:
    """Every row of ROWS at every scale for one scene, with render and training times."""
    k = classic.train_stage
    train_cams = [c.scaled(classic.heights[0]) for c in
                  load_cameras(classic.scene_dir / "transforms_train.json")]
    base = classic.stage_cloud(k)
    plain = base.replace(extra={key: v for key, v in base.extra.items() if key not in (FILTER_KEY, DILATION_KEY)})
    dilation = dilation_3d(base.means, train_cams)
    if DILATION_KEY in base.extra:  # written by the trainer: must be the training cameras' size
        assert np.allclose(base.extra[DILATION_KEY], dilation, rtol=1e-5), "stored gvae_dilation_3D differs"
    trained_mip = mip.stage_cloud(k)
    assert np.allclose(trained_mip.extra[FILTER_KEY], filter_3d(trained_mip.means, train_cams), rtol=1e-5)
    clouds = {
        "classic": plain.replace(extra={**plain.extra, DILATION_KEY: dilation}),
        "classic_mip": plain.replace(extra={**plain.extra, FILTER_KEY: filter_3d(base.means, train_cams)}),
        "plain": plain,
        "mip": trained_mip,
        "real_1.5x": classic.stage_cloud(k + 1),
        "real_2x": classic.stage_cloud(k + 2),
    }
    views = _test_views(classic)
    rows = []
    for label, which, mode in ROWS:
        cloud = clouds[which].to_torch()
        row = {"scene": classic.scene, "row": label, "cloud": which, "mode": mode, "n_gaussians": len(cloud)}
        for scale in SCALES:
            t0 = time.perf_counter()
            s = image_scores(cloud, views[scale], background, no_reference=False, antialias=mode)
            row[f"psnr_{scale}"], row[f"ssim_{scale}"] = s.psnr, s.ssim
            row[f"render_s_{scale}"] = (time.perf_counter() - t0) / max(s.n_views, 1)
        rows.append(row)
    logs = {"classic": classic.log(), "mip": mip.log()}
    train = {name: {"seconds_to_1x": sum(e["seconds"] for e in log[:k + 1]),
                    "cpu_seconds_to_1x": (sum(e["cpu_seconds"] for e in log[:k + 1])
                                          if all("cpu_seconds" in e for e in log[:k + 1]) else None),
                    "s_per_it_1x": log[k]["seconds_per_iteration"], "n_gaussians": log[k]["n_gaussians"],
                    "test_psnr_1x": log[k]["test_psnr"]} for name, log in logs.items()}
    return {"scene": classic.scene, "heights": [v.cameras[0].height for v in views.values()], "rows": rows,
            "train": train, "classic_run": str(classic.run_dir), "mip_run": str(mip.run_dir)}


def scene_job(name: str, profile: str, cache=None, out_dir=None) -> dict:
    """Prepare both runs of one scene (cached, resumable) and evaluate them (a worker's job)."""
    if out_dir is not None and (Path(out_dir) / f"{name}.json").is_file():
        return json.loads((Path(out_dir) / f"{name}.json").read_text())
    t0 = time.perf_counter()
    classic = prepare(name, profile, "classic", cache, _say)
    mip = prepare(name, profile, "mip", cache, _say)
    t1 = time.perf_counter()
    result = evaluate_scene(classic, mip)
    result["seconds"] = {"prepare": t1 - t0, "evaluate": time.perf_counter() - t1}
    _say(f"[{name}] evaluated in {time.perf_counter() - t1:.0f} s")
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / f"{name}.json").write_text(json.dumps(result, indent=1))
    return result


def _say(msg: str) -> None:
    print(time.strftime("%H:%M:%S ") + msg, flush=True)


def _one_thread() -> None:
    torch.set_num_threads(1)


def run_all(profile: str, scenes=None, *, jobs: int = 2, cache=None, out_dir=None) -> list[dict]:
    names = list(scenes or SCENES)
    if jobs <= 1:
        return [scene_job(n, profile, cache, out_dir) for n in names]
    ctx = multiprocessing.get_context("spawn")  # a forked torch process can hang in its thread pools
    with ProcessPoolExecutor(min(jobs, len(names)), mp_context=ctx, initializer=_one_thread) as pool:
        futures = [pool.submit(scene_job, n, profile, cache, out_dir) for n in names]
        return [f.result() for f in futures]


def tables(results: list[dict]) -> list[str]:
    """Markdown: the scene mean of every row, then PSNR per scene, then training times and goals."""
    lines = []
    labels = [r[0] for r in ROWS]
    cols = [f"{m}_{s}" for s in SCALES for m in ("psnr", "ssim")]
    lines.append("| mean over " + f"{len(results)} scenes | " + " | ".join(
        f"{m.upper()} {s}" for s in SCALES for m in ("psnr", "ssim")) + " | s/view 2x |")
    lines.append("|---|" + "---|" * (len(cols) + 1))
    mean = {}
    for label in labels:
        rows = [r for res in results for r in res["rows"] if r["row"] == label]
        mean[label] = {c: statistics.fmean(r[c] for r in rows) for c in cols + ["render_s_2x"]}
        lines.append(f"| {label} | " + " | ".join(f"{mean[label][c]:.2f}" if c.startswith("psnr")
                                                  else f"{mean[label][c]:.4f}" for c in cols)
                     + f" | {mean[label]['render_s_2x']:.3f} |")
    lines.append("")
    lines.append("| PSNR 1x / 1.5x / 2x | " + " | ".join(res["scene"] for res in results) + " |")
    lines.append("|---|" + "---|" * len(results))
    for label in labels:
        cells = []
        for res in results:
            (r,) = [r for r in res["rows"] if r["row"] == label]
            cells.append(" / ".join(f"{r[f'psnr_{s}']:.2f}" for s in SCALES))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("| training to 1x: wall s [CPU s], Gaussians | " + " | ".join(res["scene"] for res in results)
                 + " |")
    lines.append("|---|" + "---|" * len(results))
    for name in ("classic", "mip"):
        cells = []
        for res in results:
            t = res["train"][name]
            cpu = "" if t.get("cpu_seconds_to_1x") is None else f" [{t['cpu_seconds_to_1x']:.0f}]"
            cells.append(f"{t['seconds_to_1x']:.0f}{cpu}, {t['n_gaussians']}")
        lines.append(f"| trained {name} | " + " | ".join(cells) + " |")
    lines.append("")
    classic_1x = mean[labels[0]]["psnr_1x"]
    real_2x = mean["3DGS on real 2x images"]["psnr_2x"]
    for label in labels[1:6]:
        m = mean[label]
        lines.append(f"- {label}: 1x {m['psnr_1x'] - classic_1x:+.2f} dB against the classic render "
                     f"(goal >= -0.1); 2x {m['psnr_2x'] - real_2x:+.2f} dB against 3DGS on real 2x images "
                     f"(goal >= -3.0; classic render {mean[labels[0]]['psnr_2x'] - real_2x:+.2f})")
    return lines


def run(args) -> None:
    """`make bench`: the quick profile on all six scenes (`--quick`: chair only)."""
    scenes = ["chair"] if getattr(args, "quick", False) else None
    t0 = time.perf_counter()
    results = run_all("quick", scenes, jobs=max(1, min(2, os.cpu_count() or 1)))
    print(f"profile quick, {len(results)} scene(s), {time.perf_counter() - t0:.0f} s in all (training cached "
          "in the experiment's run cache); PSNR/SSIM against the ground-truth test views, white background")
    print("\n".join(tables(results)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.antialias", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profile", choices=list(PROTOCOLS), default="quick")
    parser.add_argument("--scenes", nargs="*", default=None, help="default: all six")
    parser.add_argument("--jobs", type=int, default=2, help="scenes at once, one torch thread each")
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None,
                        help="per-scene results (SCENE.json, read back when present) and results.json")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    t0 = time.perf_counter()
    results = run_all(args.profile, args.scenes, jobs=args.jobs, cache=args.cache_dir, out_dir=args.out)
    print(f"profile {args.profile}, {len(results)} scene(s), load average {os.getloadavg()[0]:.1f} at the end, "
          f"{time.perf_counter() - t0:.0f} s in all")
    print("\n".join(tables(results)))
    if args.out is not None:
        (args.out / "results.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
