"""Compaction: PSNR against the kept fraction for every way of removing Gaussians, on the quick
protocol's 3DGS runs (the runs `make report` trains; test split by default), splat-transform's
two decimations included; what views placed without cameras see of the shapes that fool a
placement (`views_coverage`); and the speed of a compaction at capture scale.

Per (scene, seed): the 100 px stage (the training resolution, its `gvae_dilation_3D`) compacted
to each fraction by: ours (`compact` as it is by default: the lowest-scoring tenth dropped, the
rest merged, then fine-tuned against its own renders, these scenes being small), scored from four
of its training cameras (what `gvae compact --cameras transforms_train.json` does) and from
placed views (what `gvae compact` does without cameras), each also not fine-tuned
(`distill=0`); ours merging everything that is seen (`prune=0`), the same merging with no score
(`random` weights: NanoGS-style, what splat-transform does), Hessian pruning (PUP 3D-GS without
fine-tuning), LightGaussian's global significance, opacity and random pruning (none of these
fine-tuned), and splat-transform 3.7.0's `--decimate` and `--decimate-adaptive`
(`benchmarks.splat_transform`: installed from npm into the cache on first use; skipped, with the
reason, where `node`/`npm` are missing). PSNR at 1x against the ground-truth test views (the
protocol's 8, `matched` render), minus the input's. With the training images (`--images`): two
rounds of removal and fine-tuning (the protocol's last-stage iterations each) for the Hessian and
for LightGaussian's score.

`python -m gvae_core.benchmarks compact` (environment: GVAE_COMPACT_SPLIT=test|validation,
GVAE_COMPACT_SEEDS=0,1,2, GVAE_COMPACT_OUT=folder for results.json and the plot;
GVAE_COMPACT_SPEED=0 skips the speed rows, GVAE_COMPACT_VIEWS=0 the placed views' table);
`--quick`: one validation scene, one seed, the speed at 100k only. `python -m
gvae_core.benchmarks.compact --help` runs parts of it with options (the scenes, fractions and rows of
docs/benchmarks/compact.md's tables; `--smoke`: the smallest size, to show that it runs).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..antialias import DILATION_KEY, with_training_cameras
from ..capture import load_nerf_synthetic
from ..compaction import PRUNE_FRACTION, compact, finetune, moments
from ..examples import example_cloud
from ..experiment import PROTOCOLS, SMOKE, Evaluator, prepare_scene
from ..metrics.image import image_scores
from ..ply import read_ply, write_ply
from ..resources import estimate_compact_memory, peak_rss_mb, reset_peak_rss
from ..scenes import SPLITS
from .splat_transform import PACKAGE
from .splat_transform import command as splat_transform_command

FRACTIONS = (0.7, 0.5, 0.3, 0.2, 0.1, 0.05)
OURS, NOT_TUNED, PLACED, PLACED_NOT_TUNED = ("ours", "ours, not fine-tuned", "ours, placed views",
                                             "ours, placed views, not fine-tuned")
MERGING_ONLY = "ours, merging only"


@dataclass(frozen=True)
class Method:
    """A `compact` row: its label, score, removal, the fraction dropped before merging, the
    fine-tuning against the input's own renders (`compact(distill=)`: "auto", the default, or
    iterations; in `rounds`, default one) and whether it is scored from VIEWS of the training cameras
    (else from placed views, as without cameras)."""

    label: str
    score: str = "hessian"
    removal: str = "merge"
    prune: float = PRUNE_FRACTION
    distill: int | str = 0
    cameras: bool = True
    rounds: int | None = None


#: The `compact` rows; splat-transform's come after these. "ours" is the default (fine-tuned
#: against its own renders, `AUTO_DISTILL` iterations, the scenes being small); "merging only"
#: merges all that is seen (no lowest-scoring tenth dropped first); the baselines are not
#: fine-tuned.
METHODS = (Method(OURS, distill="auto"), Method(NOT_TUNED), Method(PLACED, distill="auto", cameras=False),
           Method(PLACED_NOT_TUNED, cameras=False), Method(MERGING_ONLY, prune=0.0),
           Method("merge, no score", score="random"), Method("Hessian prune", removal="prune"),
           Method("LightGaussian", score="lightgaussian", removal="prune"),
           Method("opacity", score="opacity", removal="prune"), Method("random", score="random", removal="prune"))
ST_MODES = ("decimate", "decimate-adaptive")
#: Scoring views of every `compact` row scored from the training cameras: this many of them.
VIEWS = 4
#: Ours fine-tuned longer against the input's own renders (two rounds of the protocol's last-stage
#: iterations, placed views: the earlier default of `--distill`), at these fractions.
DISTILLED = "ours + distill 2 x 200 (no images)"
DISTILL_FRACTIONS = (0.5, 0.3, 0.1)
#: The rows the per-scene table shows, beside splat-transform's better mode.
PER_SCENE = (OURS, NOT_TUNED, PLACED, PLACED_NOT_TUNED)
IMAGE_FRACTIONS = (0.1,)
IMAGE_METHODS = (("ours + fine-tune", "hessian", "merge"), ("Hessian prune + fine-tune", "hessian", "prune"),
                 ("LightGaussian + fine-tune", "lightgaussian", "prune"))


def splat_transform() -> tuple[list[str] | None, str]:
    """The command that runs splat-transform (`benchmarks.splat_transform`: installed from npm into
    the cache on first use) and its version; (None, why) where node or npm is missing or the
    install fails."""
    try:
        return splat_transform_command(), PACKAGE
    except RuntimeError as exc:  # (Unavailable is one)
        return None, str(exc).strip().splitlines()[0]


def _decimate(command: list[str], cloud, mode: str, count: int, work: Path):
    """splat-transform's `--<mode> count` on `cloud`: the result and the seconds it took."""
    src, out = work / "in.ply", work / f"{mode}_{count}.ply"
    if not src.is_file():
        write_ply(cloud, src)
    t0 = time.perf_counter()
    done = subprocess.run(command + ["-q", "-w", "-g", "cpu", str(src), f"--{mode}", str(count), str(out)],
                          capture_output=True, text=True, timeout=1800)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"splat-transform --{mode} {count} failed: {done.stderr[-500:]}")
    return read_ply(out), seconds


