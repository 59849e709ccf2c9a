"""The compiled CPU kernels (`gvae_core.rendering.compiled`) against a plain C/OpenMP rasteriser
(`reference_rasteriser.c`, compiled here when a C compiler is at hand) and the torch path, in one
run; the Hessian scores of a capture-sized cloud; the kernels' first-call cost.

Rows of the first table, repeats interleaved (C, compiled, torch, C, ...) so that load from other
work hits all alike; times are medians, the ratio is against the C forward pass of the same run:
- C: the reference's forward pass by stage (projection + SH, binning + depth sort, compositing);
- compiled forward: `render` (kernels="compiled") by stage, and in all (with the image assembly);
- compiled fwd+bwd: `render` and the backward pass of a per-pixel weighted sum to all six raw
  parameter tensors;
- torch: the same two through the torch code (kernels="torch"), the reference the tests hold the
  kernels to.
Errors of the same run: |image - float64 reference| on sampled pixels (compiled and C), |compiled -
torch| over the image, and the largest difference of any gradient relative to its largest value.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

from ..examples import example_cloud
from ..rendering import RenderSettings, compiled, render
from ..rendering.reference import render_reference
from ..rendering.tiles import Binning
from .c_reference import build
from .render import benchmark_camera, benchmark_scene

FIELDS = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
BG = (0.2, 0.3, 0.4)
#: (Gaussians, image height) of the renderer rows; threads 2 and 1 each.
SIZES = ((100_000, 800), (1_000_000, 800))
SIZES_QUICK = ((100_000, 800),)


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _compiled_stages(tc, cam) -> tuple[dict, torch.Tensor]:
    """The compiled forward pass by stage (seconds) and its image."""
    t0 = time.perf_counter()
    proj, table = compiled.project(tc.means, tc.scales, tc.quats, tc.opacities, tc.sh_dc, tc.sh_rest, cam, 3)
    t1 = time.perf_counter()
    binning: Binning = compiled.bin_gaussians(table, proj.footprint, proj.visible, cam.width, cam.height, 8)
    t2 = time.perf_counter()
    acc = compiled.composite_forward(table, binning)
    t3 = time.perf_counter()
    return {"project": t1 - t0, "bin": t2 - t1, "composite": t3 - t2}, acc


def _fwd_bwd(tc, cam, weights, settings) -> tuple[float, dict]:
    for name in FIELDS:
        getattr(tc, name).grad = None
    t = time.perf_counter()
    out = render(tc, cam, background=BG, settings=settings)
    (out.image * weights).sum().backward()
    return time.perf_counter() - t, {name: getattr(tc, name).grad.clone() for name in FIELDS}


def renderer_rows(sizes, threads_list=(2, 1), repeats: int = 7, torch_repeats: int = 3) -> list[dict]:
    """The first table's rows (see the module docstring)."""
    cref = build()
    rows = []
    for n, height in sizes:
        cloud = benchmark_scene(n)
        cam = benchmark_camera(height)
        tc = cloud.to_torch()
        for name in FIELDS:
            getattr(tc, name).requires_grad_()
        weights = torch.rand(height, height, 3, generator=torch.Generator().manual_seed(0))
        fast, slow = RenderSettings(kernels="compiled"), RenderSettings(kernels="torch")
        for threads in threads_list:
            torch.set_num_threads(threads)
            t = {k: [] for k in ("c_project", "c_bin", "c_composite", "c", "project", "bin", "composite", "fwd",
                                 "both", "torch_fwd", "torch_both")}
            load = _load()
            for r in range(repeats):
                if cref.lib is not None:
                    c_image, c_times = cref.render(cloud, cam, threads=threads, background=BG)
                    for k in ("project", "bin", "composite"):
                        t[f"c_{k}"].append(c_times[k])
                    t["c"].append(c_times["total"])
                with torch.no_grad():
                    stages, _ = _compiled_stages(tc, cam)
                    for k, v in stages.items():
                        t[k].append(v)
                    s = time.perf_counter()
                    image = render(tc, cam, background=BG, settings=fast).image
                    t["fwd"].append(time.perf_counter() - s)
                dt, grads = _fwd_bwd(tc, cam, weights, fast)
                t["both"].append(dt)
                if r < torch_repeats:
                    with torch.no_grad():
                        s = time.perf_counter()
                        torch_image = render(tc, cam, background=BG, settings=slow).image
                        t["torch_fwd"].append(time.perf_counter() - s)
                    dt, torch_grads = _fwd_bwd(tc, cam, weights, slow)
                    t["torch_both"].append(dt)
            rng = np.random.default_rng(1)
            samples = 64 if n >= 1_000_000 else 200
            pix = np.stack([rng.integers(0, height, samples), rng.integers(0, height, samples)], 1)
            ref, _, _ = render_reference(cloud, cam, background=BG, pixels=pix)
            med = {k: statistics.median(v) if v else float("nan") for k, v in t.items()}
            grad_err = max(float((grads[k] - torch_grads[k]).abs().max()
                                 / torch_grads[k].abs().max().clamp(min=1e-30)) for k in FIELDS)
            rows.append(dict(
                n=n, height=height, threads=threads, load=load, **med,
                err=float(np.abs(image.numpy()[pix[:, 0], pix[:, 1]] - ref).max()),
                c_err=(float(np.abs(c_image[pix[:, 0], pix[:, 1]] - ref).max()) if cref.lib is not None
                       else float("nan")),
                vs_torch=float((image - torch_image).abs().max()), grad_err=grad_err))
    torch.set_num_threads(threads_list[0])
    return rows, cref


