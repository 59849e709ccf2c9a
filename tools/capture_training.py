"""Train a real capture with the project and tabulate the held-out figures (docs/benchmarks/training.md,
"Training on a real capture"): one `gvae train` per (image size, variant), each in its own process,
every 8th photo held out (the LLFF / Mip-NeRF 360 convention); PSNR and SSIM of the held-out photos
at the training resolution, the validation photos' PSNR (training photos set aside, what choices are
made on), Gaussians, the last stage's iterations and why it stopped, wall and CPU time with the load,
peak memory, how much of the training pixels the start covered; with `--more N`, what `gvae train
RUN --more N` adds afterwards (is the run converged?).

Usage: python tools/capture_training.py CAPTURE --out RUNS [--downscale 4 2] [--init sfm random]
                                        [--variant NAME="gvae train options" ...] [--more N]
                                        [--threads 2] [--test-every 8] [--picture OUT.png]
                                        [-- extra gvae train options for every run]
e.g.   python tools/capture_training.py ../shared/captures/plush --out runs/plush --downscale 4 --init sfm
       python tools/capture_training.py ../shared/captures/plush --out runs/plush --variant default= \\
           --variant cap50k="--gaussians-per-pixel 0 --max-gaussians 50000" --variant legacy="--profile legacy"
Without `--variant`, one variant per `--init` (named after it). `--picture`: three held-out photos above
the first run's renders of them (at its resolution). Runs that finished already are reused (gvae train
resumes); a long job: start it in the background with its log on disk.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("capture", type=Path)
    p.add_argument("--out", type=Path, required=True, help="folder for the runs (one subfolder each)")
    p.add_argument("--downscale", type=float, nargs="+", default=[4.0], help="image sizes: stored size / F")
    p.add_argument("--init", nargs="+", default=["sfm", "random"], help="starts to compare (without --variant)")
    p.add_argument("--variant", action="append", default=[], metavar='NAME="OPTIONS"',
                   help="a named set of gvae train options (repeatable)")
    p.add_argument("--more", type=int, metavar="N", help="then train each run's last stage N more iterations")
    p.add_argument("--test-every", type=int, default=8)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--picture", type=Path, help="held-out photos above the first run's renders of them")
    args = p.parse_args(argv)
    variants = [v.split("=", 1) if "=" in v else (v, "") for v in args.variant] or [
        (init, f"--init {init}") for init in args.init]
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    rows = []
    for factor in args.downscale:
        for name, options in variants:
            run = args.out / f"d{factor:g}-{name}"
            cmd = [sys.executable, "-m", "gvae_core", "train", str(args.capture), "--out", str(run), "--downscale",
                   f"{factor:g}", "--test-every", str(args.test_every), "--threads", str(args.threads), "--quiet",
                   *shlex.split(options), *extra]
            print("$ " + " ".join(cmd), flush=True)
            row = {"downscale": factor, "variant": name, "options": options, "load_at_start": _load()}
            t0, c0 = time.perf_counter(), _children_cpu()
            subprocess.run(cmd, check=True, env=env)
            row.update(command_seconds=round(time.perf_counter() - t0, 1), command_cpu=round(_children_cpu() - c0, 1),
                       load_at_end=_load(), stages=json.loads((run / "log.json").read_text()))
            if args.more:
                more = [sys.executable, "-m", "gvae_core", "train", str(run), "--more", str(args.more), "--threads",
                        str(args.threads), "--quiet"]
                print("$ " + " ".join(more), flush=True)
                subprocess.run(more, check=True, env=env)
                entries = json.loads((run / "more.json").read_text())
                row["more"] = next(e for e in entries if e["more"] == args.more)
            rows.append(row)
            (args.out / "summary.json").write_text(json.dumps(rows, indent=2))
    print()
    print(table(rows))
    if args.picture is not None and rows:
        _picture(args.out / f"d{rows[0]['downscale']:g}-{rows[0]['variant']}", args.picture)
    return 0


def table(rows: list[dict]) -> str:
    """The markdown table of `rows` (summary.json's)."""
    out = ["| stored size / | variant | stages (px) | last stage iterations (why it stopped) | Gaussians | "
           "validation PSNR | held-out PSNR / SSIM | training PSNR | wall s (CPU s) | load | more: held-out dB |",
           "|---|---|---|---|---:|---:|---|---:|---|---|---|"]
    for r in rows:
        last = r["stages"][-1]
        wall = sum(e["seconds"] + e["eval_seconds"] for e in r["stages"])
        cpu = sum(e["cpu_seconds"] for e in r["stages"])
        why = last.get("stopped", "fixed")
        more = r.get("more")
        more_txt = (f"+{more['more']}: {more['test_psnr']:.2f} ({more['test_psnr'] - last['test_psnr']:+.2f})"
                    if more else "")
        out.append(f"| {r['downscale']:g} | {r['variant']} | {'/'.join(str(e['resolution']) for e in r['stages'])} "
                   f"| {last['iterations']} ({why}) | {last['n_gaussians']:,} | {_f(last.get('validation_psnr'))} | "
                   f"{last['test_psnr']:.2f} / {last['test_ssim']:.3f} | {last['train_psnr']:.2f} | "
                   f"{wall:.0f} ({cpu:.0f}) | {r['load_at_start']}-{r.get('load_at_end', '?')} | {more_txt} |")
    return "\n".join(out)


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def _load() -> float:
    return round(os.getloadavg()[0], 1)


def _children_cpu() -> float:
    t = os.times()
    return t.children_user + t.children_system


def _picture(run: Path, path: Path, count: int = 3) -> None:
    """`count` held-out photos of the run's capture (top) and the run's last stage drawn through
    their cameras (bottom), at the run's last resolution, over the background it was trained over."""
    import numpy as np  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    from gvae_core.capture import read_capture  # noqa: PLC0415
    from gvae_core.metrics.image import render_views  # noqa: PLC0415
    from gvae_core.ply import read_ply  # noqa: PLC0415
    from gvae_core.train import RunFolder  # noqa: PLC0415

    state = RunFolder(run).finished()
    stage = state.stages_done - 1
    height = state.config.resolutions[stage]
    views = read_capture(state.data, state.config.test_every).load("test", height)
    pick = np.linspace(0, len(views) - 1, min(count, len(views))).round().astype(int)
    one = type(views)([views.cameras[i] for i in pick], views.images[pick], views.alphas[pick])
    renders = render_views(read_ply(run / f"stage_{stage}.ply"), one)
    sheet = np.concatenate([np.concatenate(list(one.images), 1), np.concatenate(list(renders), 1)], 0)
    Image.fromarray((np.clip(sheet, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path, quality=85)  # (.jpg: small)
    print(f"wrote {path}: held-out photos {', '.join(views.names[i] for i in pick)} (top), {run.name} (bottom)")


if __name__ == "__main__":
    raise SystemExit(main())