def evaluate_scene(name: str, seed: int, fractions=FRACTIONS, *, methods=METHODS, images: bool = True,
                   image_methods=IMAGE_METHODS, distill: bool = True, splat: bool = True, say=print,
                   protocol=None, plateau: bool = True, options: dict | None = None) -> list[dict]:
    """Every method (`methods`) at every fraction on one (scene, seed) of the quick protocol (or
    `protocol`); one row each. `images`: also the rows with fine-tuning (`image_methods`, and the
    input fine-tuned as long); `distill`: also ours fine-tuned against the input's own renders (no
    images) at DISTILL_FRACTIONS; `splat`: splat-transform's rows; `options`: more keyword arguments
    of every `compact` call (`compact_options`)."""
    options = options or {}
    p = protocol or PROTOCOLS["quick"]
    run = prepare_scene(name, p, seed=seed, threads=1, say=say)
    k = p.train_stage
    train = load_nerf_synthetic(run.scene_dir, "train", resolution=p.resolutions[k])
    base = run.stage_cloud(k)
    base = base.replace(extra={DILATION_KEY: base.extra[DILATION_KEY]})  # the anti-aliasing size only
    evaluate = Evaluator(run)
    views = evaluate.views["1x"]

    def score(cloud) -> float:
        if DILATION_KEY not in cloud.extra:  # (a tool that drops it: the training cameras give it back)
            cloud = with_training_cameras(cloud, train.cameras)
        return image_scores(cloud, views, evaluate.background, no_reference=False, antialias=p.antialias).psnr

    tag = {"scene": name, "seed": seed, "n_input": len(base)}
    base_psnr = score(base)
    rows = [{**tag, "method": "input", "fraction": 1.0, "count": len(base), "psnr": base_psnr, "seconds": 0.0}]

    def add(method: str, fraction: float, cloud, seconds: float, **info) -> None:
        value = score(cloud)
        rows.append({**tag, "method": method, "fraction": fraction, "count": len(cloud), "psnr": value,
                     "drop": base_psnr - value, "seconds": seconds, **info})
        say(f"[{name} s{seed}] {method:26s} {fraction:5.0%} n={len(cloud):6d} PSNR {value:6.2f} "
            f"({value - base_psnr:+.2f}) {seconds:6.2f} s")

    for fraction in fractions:
        for m in methods:
            t0 = time.perf_counter()
            r = compact(base, keep=fraction, cameras=train.cameras if m.cameras else None, views=VIEWS, score=m.score,
                        removal=m.removal, seed=seed, prune=m.prune, distill=m.distill, rounds=m.rounds,
                        plateau=plateau, **options)
            add(m.label, fraction, r.cloud, time.perf_counter() - t0, report_psnr=r.psnr, unseen=r.unseen,
                rounds=[{k: v for k, v in x.items() if k != "checks"} for x in r.rounds])
    if distill:
        distilled_rows(base, p.iterations[k], seed, add, options)
    command, note = splat_transform() if splat else (None, None)
    if command is not None:
        with tempfile.TemporaryDirectory() as tmp:
            for fraction in fractions:
                for mode in ST_MODES:
                    cloud, seconds = _decimate(command, base, mode, max(1, round(fraction * len(base))), Path(tmp))
                    add(f"splat-transform --{mode}", fraction, cloud, seconds)
    elif splat:
        say(f"[{name} s{seed}] splat-transform skipped: {note}")
        rows.append({**tag, "method": "splat-transform", "skipped": note})
    if images:
        iterations = p.iterations[k]
        t0 = time.perf_counter()  # the input itself fine-tuned as long: what compaction is measured against too
        r = compact(base, keep=1.0, images=train, views=VIEWS, iterations=iterations, seed=seed, **options)
        add("input + fine-tune", 1.0, r.cloud, time.perf_counter() - t0, iterations=iterations)
        for fraction in IMAGE_FRACTIONS:
            for label, score_name, removal in image_methods:
                t0 = time.perf_counter()
                r = compact(base, keep=fraction, images=train, views=VIEWS, score=score_name, removal=removal,
                            iterations=iterations, seed=seed, **options)
                add(label, fraction, r.cloud, time.perf_counter() - t0, report_psnr=r.psnr,
                    iterations=iterations, rounds=[dict(x) for x in r.rounds])
    return rows


