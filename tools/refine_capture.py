"""Refine a cloud trained on a real capture and score it on the capture's held-out photos at 2x
(docs/benchmarks/refine-images.md, "A real capture: the plush"): every row beside each other.

The cloud is the last stage of a `gvae train CAPTURE --test-every N` run (`--run`); its training
images are the capture's training split at the run's last resolution H; the held-out photos are
area-averaged from the stored ones to 2H (and H). Rows (`--rows`, each optional):
- unrefined: the cloud as it is (its best render: the anti-aliasing it stores, matched);
- detail: `refine` without images (the detail model);
- images: `refine` with the training images (the default fit, or `--fit key=value ...`);
- more: the same steps of plain training at H (`train.fine_tune`, as `gvae train RUN --more N`),
  the step count of the `images` row's fit (or `--more-steps`);
- oracle: the same fit to the real 2H photos of the training views (`fit_octaves(images_scale=2)`);
- real: a cloud trained by the project on the 2H photos (`--real-run`, a `gvae train` run at 2H);
- trace: the `images` fit run with the held-out photos scored at 2H at every check of the fit (how
  the fit's own judge and the photos it never sees agree; nothing kept).
PSNR and SSIM on every held-out photo at 2H (and at H), Gaussians, seconds; a picture of one
held-out view with zoomed crops (`--picture`).

A benchmark scene works the same way (`--scene chair`): its run of the experiment's quick protocol
to the training resolution (`gvae_core.experiment`, trained and cached on first use), its own test
views as the held-out ones.

Usage: python tools/refine_capture.py (--run RUNS/d4-sfm | --scene chair) --out RESULT.json
        [--rows unrefined detail images more oracle real] [--real-run RUNS/d2-sfm]
        [--fit lr=0.3 epochs=4 ...] [--picture OUT.png] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gvae_core.atomic import atomic_write_text
from gvae_core.capture import read_capture
from gvae_core.metrics.image import image_scores, render_views
from gvae_core.octaves import with_octaves
from gvae_core.ply import read_ply
from gvae_core.refinement import refine
from gvae_core.superres import SuperResConfig, fit_octaves
from gvae_core.train import RunFolder, TrainConfig, fine_tune

ROWS = ("unrefined", "detail", "images", "more", "oracle", "real", "trace")


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    if text in ("None", "none"):
        return None
    if text in ("True", "False"):
        return text == "True"
    return tuple(text.split(",")) if "," in text else text


def _scores(cloud, views_by_height: dict) -> dict:
    out = {}
    for h, views in views_by_height.items():
        s = image_scores(cloud, views, no_reference=False)
        out[str(h)] = {"psnr": round(s.psnr, 4), "ssim": round(s.ssim, 5)}
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--run", type=Path, help="a finished `gvae train --test-every` run")
    where.add_argument("--scene", help="a benchmark scene, trained with the quick protocol to its training resolution")
    p.add_argument("--seed", type=int, default=0, help="--scene: the 3DGS seed of its run")
    p.add_argument("--cloud", type=Path, help="the cloud to refine instead of the run's last stage (the same run's "
                   "stage trained further: `gvae train RUN --more N`)")
    p.add_argument("--out", type=Path, required=True, help="JSON of the rows (rewritten after each)")
    p.add_argument("--rows", nargs="+", default=list(ROWS[:5]), choices=ROWS)
    p.add_argument("--real-run", type=Path, help="a run trained at 2H for the `real` row")
    p.add_argument("--fit", nargs="*", default=[], metavar="KEY=VALUE", help="SuperResConfig fields")
    p.add_argument("--more-steps", type=int, help="iterations of the `more` row (default: the fit's)")
    p.add_argument("--picture", type=Path, help="a PNG of a held-out view with zoomed crops")
    p.add_argument("--threads", type=int, default=2)
    return p


@dataclass
class _Study:
    """One run's rows as they are made: its cloud, capture and trainer's configuration, the training
    images at H, the held-out photos at 2H and H, the fit's configuration, the JSON document (written
    to `out` after every row) and every row's cloud (for the picture)."""

    cloud: object
    capture: object
    config: TrainConfig
    height: int
    train: object
    test: dict
    fit: SuperResConfig
    doc: dict
    out: Path
    clouds: dict = field(default_factory=dict)

    def record(self, name: str, result, seconds: float, **info) -> None:
        self.clouds[name] = result
        self.doc["rows"][name] = {"scores": _scores(result, self.test), "gaussians": len(result),
                                  "seconds": round(seconds, 1), **info}
        r, h = self.doc["rows"][name], self.height
        print(f"{name:>10}: {r['scores'][str(2 * h)]['psnr']:.3f} dB / {r['scores'][str(2 * h)]['ssim']:.4f}"
              f" at 2x, {r['scores'][str(h)]['psnr']:.3f} dB at 1x, {r['gaussians']} Gaussians, {seconds:.0f} s"
              + (f"  {info}" if info else ""), flush=True)
        self.save()

    def save(self) -> None:
        atomic_write_text(self.out, json.dumps(self.doc, indent=2))

    def start(self) -> dict | None:
        """Where the fit starts: the detail model's changes, unless it starts from zero."""
        return _detail_start(self.cloud) if self.fit.start == "detail" else None