def print_renderer(rows, cref) -> None:
    if cref.lib is None:
        print(f"C reference skipped: {cref.reason}")
    else:
        print(f"C reference built with: {cref.command}")
    print("| Gaussians | image | threads | C: project / bin / composite = forward ms | compiled: project / bin / "
          "composite ms | compiled forward ms (x C; x C without its binning) | compiled fwd+bwd ms (x C; x C without "
          "its binning) | torch forward ms | torch fwd+bwd ms | max err vs float64 (compiled / C) | compiled - torch "
          "image | grad rel. diff | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ms = {k: 1000 * v if isinstance(v, float) else v for k, v in r.items()}
        c, pc = r["c"], r["c_project"] + r["c_composite"]
        cells = [f"{r['n']:,}", f"{r['height']}x{r['height']}", str(r["threads"]),
                 f"{ms['c_project']:.1f} / {ms['c_bin']:.1f} / {ms['c_composite']:.1f} = **{ms['c']:.1f}**",
                 f"{ms['project']:.1f} / {ms['bin']:.1f} / {ms['composite']:.1f}",
                 f"**{ms['fwd']:.1f}** ({r['fwd'] / c:.2f}x; {r['fwd'] / pc:.2f}x)",
                 f"**{ms['both']:.1f}** ({r['both'] / c:.2f}x; {r['both'] / pc:.2f}x)",
                 f"{ms['torch_fwd']:.1f}", f"{ms['torch_both']:.1f}", f"{r['err']:.1g} / {r['c_err']:.1g}",
                 f"{r['vs_torch']:.1g}", f"{r['grad_err']:.1g}", r["load"]]
        print("| " + " | ".join(cells) + " |", flush=True)


def hessian_rows(sizes=(1_000_000,), repeats: int = 3, with_torch: bool = True) -> list[dict]:
    """The Hessian scores (`hessian_scores`, default views) of `example_cloud(n)`, compiled (median of
    `repeats`) and, once, through the torch code; parts by `timings`."""
    from ..hessian import hessian_scores  # noqa: PLC0415 - (imports the model stack)

    rows = []
    for n in sizes:
        cloud = example_cloud(n, seed=1)
        for kernels in ("compiled",) + (("torch",) if with_torch else ()):
            settings = RenderSettings(tile_size=4, kernels=kernels)
            runs = []
            for _ in range(repeats if kernels == "compiled" else 1):
                timings: dict = {}
                load = _load()
                t, c = time.perf_counter(), time.process_time()
                scores = hessian_scores(cloud, render_settings=settings, timings=timings)
                runs.append((time.perf_counter() - t, timings, load, scores, time.process_time() - c))
            runs.sort(key=lambda x: x[0])
            total, timings, load, scores, cpu = runs[len(runs) // 2]
            rows.append(dict(n=n, kernels=kernels, total=total, timings=timings, load=load, scores=scores, cpu=cpu))
        if with_torch:
            a, b = rows[-2]["scores"], rows[-1]["scores"]
            rows[-2]["diff"] = float(((a - b).abs() / b.abs().clamp(min=1e-3)).max())
    return rows


def print_hessian(rows) -> None:
    print("| Gaussians | path | seconds (process CPU) | parts (project / bin / composite / sweep / blocks / score) | "
          "max score difference (relative) | load |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        t = r["timings"]
        parts = " / ".join(f"{t.get(k, 0.0):.2f}" for k in ("project", "bin", "composite", "sweep", "blocks", "score"))
        diff = f"{r['diff']:.1g}" if "diff" in r else ""
        cells = [f"{r['n']:,}", r["kernels"], f"**{r['total']:.2f}** ({r['cpu']:.1f})", parts, diff, r["load"]]
        print("| " + " | ".join(cells) + " |", flush=True)


_FIRST_CALL = """
import json, time
t0 = time.perf_counter()
from gvae_core.rendering import compiled
t1 = time.perf_counter()
cached = compiled.kernels_cached()
seconds = compiled.compile_kernels()
print(json.dumps(dict(imports=t1 - t0, cached=cached, ready=seconds)))
"""


def first_call(cache_dir: str | None = None) -> list[dict]:
    """Seconds to make every kernel ready in a fresh process: compiled into an empty cache, then
    loaded from it (each in its own process, the cache in a temporary folder)."""
    with tempfile.TemporaryDirectory(prefix="gvae-kernels-") as tmp:
        env = {**os.environ, "GVAE_CACHE_DIR": cache_dir or tmp}
        out = []
        for _ in range(2):
            load = _load()
            t = time.perf_counter()
            proc = subprocess.run([sys.executable, "-c", _FIRST_CALL], env=env, capture_output=True, text=True,
                                  check=True)
            out.append({**json.loads(proc.stdout.strip().splitlines()[-1]), "process": time.perf_counter() - t,
                        "load": load})
    return out


def print_first_call(rows) -> None:
    print("| cache | process s | importing the kernels s | compiling or loading them s | load |")
    print("|---|---|---|---|---|")
    for r in rows:
        state = "filled (loaded)" if r["cached"] else "empty (compiled)"
        print(f"| {state} | {r['process']:.1f} | {r['imports']:.2f} | **{r['ready']:.1f}** | {r['load']} |")


def ready() -> bool:
    """Whether the kernels can run here (else says why, skipped); OpenMP's threads told to sleep
    when idle (OMP_WAIT_POLICY=PASSIVE unless set: spinning threads steal the other path's cores)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    missing = compiled.numba_missing()
    if missing:
        print(f"skipped: {missing}")
    return missing is None


def run(args) -> None:
    if not ready():
        return
    quick = getattr(args, "quick", False)
    print(f"load average (1, 5, 15 min) at start: {_load()}; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    print("\nFirst call of the kernels in a fresh process (`compiled.compile_kernels`):")
    print_first_call(first_call())
    compiled.compile_kernels()
    print("\nRenderer, forward and forward+backward (SH 3, `benchmark_scene`), against the C reference:")
    rows, cref = renderer_rows(SIZES_QUICK if quick else SIZES, repeats=3 if quick else 7)
    print_renderer(rows, cref)
    print("\nHessian scores (4 placed views at 256 px, `example_cloud`):")
    print_hessian(hessian_rows((100_000,) if quick else (1_000_000,), repeats=1 if quick else 3))


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.kernels")
    parser.add_argument("--quick", action="store_true", help="100k Gaussians only")
    run(parser.parse_args())