def distilled_rows(base, iterations: int, seed: int, add, options: dict | None = None) -> None:
    """`add` the rows of ours with `compact(distill=iterations, rounds=2, **options)` (views placed
    around the cloud) at DISTILL_FRACTIONS."""
    for fraction in DISTILL_FRACTIONS:
        t0 = time.perf_counter()
        r = compact(base, keep=fraction, distill=iterations, rounds=2, seed=seed, **(options or {}))
        add(DISTILLED, fraction, r.cloud, time.perf_counter() - t0, report_psnr=r.psnr, iterations=iterations)


#: The rows of a capture's table (`capture_rows`): label, score, removal, with the capture's photos,
#: with its cameras, distill. Ours with photos merges then fine-tunes; "PUP 3D-GS" prunes by the same
#: Hessian score then fine-tunes (as PUP 3D-GS); "LightGaussian" prunes by its global significance
#: then fine-tunes; every fine-tuning the same (`compact(images=, plateau=)`; `compact`'s default with
#: photos is the LightGaussian row from PHOTOS_PRUNE_FROM kept, ours below). The rows without photos
#: are `gvae compact` without --images: placed views (the default) or the capture's cameras, fine-tuned
#: against the input's own renders by default up to AUTO_DISTILL_MAX Gaussians, or as `--distill` says.
CAPTURE_METHODS = (("ours, photos", "hessian", "merge", True, False, "auto"),
                   ("PUP 3D-GS: Hessian prune + fine-tune", "hessian", "prune", True, False, "auto"),
                   ("LightGaussian prune + fine-tune", "lightgaussian", "prune", True, False, "auto"),
                   ("ours, no photos, placed views", "hessian", "merge", False, False, "auto"),
                   ("ours, no photos, capture cameras", "hessian", "merge", False, True, "auto"),
                   ("ours, no photos, placed views, --distill 1000", "hessian", "merge", False, False, 1000),
                   ("ours, no photos, placed views, --distill 0", "hessian", "merge", False, False, 0),
                   ("LightGaussian prune, no photos, placed views", "lightgaussian", "prune", False, False, "auto"),
                   ("LightGaussian prune, no photos, placed views, --distill 0", "lightgaussian", "prune", False, False,
                    0))
INPUT_TUNED = "input + fine-tune as long"


@dataclass
class _CaptureBench:
    """A capture's compaction table as it is made: the trained cloud and the capture's cameras, its
    training photos and held-out ones at the height the cloud was trained at, the training photos
    set aside (every row is scored on them too), the rows so far and where they are said."""

    base: object
    cameras: list
    height: int
    photos: object
    test: object
    judge: object
    background: tuple
    tag: dict
    say: object
    rows: list = dataclasses.field(default_factory=list)
    base_psnr: float = float("nan")
    base_auto: float = float("nan")

    def score(self, cloud) -> tuple[float, float, float, float]:
        """Held-out PSNR and SSIM drawn as the cloud was trained (classic: what the trainer's log and
        other 3DGS viewers show), the PSNR of the default render (auto: matched, its size), and the
        classic PSNR on the set-aside training photos (what chooses)."""
        from ..rendering import RenderSettings  # noqa: PLC0415
        from ..train import evaluate_views  # noqa: PLC0415

        if DILATION_KEY not in cloud.extra:
            cloud = with_training_cameras(cloud, self.cameras)
        tc, bg, deg = cloud.to_torch(), self.background, cloud.sh_degree
        classic = evaluate_views(tc, self.test, bg, deg, None, RenderSettings(antialias="classic"))
        auto = evaluate_views(tc, self.test, bg, deg, None, RenderSettings(), with_ssim=False)[0]
        val = evaluate_views(tc, self.judge, bg, deg, None, RenderSettings(antialias="classic"), with_ssim=False)[0]
        return (*classic, auto, val)

    def add(self, method: str, fraction: float, cloud, seconds: float, cpu: float, peak: float, **info) -> dict:
        value, ssim_value, auto, val = self.score(cloud)
        row = {**self.tag, "method": method, "fraction": fraction, "count": len(cloud), "psnr": value,
               "ssim": ssim_value, "psnr_auto": auto, "val_psnr": val, "drop": self.base_psnr - value,
               "drop_auto": self.base_auto - auto, "seconds": seconds, "cpu_seconds": cpu, "peak_gib": peak,
               "load": _loadavg(), **info}
        self.rows.append(row)
        self.say(f"  {method:40s} {fraction:4.0%} n={len(cloud):7,d} held-out PSNR {value:6.2f} "
                 f"({value - self.base_psnr:+.2f}; auto {auto - self.base_auto:+.2f}; set-aside photos {val:.2f}) "
                 f"SSIM {ssim_value:.4f} {seconds:6.1f} s (CPU {cpu:6.1f} s) {peak:.2f} GiB"
                 + (f"; {info['note']}" if info.get("note") else ""))
        return row