def _study(args) -> _Study:
    run = RunFolder(args.run).finished()
    config, stage = run.config, run.stages_done - 1
    height = config.resolutions[stage]
    capture = read_capture(run.data, config.test_every)
    cloud = read_ply(args.cloud or args.run / f"stage_{stage}.ply")
    train = capture.load("train", height)
    test = {2 * height: capture.load("test", 2 * height), height: capture.load("test", height)}
    fit = SuperResConfig(**{k: _value(v) for k, v in (kv.split("=", 1) for kv in args.fit)})
    print(f"{capture.summary()}\ncloud {len(cloud)} Gaussians at {height} px; held-out photos at {2 * height} and "
          f"{height} px; fit {fit}", flush=True)
    doc = {"run": str(args.run), "cloud": str(args.cloud or ""), "height": height, "gaussians": len(cloud),
           "fit": repr(fit), "rows": {}}
    return _Study(cloud, capture, config, height, train, test, fit, doc, args.out)


def _images_row(study: _Study, t0: float) -> int:
    """The `images` row; returns the fit's steps times the views a step sums."""
    r = refine(study.cloud, images=study.train, fit=study.fit)
    study.record("images", r.cloud, time.perf_counter() - t0, notes=r.notes, steps=r.fit.steps_run,
                 kept=r.fit.kept, holdout=[r.fit.holdout_input, r.fit.holdout_start, r.fit.holdout_fit],
                 own=[r.fit.psnr_before, r.fit.psnr_after], checks=[[s, round(v, 3)] for s, v in r.fit.checks],
                 fit_seconds=round(r.fit.timings.get("fit", 0.0), 1))
    return r.fit.steps_run * study.fit.views_per_step


def _oracle_row(study: _Study, t0: float) -> None:
    cloud = study.cloud
    real = study.capture.load("train", 2 * study.height)
    start = study.start()
    f = fit_octaves(cloud, real, 1, study.fit, start=start, background=cloud.background or (1.0, 1.0, 1.0),
                    images_scale=2)
    chosen = f.changes if f.kept in ("fit", "begin") else {"start": start or {}, "input": {}}[f.kept]
    study.record("oracle", with_octaves(cloud, chosen, limit=1.0), time.perf_counter() - t0, kept=f.kept,
                 steps=f.steps_run, holdout=[f.holdout_input, f.holdout_start, f.holdout_fit],
                 checks=[[s, round(v, 3)] for s, v in f.checks])