def _capture_bench(base_path, capture, test_every: int, say) -> _CaptureBench:
    """The capture's cloud, cameras and photos read, and the input's row."""
    from ..capture import load_cameras, load_capture_images, read_capture  # noqa: PLC0415
    from ..compaction import fine_tune_height, set_aside  # noqa: PLC0415

    base = read_ply(base_path)
    cameras = load_cameras(capture, test_every)
    height = fine_tune_height(base, cameras)
    photos = load_capture_images(capture, height, test_every)
    test = read_capture(capture).held_out(test_every).load("test", height)
    judge = set_aside(photos)[1]  # (what the fine-tuning with photos is judged on: every row scored on them too)
    background = tuple(base.background) if base.background is not None else (1.0, 1.0, 1.0)
    tag = {"capture": str(capture), "base": str(base_path), "n_input": len(base), "height": height,
           "test_views": len(test), "train_views": len(photos)}
    bench = _CaptureBench(base, cameras, height, photos, test, judge, background, tag, say)
    base_psnr, base_ssim, base_auto, base_val = bench.score(base)
    bench.base_psnr, bench.base_auto = base_psnr, base_auto
    bench.rows.append({**tag, "method": "input", "fraction": 1.0, "count": len(base), "psnr": base_psnr,
                       "ssim": base_ssim, "psnr_auto": base_auto, "val_psnr": base_val})
    say(f"{capture}: {len(base):,} Gaussians, {len(photos)} training photos and {len(test)} held out at {height} px; "
        f"held-out PSNR {base_psnr:.2f} dB (auto render {base_auto:.2f}), SSIM {base_ssim:.4f}; set-aside photos "
        f"{base_val:.2f} dB; load {_loadavg()}")
    return bench


def _timed(fn, *args, **kwargs):
    """fn(*args, **kwargs), its wall and process CPU seconds and its peak RSS (GiB)."""
    reset_peak_rss()
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0, time.process_time() - c0, peak_rss_mb() / 1024


def _rounds_info(r) -> dict:
    """What a compaction's fine-tuning rounds did, for its row."""
    its = sum(x["iterations"] for x in r.rounds)
    return {"iterations": its, "rounds": [dict(x) for x in r.rounds], "aside_psnr": r.rounds[-1]["psnr_after"],
            "note": "iterations " + " + ".join(f"{x['iterations']} (best {x['best_at']})" for x in r.rounds)
            + f", set-aside PSNR {r.rounds[0]['psnr_before']:.2f} -> {r.rounds[-1]['psnr_after']:.2f}"}


def _capture_compactions(bench: _CaptureBench, fraction: float, methods, *, iterations, rounds, plateau: bool,
                         seed: int, views: int, options: dict) -> int | None:
    """Every row of `methods` at `fraction`; returns the fine-tuning iterations of the first row that
    fine-tuned (None: none did)."""
    def checks(fraction: float, message: str) -> None:  # the estimate and every check of the set-aside photos
        if "s an iteration" in message or "set-aside PSNR" in message:
            bench.say(f"    {message} [{_loadavg()}]")

    tuned_iterations = None
    for label, score_name, removal, with_photos, with_cameras, distill, *drop in methods:
        r, seconds, cpu, peak = _timed(
            compact, bench.base, keep=fraction, images=bench.photos if with_photos else None, score=score_name,
            removal=removal, cameras=bench.cameras if with_cameras else None, iterations=iterations,
            distill=distill, rounds=rounds if with_photos else None, plateau=plateau, seed=seed, progress=checks,
            views=views, prune=drop[0] if drop else PRUNE_FRACTION, **options)
        info = _rounds_info(r) if r.rounds else {}
        if r.rounds and tuned_iterations is None:
            tuned_iterations = info["iterations"]
        bench.add(label, fraction, r.cloud, seconds, cpu, peak, **info)
    return tuned_iterations


def _input_tuned(bench: _CaptureBench, fraction: float, iterations: int, plateau: bool, seed: int,
                 tuning: finetune.TuningOptions) -> None:
    """The row of the uncompacted input fine-tuned for `iterations` on the photos the compactions had."""
    from ..compaction import set_aside  # noqa: PLC0415
    from ..rendering import RenderSettings  # noqa: PLC0415
    from ..train import fine_tune  # noqa: PLC0415

    fit, aside = set_aside(bench.photos) if plateau else (bench.photos, None)
    config = finetune.tuning_config(bench.base, RenderSettings(), seed, tuning.train_overrides)
    out, seconds, cpu, peak = _timed(fine_tune, bench.base, fit, iterations, config=config, seed=seed,
                                     average=tuning.average)
    bench.add(INPUT_TUNED, fraction, out, seconds, cpu, peak, iterations=iterations,
              note=f"{iterations} iterations, as ours with photos at {fraction:.0%}")