def _trace_row(study: _Study, t0: float) -> None:
    cloud = study.cloud
    trace = []

    def look(step: int, now) -> None:
        s = image_scores(now, study.test[2 * study.height], cloud.background, no_reference=False)
        trace.append([step, round(s.psnr, 4), round(s.ssim, 5)])
        print(f"  step {step}: held-out photos at 2x {s.psnr:.3f} dB / {s.ssim:.4f}", flush=True)

    f = fit_octaves(cloud, study.train, 1, study.fit, start=study.start(),
                    background=cloud.background or (1.0, 1.0, 1.0), on_check=look)
    study.doc["rows"]["trace"] = {"checks": [[s, round(v, 3)] for s, v in f.checks], "photos_2x": trace,
                                  "kept": f.kept, "holdout": [f.holdout_input, f.holdout_start, f.holdout_fit],
                                  "seconds": round(time.perf_counter() - t0, 1)}
    study.save()


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.scene is not None:
        from gvae_core.experiment import PROTOCOLS, prepare_scene  # noqa: PLC0415

        args.run = prepare_scene(args.scene, PROTOCOLS["quick"].fits(), seed=args.seed, threads=args.threads).run_dir
    study = _study(args)
    cloud = study.cloud
    steps = args.more_steps
    for name in args.rows:
        t0 = time.perf_counter()
        if name == "unrefined":
            study.record(name, cloud, 0.0)
        elif name == "detail":
            r = refine(cloud, cameras=study.train.cameras)
            study.record(name, r.cloud, time.perf_counter() - t0, notes=r.notes)
        elif name == "images":
            fitted = _images_row(study, t0)
            steps = steps or fitted
        elif name == "more":
            n = steps or 400
            study.record(name, fine_tune(cloud, study.train, n, config=study.config, seed=0)
                         .replace(background=cloud.background), time.perf_counter() - t0, iterations=n)
        elif name == "oracle":
            _oracle_row(study, t0)
        elif name == "trace":
            _trace_row(study, t0)
        elif name == "real":
            if args.real_run is None:
                raise SystemExit("the real row needs --real-run")
            real_run = json.loads((args.real_run / "run.json").read_text())
            study.record(name, read_ply(args.real_run / f"stage_{int(real_run['stages_done']) - 1}.ply"), 0.0)
    if args.picture is not None:
        _picture(args.picture, study.clouds, study.test[2 * study.height])
    return 0


def _detail_start(cloud) -> dict:
    """The detail model's changes per octave of `cloud`: where `refine(images=...)` starts its fit."""
    from gvae_core.octaves import octave_fields  # noqa: PLC0415

    return octave_fields(refine(cloud, fidelity=None).cloud)


def _picture(path: Path, clouds: dict, views) -> None:
    """One held-out view at 2x: the photo and every row's render, each with its centre third zoomed 3x below."""
    from PIL import Image  # noqa: PLC0415

    v = len(views) // 2
    one = type(views)([views.cameras[v]], views.images[v:v + 1], views.alphas[v:v + 1], [views.names[v]])
    panels = [("photo", one.images[0])] + [(name, render_views(c, one)[0]) for name, c in clouds.items()]
    h, w = panels[0][1].shape[:2]
    ch, cw = h // 3, w // 3
    y0, x0 = h // 2 - ch // 2, w // 2 - cw // 2
    columns = []
    for _, img in panels:
        crop = np.kron(img[y0:y0 + ch, x0:x0 + cw], np.ones((3, 3, 1)))
        col = np.concatenate([img, np.pad(crop, ((0, 0), (0, w - crop.shape[1]), (0, 0)), mode="edge")], 0)
        columns.append(col)
    sheet = np.concatenate(columns, 1)
    Image.fromarray((np.clip(sheet, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path, quality=85)  # (.jpg: small)
    print(f"wrote {path}: columns {', '.join(name for name, _ in panels)}")


if __name__ == "__main__":
    raise SystemExit(main())