def capture_rows(base_path, capture, test_every: int = 8, fractions=(0.5, 0.3, 0.1), *, methods=CAPTURE_METHODS,
                 splat: bool = True, input_tuned: bool = True, iterations: int | None = None, rounds: int | None = None,
                 plateau: bool = True, seed: int = 0, views: int = VIEWS, options: dict | None = None,
                 say=print) -> list[dict]:
    """A trained capture's cloud (`base_path`, the PLY `gvae train` wrote) compacted to each fraction
    by every row of `methods` and splat-transform's decimation; each scored on the capture's
    held-out photos (every `test_every`-th by name, at the height the cloud was trained at:
    `compaction.fine_tune_height`), PSNR and SSIM, with seconds (wall and process CPU) and peak
    RSS. The rows with photos fine-tune on the capture's training photos (`compact(images=...)`:
    every SET_ASIDE_EVERY-th set aside to judge, `plateau`); `input_tuned`: the uncompacted cloud
    fine-tuned on the same photos for as many iterations as ours with photos ran at each fraction,
    ending on the average of its iterates as they do (the same cost: what the compaction is measured
    against beside the input itself). `options`: more keyword arguments of every `compact` call
    (`compact_options`)."""
    options = options or {}
    bench = _capture_bench(base_path, capture, test_every, say)
    for fraction in fractions:
        tuned_iterations = _capture_compactions(bench, fraction, methods, iterations=iterations, rounds=rounds,
                                                plateau=plateau, seed=seed, views=views, options=options)
        if input_tuned and tuned_iterations:
            _input_tuned(bench, fraction, tuned_iterations, plateau, seed,
                         options.get("tuning_options") or finetune.TuningOptions())
    command, note = splat_transform() if splat else (None, None)
    if command is not None:
        with tempfile.TemporaryDirectory() as tmp:
            for fraction in fractions:
                cloud, seconds = _decimate(command, bench.base, "decimate", max(1, round(fraction * len(bench.base))),
                                           Path(tmp))
                bench.add("splat-transform --decimate", fraction, cloud, seconds, float("nan"), float("nan"),
                          note="its own process: CPU and memory not measured here")
    elif splat:
        say(f"  splat-transform skipped: {note}")
    return bench.rows


def capture_table(rows: list[dict]) -> list[str]:
    """Markdown: per method and fraction, held-out PSNR and its change against the input, SSIM,
    fine-tuning iterations (and where the best state was), the PSNR of the training photos set
    aside (what chooses; rows made before it was measured for every row: the fine-tuning's own
    figure, photos rows only), seconds (CPU), peak memory."""
    lines = ["| method | kept | Gaussians | held-out PSNR | vs input | SSIM | iterations (best at) | set-aside photos "
             "PSNR | seconds (CPU) | peak RSS | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "psnr" not in r:
            continue
        cpu = f" ({r['cpu_seconds']:.0f})" if np.isfinite(r.get("cpu_seconds", float("nan"))) else ""
        peak = f"{r['peak_gib']:.2f} GiB" if np.isfinite(r.get("peak_gib", float("nan"))) else "-"
        its, aside = r.get("iterations", "-"), "-"
        if r.get("rounds"):
            its = " + ".join(f"{x['iterations']} ({x['best_at']})" for x in r["rounds"])
            if "training images" in r["rounds"][0].get("judged_on", ""):
                aside = f"{r['aside_psnr']:.2f}"
        if np.isfinite(r.get("val_psnr", float("nan"))):
            aside = f"{r['val_psnr']:.2f}"
        lines.append(f"| {r['method']} | {r['fraction']:.0%} | {r['count']:,} | {r['psnr']:.2f} | "
                     f"{-r.get('drop', 0.0):+.2f} | {r['ssim']:.4f} | {its} | {aside} | "
                     f"{r.get('seconds', 0.0):.0f}{cpu} | {peak} | {r.get('load', '-')} |")
    return lines


def _loadavg() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _mean_ci(values) -> str:
    v = np.asarray(values, np.float64)
    if len(v) == 0:
        return "-"
    if len(v) == 1:
        return f"{v[0]:+.2f}"
    half = 1.96 * v.std(ddof=1) / np.sqrt(len(v))
    return f"{v.mean():+.2f} ± {half:.2f}"


def tables(rows: list[dict]) -> list[str]:
    """Markdown: mean change of PSNR against the input (± 95% interval over scenes x seeds) per
    method and fraction; then per scene, the change at 50/30/10% of PER_SCENE and splat-transform's
    better mode."""
    scored = [r for r in rows if "drop" in r]
    methods = list(dict.fromkeys(r["method"] for r in scored))
    fractions = sorted({r["fraction"] for r in scored}, reverse=True)
    lines = ["| method | " + " | ".join(f"{f:.0%} kept" for f in fractions) + " |",
             "|---|" + "---|" * len(fractions)]
    for m in methods:
        cells = [_mean_ci([-r["drop"] for r in scored if r["method"] == m and r["fraction"] == f]) for f in fractions]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    shown = [f for f in (0.5, 0.3, 0.1) if f in fractions]
    names = " / ".join(PER_SCENE) + " / best splat-transform"
    lines += ["", "| scene | seed | input PSNR | " + " | ".join(f"{f:.0%}: {names}" for f in shown) + " |",
              "|---|---|---|" + "---|" * len(shown)]
    pairs = sorted({(r["scene"], r["seed"]) for r in scored})
    for scene, seed in pairs:
        mine = {(r["method"], r["fraction"]): r for r in scored if r["scene"] == scene and r["seed"] == seed}
        base = next(r["psnr"] for r in rows if r["scene"] == scene and r["seed"] == seed and r["method"] == "input")
        cells = []
        for f in shown:
            change = {m: -r["drop"] for (m, fr), r in mine.items() if fr == f}
            st = [change[f"splat-transform --{m}"] for m in ST_MODES if f"splat-transform --{m}" in change]
            values = [change.get(m) for m in PER_SCENE] + [max(st) if st else None]
            cells.append(" / ".join("-" if v is None else f"{v:+.2f}" for v in values))
        lines.append(f"| {scene} | {seed} | {base:.2f} | " + " | ".join(cells) + " |")
    return lines


def plot(rows: list[dict], out: Path) -> Path:
    """PSNR change against the kept fraction, one line per method (mean over scenes x seeds)."""
    import matplotlib  # noqa: PLC0415 - drawn without a screen

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    scored = [r for r in rows if "drop" in r]
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8))
    methods = list(dict.fromkeys(r["method"] for r in scored))
    colours = dict(zip(methods, plt.get_cmap("tab20").colors[::2] + plt.get_cmap("tab20").colors[1::2]))
    for ax, low in zip(axes, (-16.0, -4.5)):
        for m in methods:
            fr = sorted({r["fraction"] for r in scored if r["method"] == m})
            ys = [np.mean([-r["drop"] for r in scored if r["method"] == m and r["fraction"] == f]) for f in fr]
            style = "-o" if m == "ours" else "--s" if m.startswith("splat") else "^" if "+ fine-tune" in m else ":."
            ax.plot(fr, ys, style, label=m, color=colours[m], lw=2.2 if m == "ours" else 1.2,
                    ms=8 if "fine-tune" in m else 5)
        ax.set_xscale("log")
        ax.set_xlabel("fraction of Gaussians kept")
        ax.set_ylabel("PSNR change at 1x against the input (dB)")
        ax.set_ylim(low, 1.8)
        ax.grid(True, alpha=0.3)
    axes[0].set_title("every method")
    axes[1].set_title("close up")
    fig.legend(*axes[1].get_legend_handles_labels(), fontsize=8, loc="center left", bbox_to_anchor=(0.81, 0.5))
    fig.tight_layout(rect=(0, 0, 0.8, 1))
    path = out / "compact_psnr_vs_fraction.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def views_coverage(n: int = 6000, resolution: int = 256, seeds=(0, 1), ring: int = 64) -> list[dict]:
    """Placed views (`capture.placed_views`, 4 to score) on the shapes that fool a placement
    (`examples.shape_cloud`): what they are taken for, where the views stand, and the share of the
    Gaussians that `ring` views all around from outside see that the scoring views see (and, for a
    scene, the scoring and extra views together), at `resolution` px; one row per shape and seed."""
    from ..capture import outside_views, placed_views  # noqa: PLC0415
    from ..compaction import pixel_hits  # noqa: PLC0415
    from ..examples import SHAPES, shape_cloud  # noqa: PLC0415

    print(f"\n| shape | seed | taken for | views' distance from the centre (half-extents) | seen by {ring} views "
          f"outside | of those, seen by the 4 scoring views | with the extra views | placing (s) |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for kind in SHAPES:
        for seed in seeds:
            cloud = shape_cloud(kind, n, seed=seed)
            t0 = time.perf_counter()
            placed = placed_views(cloud, 4, resolution)
            seconds = time.perf_counter() - t0
            center, half = cloud.normalization()
            outside = pixel_hits(cloud, outside_views(cloud, ring, resolution)) > 0
            seen = pixel_hits(cloud, placed.scoring) > 0
            both = seen | (pixel_hits(cloud, placed.extra) > 0) if placed.extra else seen
            dist = [float(np.linalg.norm(c.center - center)) / half for c in placed.scoring]
            row = {"shape": kind, "seed": seed, "scene": placed.surround is not None, "outside": float(outside.mean()),
                   "scoring": float((seen & outside).sum() / max(outside.sum(), 1)),
                   "with_extra": float((both & outside).sum() / max(outside.sum(), 1)), "seconds": seconds}
            rows.append(row)
            print(f"| {kind} | {seed} | {'scene, from inside' if row['scene'] else 'object'} | "
                  f"{min(dist):.2f}-{max(dist):.2f} | {row['outside']:.1%} | {row['scoring']:.2%} | "
                  f"{row['with_extra']:.2%} | {seconds:.2f} |", flush=True)
    return rows


def _speed(counts, fractions=(0.5, 0.1), repeats: int = 3) -> None:
    """Seconds and peak memory of `compact` without images on example_cloud(N) (SH 3, default
    views), each size in a fresh process; `uptime` beside."""
    print("\n| Gaussians | kept | seconds (median) | parts (median s) | peak RSS | estimate | PSNR vs input | load |")
    print("|---|---|---|---|---|---|---|---|")
    for n in counts:
        for fraction in fractions:
            code = (f"import json, sys; from gvae_core.benchmarks.compact import _speed_child; "
                    f"print(json.dumps(_speed_child({n}, {fraction}, {repeats})))")
            done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                  env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
            if done.returncode != 0:
                print(f"| {n:,} | {fraction:.0%} | failed: {done.stderr.strip()[-200:]} |")
                continue
            r = json.loads(done.stdout.strip().splitlines()[-1])
            parts = ", ".join(f"{k} {v:.2f}" for k, v in r["parts"].items())
            print(f"| {n:,} | {fraction:.0%} | {r['seconds']:.2f} | {parts} | {r['peak_gib']:.2f} GiB | "
                  f"{r['estimate_gib']:.2f} GiB | {r['psnr']:.2f} dB | {r['load']} |", flush=True)


def _speed_child(n: int, fraction: float, repeats: int) -> dict:
    cloud = example_cloud(n, seed=1)
    times, parts = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = compact(cloud, keep=fraction)
        times.append(time.perf_counter() - t0)
        parts.append(r.timings)
    med = {k: statistics.median(p[k] for p in parts) for k in parts[0] if k != "total"}
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"seconds": statistics.median(times), "parts": med, "peak_gib": peak / 2 ** 30,
            "estimate_gib": estimate_compact_memory(n, 3) / 2 ** 30, "psnr": r.psnr,
            "load": " ".join(f"{x:.2f}" for x in os.getloadavg())}


def run(args) -> None:
    quick = bool(getattr(args, "quick", False))
    split = os.environ.get("GVAE_COMPACT_SPLIT", "validation" if quick else "test")
    seeds = [int(s) for s in os.environ.get("GVAE_COMPACT_SEEDS", "0" if quick else "0,1,2").split(",")]
    scenes = SPLITS[split][:1] if quick else SPLITS[split]
    out = Path(os.environ.get("GVAE_COMPACT_OUT", "reports/compact"))
    print(f"compaction on the {split} scenes {', '.join(scenes)}, seeds {seeds} (quick protocol, 100 px runs); "
          f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    rows = []
    t0 = time.perf_counter()
    for name in scenes:
        for seed in seeds:
            rows += evaluate_scene(name, seed, images=not quick, say=lambda msg: print(msg, flush=True))
    print(f"\n{time.perf_counter() - t0:.0f} s in all; PSNR change at 1x against the input (mean ± 95% interval over "
          f"{len(scenes)} scenes x {len(seeds)} seeds):\n")
    print("\n".join(tables(rows)))
    out.mkdir(parents=True, exist_ok=True)
    (out / f"results_{split}.json").write_text(json.dumps(rows, indent=1))
    print(f"\nplot: {plot(rows, out)}; rows: {out / f'results_{split}.json'}")
    if os.environ.get("GVAE_COMPACT_VIEWS", "1") != "0":
        views_coverage(2000, 128, seeds=(0,)) if quick else views_coverage()
    if os.environ.get("GVAE_COMPACT_SPEED", "1") != "0":
        _speed((100_000,) if quick else (100_000, 1_000_000))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.compact",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", choices=list(SPLITS), default="test", help="scenes (default: %(default)s)")
    parser.add_argument("--scenes", nargs="*", default=None,
                        help="only these scenes, none: no scene rows (default: the split's)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="3DGS seeds (default: 0 1 2)")
    parser.add_argument("--fractions", nargs="+", type=float, default=list(FRACTIONS),
                        help=f"kept fractions (default: {' '.join(map(str, FRACTIONS))})")
    parser.add_argument("--methods", type=int, default=len(METHODS),
                        help=f"the first K of the compact rows ({', '.join(m.label for m in METHODS)}) "
                        "(default: all)")
    parser.add_argument("--only", nargs="+", type=int, default=None, metavar="K",
                        help="instead of --methods: these compact rows, by number from 0 (default: none)")
    parser.add_argument("--distill", default=None, metavar="ITERATIONS",
                        help="fine-tuning of the fine-tuned rows (ours, placed views): 'auto' or iterations a round "
                        "(default: auto)")
    parser.add_argument("--rounds", type=int, default=None, help="their rounds (default: one)")
    parser.add_argument("--prune", type=float, default=None,
                        help=f"fraction dropped before merging, in the merging rows (default: {PRUNE_FRACTION:g})")
    parser.add_argument("--colour-weight", type=float, default=None,
                        help=f"the merge cost's colour weight (default: {moments.COLOUR_WEIGHT:g})")
    parser.add_argument("--images", action="store_true", help="also the rows fine-tuned with the training images")
    parser.add_argument("--distilled", action="store_true", help=f"also the rows {DISTILLED!r}")
    parser.add_argument("--no-splat-transform", action="store_true", help="without splat-transform's rows")
    parser.add_argument("--views-table", action="store_true", help="also the placed views' table")
    parser.add_argument("--speed", nargs="*", type=int, default=None, metavar="N",
                        help="also the speed of compact on example_cloud(N) (default: none)")
    parser.add_argument("--speed-fractions", nargs="+", type=float, default=[0.5, 0.1],
                        help="kept fractions of the speed rows (default: 0.5 0.1)")
    parser.add_argument("--repeats", type=int, default=3, help="speed repeats (default: %(default)s)")
    parser.add_argument("--capture", type=Path, default=None, metavar="CAPTURE",
                        help="instead of the scenes: a real capture (with --base, the cloud gvae train made of it), "
                        "scored on its held-out photos (capture_rows)")
    parser.add_argument("--base", type=Path, default=None, metavar="PLY", help="the capture's trained cloud")
    parser.add_argument("--test-every", type=int, default=8, help="the capture's held-out photos (default: 8)")
    parser.add_argument("--capture-methods", nargs="*", type=int, default=None, metavar="K",
                        help="rows of the capture's table, by number (0-8: " +
                        "; ".join(m[0] for m in CAPTURE_METHODS) + "; default: all)")
    parser.add_argument("--capture-row", nargs=3, action="append", default=[], metavar=("SCORE", "REMOVAL", "PRUNE"),
                        help="with --capture: also a row with photos of this score, removal and fraction dropped "
                        "before merging (repeatable)")
    parser.add_argument("--average", type=float, default=None, metavar="DECAY",
                        help="with --capture: the decay of the running average of the iterates the photos' "
                        "fine-tuning ends on (default: compaction.finetune.AVERAGE; 0: the last iterate)")
    parser.add_argument("--distill-average", type=float, default=None, metavar="DECAY",
                        help="the same for the fine-tuning against the input's own renders (default: "
                        "compaction.finetune.DISTILL_AVERAGE)")
    parser.add_argument("--fine-tune-seed", type=int, default=0,
                        help="with --capture: the seed of the compactions' fine-tuning (default: %(default)s)")
    parser.add_argument("--views", type=int, default=VIEWS,
                        help="with --capture: the cameras that score (default: %(default)s; 0: all of them)")
    parser.add_argument("--iterations", type=int, default=None, help="with --capture: the most fine-tuning iterations "
                        "a round (default: compact's)")
    parser.add_argument("--tuning", nargs="+", default=[], metavar="FIELD=VALUE",
                        help="changes to the trainer's configuration for compaction's fine-tuning "
                        "(compaction.finetune.TuningOptions.train_overrides), e.g. position_lr_init=1.6e-5")
    parser.add_argument("--distill-target", choices=("tuned", "auto"), default=None,
                        help="how the input's own renders are drawn (compaction.finetune.DISTILL_TARGET)")
    parser.add_argument("--no-plateau", dest="plateau", action="store_false",
                        help="with --capture: no images set aside, every iteration run")
    parser.add_argument("--no-input-tuned", dest="input_tuned", action="store_false",
                        help=f"with --capture: without the row {INPUT_TUNED!r}")
    parser.add_argument("--out", type=Path, default=None, help="folder for results_SPLIT.json (default: none)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest size (experiment.SMOKE: 64 px scenes), to show that it runs")
    return parser


def compact_options(args) -> dict:
    """The keyword arguments of `compact` the options ask for beside each row's own: the merge
    cost's colour weight and what the fine-tuning changes (`finetune.TuningOptions`)."""
    options = {}
    if args.colour_weight is not None:
        options["colour_weight"] = args.colour_weight
    changes = {}
    if args.tuning:
        changes["train_overrides"] = {k: float(v) for k, v in (item.split("=", 1) for item in args.tuning)}
    if args.average is not None:
        changes["average"] = args.average or None
    if args.distill_average is not None:
        changes["distill_average"] = args.distill_average or None
    if args.distill_target:
        changes["distill_target"] = args.distill_target
    if changes:
        options["tuning_options"] = finetune.TuningOptions(**changes)
    return options


def _scene_methods(args) -> list[Method]:
    methods = list(METHODS[:args.methods]) if args.only is None else [METHODS[k] for k in args.only]
    if args.prune is not None:
        methods = [dataclasses.replace(m, prune=args.prune) if m.removal == "merge" and m.prune else m for m in methods]
    if args.distill is not None or args.rounds is not None:
        distill = args.distill if args.distill in (None, "auto") else int(args.distill)
        methods = [dataclasses.replace(m, distill=m.distill if distill is None else distill, rounds=args.rounds)
                   if m.label in (OURS, PLACED) else m for m in methods]
    return methods


def _run_capture(args, options: dict) -> None:
    methods = [CAPTURE_METHODS[k] for k in (range(len(CAPTURE_METHODS)) if args.capture_methods is None
                                             else args.capture_methods)]
    methods += [(f"{score} {removal}, {float(q):g} dropped first + fine-tune", score, removal, True, False, "auto",
                 float(q)) for score, removal, q in args.capture_row]
    print(f"compaction of {args.base} (capture {args.capture}); load {_loadavg()}", flush=True)
    rows = capture_rows(args.base, args.capture, args.test_every, tuple(args.fractions), methods=methods,
                        splat=not args.no_splat_transform, input_tuned=args.input_tuned,
                        iterations=args.iterations, rounds=args.rounds, plateau=args.plateau,
                        views=args.views, seed=args.fine_tune_seed, options=options,
                        say=lambda msg: print(msg, flush=True))
    print("\n".join(["", *capture_table(rows)]))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"results_{args.capture.name}.json").write_text(json.dumps(rows, indent=1))


def _run_scenes(args, options: dict) -> None:
    methods = _scene_methods(args)
    protocol = SMOKE if args.smoke else PROTOCOLS["quick"]
    scenes = SPLITS[args.split] if args.scenes is None else args.scenes
    print(f"compaction, {protocol.name} protocol, scenes {', '.join(scenes)}, seeds {args.seeds}; load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    rows = []
    for name in scenes:
        for seed in args.seeds:
            rows += evaluate_scene(name, seed, tuple(args.fractions), methods=tuple(methods), images=args.images,
                                   distill=args.distilled, splat=not args.no_splat_transform, protocol=protocol,
                                   plateau=args.plateau, options=options,
                                   say=lambda msg: print(msg, flush=True))
    if rows:
        print("\n".join(["", *tables(rows)]))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"results_{args.split}.json").write_text(json.dumps(rows, indent=1))
    if args.views_table:
        views_coverage(2000, 128, seeds=(0,)) if args.smoke else views_coverage()
    if args.speed:
        _speed(args.speed, tuple(args.speed_fractions), args.repeats)


def main(argv=None) -> int:
    """`python -m gvae_core.benchmarks.compact`: the benchmark's parts, with options."""
    parser = _parser()
    args = parser.parse_args(argv)
    options = compact_options(args)
    if args.capture is not None:
        if args.base is None:
            parser.error("--capture needs --base")
        _run_capture(args, options)
    else:
        _run_scenes(args, options)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
