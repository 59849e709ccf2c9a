"""Progressive training: seconds per iteration, peak memory and PSNR per resolution; and a training
step's profile, part by part (`profile_step`, `python -m gvae_core.benchmarks.train CAPTURE CLOUD`).

Benchmark scenes (default: the first of `list_scenes()`; $GVAE_BENCH_TRAIN_SCENE: one name or several,
comma-separated) trained with a training profile ($GVAE_BENCH_TRAIN_PROFILE: `default`, or `legacy`
for the schedule before the last stage trained until it converged) on the `default` scene profile
(`--quick`: the `tiny` profiles). Every row is one stage of the same run: its time and its error
(train/validation/test PSNR). The project's counterpart of the paper's resolution-scaling (VRAM)
table: peak resident memory of the process per stage, and how much it rose above the memory at the
start of the stage.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time

from ..scenes import BlenderNotAvailable, list_scenes, make_scene
from ..train import TrainConfig, train_progressive


def run(args) -> None:
    quick = bool(getattr(args, "quick", False))
    names = (os.environ.get("GVAE_BENCH_TRAIN_SCENE") or list_scenes()[0]).split(",")
    for name in names:
        _scene(name.strip(), quick)


def _scene(name: str, quick: bool) -> None:
    scene_profile = "tiny" if quick else "default"
    profile = "tiny" if quick else os.environ.get("GVAE_BENCH_TRAIN_PROFILE", "default")
    threads = int(os.environ.get("GVAE_BENCH_TRAIN_THREADS", "1"))
    try:
        t = time.perf_counter()
        scene = make_scene(name, profile=scene_profile)
        print(f"scene {name} ({scene_profile} profile) ready in {time.perf_counter() - t:.1f} s: {scene}")
    except BlenderNotAvailable as exc:
        print(f"skipped: no benchmark scene ({exc})")
        return
    config = TrainConfig.profile(profile)
    print(f"training profile {profile}: resolutions {config.resolutions}, iterations {config.iterations}"
          f"{' (the last until the validation views stop improving)' if config.converge else ''}, "
          f"torch threads {threads}, load average {os.getloadavg()[0]:.2f} at start")
    with tempfile.TemporaryDirectory(prefix="gvae-bench-train-") as out:
        t, c = time.perf_counter(), time.process_time()
        result = train_progressive(scene, config, out_dir=out, progress=False, threads=threads)
        total, cpu = time.perf_counter() - t, time.process_time() - c
    print(f"| {'res (px)':>8} | {'iters':>5} | {'s/iter':>7} | {'stage s':>7} | {'Gaussians':>9} | "
          f"{'train dB':>8} | {'val dB':>6} | {'test dB':>7} | {'peak RSS MB':>11} | {'rise MB':>7} |")
    print("|" + "|".join("-" * (w + 2) for w in (8, 5, 7, 7, 9, 8, 6, 7, 11, 7)) + "|")
    for e in result.log:
        test = e["test_psnr"] if e["test_psnr"] is not None else float("nan")
        val = e.get("validation_psnr")
        print(f"| {e['resolution']:>8} | {e['iterations']:>5} | {e['seconds_per_iteration']:>7.3f} | "
              f"{e['seconds']:>7.1f} | {e['n_gaussians']:>9} | {e['train_psnr']:>8.2f} | "
              f"{val if val is not None else float('nan'):>6.2f} | {test:>7.2f} | "
              f"{e['peak_rss_mb']:>11.0f} | {e['peak_rss_mb'] - e['rss_start_mb']:>7.0f} |")
    if "stopped" in result.log[-1]:
        print(f"last stage: {result.log[-1]['stopped']}")
    print(f"total {total:.1f} s ({cpu:.1f} CPU s) including evaluation and writing (load average at end "
          f"{os.getloadavg()[0]:.2f})")


# ----------------------------------------------------------------------------- one step, part by part

#: The parts of a training step `profile_step` times, in the order a step runs them.
STEP_PARTS = ("project", "bin", "composite", "loss", "backward (loss, image)", "composite backward",
              "project backward", "optimizer", "statistics", "densify")


@contextlib.contextmanager
def _timed_renderer(spent: dict[str, float], clock):
    """The compiled renderer's stages, forward and backward, timed into `spent` while in the block."""
    from ..rendering import compiled  # noqa: PLC0415

    def timed(part, fn):
        def wrapper(*a, **k):
            t = clock()
            try:
                return fn(*a, **k)
            finally:
                spent[part] += clock() - t
        return wrapper

    patched = {"project": (compiled, "project"), "bin": (compiled, "bin_gaussians"),
               "composite": (compiled, "composite_forward"), "composite backward": (compiled, "composite_backward")}
    saved = {part: getattr(owner, name) for part, (owner, name) in patched.items()}
    saved_backward = compiled.ProjectFunction.backward
    try:
        for part, (owner, name) in patched.items():
            setattr(owner, name, timed(part, saved[part]))
        compiled.ProjectFunction.backward = staticmethod(timed("project backward", saved_backward))
        yield
    finally:
        for part, (owner, name) in patched.items():
            setattr(owner, name, saved[part])
        compiled.ProjectFunction.backward = saved_backward


def profile_step(cloud, views, *, steps: int = 20, sh_degree: int = 3, densify_every: int = 25,
                 config=None, seed: int = 0, fused_adam: bool = True,
                 compiled_loss: bool = True) -> dict[str, float]:
    """CPU seconds of this thread per training step, part by part (`STEP_PARTS`), over `steps`
    steps of the trainer's recipe on `cloud` and the training `views` (one view a step, in a seeded
    order): the renderer's stages forward and backward (timed inside the compiled path: run it with
    one torch thread, so that the thread's CPU time is the step's), the loss, the optimiser, the
    densification statistics and a round of density control every `densify_every` steps (its
    cost spread over the steps; at the cloud's count, as at a budget). Also "step" (the whole step),
    "other" (what no part covers) and "gaussians_end". `fused_adam` False: Adam looping over the
    parameters."""
    import numpy as np  # noqa: PLC0415
    import torch  # noqa: PLC0415

    from ..camera import scene_extent  # noqa: PLC0415
    from ..train.photometric import photometric_loss  # noqa: PLC0415
    from ..rendering import RenderSettings, render  # noqa: PLC0415
    from ..train.evaluation import training_targets  # noqa: PLC0415
    from ..train.model import GaussianModel  # noqa: PLC0415
    from ..train.strategy import DensifyStrategy  # noqa: PLC0415

    config = config or TrainConfig()
    spent = dict.fromkeys(STEP_PARTS, 0.0)
    clock = time.thread_time
    _, extent = scene_extent(views.cameras)
    model = GaussianModel.fresh(cloud.replace(extra={}), config.learning_rates(extent), extent, fused_adam=fused_adam)
    strategy = DensifyStrategy.for_stage(config, 0, len(cloud))  # at its budget
    state = strategy.initialize_state(model)
    targets = training_targets(views, config.background)
    settings = RenderSettings(antialias=config.antialias)
    order = np.random.default_rng(seed).permutation(max(steps, len(views)))
    gen = torch.Generator().manual_seed(seed)
    total = 0.0
    with _timed_renderer(spent, clock):
        for it in range(1, steps + 1):
            v = int(order[it - 1] % len(views))
            camera = views.cameras[v]
            t0 = clock()
            result = render(model.cloud(), camera, background=config.background, sh_degree=sh_degree,
                            settings=settings)
            result.means2d.retain_grad()
            t = clock()
            loss = photometric_loss(result.image, targets[v], config.lambda_dssim, compiled=compiled_loss)
            spent["loss"] += clock() - t
            t = clock()
            inner = spent["composite backward"] + spent["project backward"]
            loss.backward()
            spent["backward (loss, image)"] += clock() - t - (spent["composite backward"] + spent["project backward"]
                                                              - inner)
            with torch.no_grad():
                t = clock()
                state.add(result.means2d.grad, result.visible, result.radii, camera.width, camera.height)
                spent["statistics"] += clock() - t
                t = clock()
                model.optimizer.step()
                model.optimizer.zero_grad(set_to_none=True)
                spent["optimizer"] += clock() - t
                if it % densify_every == 0:
                    t = clock()
                    strategy.densify_and_prune(model, state, gen, image_height=camera.height, prune_large=False)
                    spent["densify"] += clock() - t
            total += clock() - t0
    out = {part: s / steps for part, s in spent.items()}
    out["step"] = total / steps
    out["other"] = out["step"] - sum(spent.values()) / steps
    out["gaussians_end"] = float(len(model))
    return out


def main(argv=None) -> int:
    """`python -m gvae_core.benchmarks.train --step CAPTURE CLOUD.ply --height H`: the step profile."""
    import argparse  # noqa: PLC0415

    import torch  # noqa: PLC0415

    from ..capture import read_capture  # noqa: PLC0415
    from ..ply import read_ply  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m gvae_core.benchmarks.train", description=profile_step.__doc__)
    p.add_argument("capture")
    p.add_argument("cloud")
    p.add_argument("--height", type=int, required=True)
    p.add_argument("--test-every", type=int, default=8)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--plain-adam", action="store_true",
                   help="torch's Adam looping over the parameters (what the trainer used before its fused Adam)")
    p.add_argument("--torch-loss", action="store_true",
                   help="the loss and its backward by torch (what the trainer used before its compiled loss)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    views = read_capture(args.capture).held_out(args.test_every).load("train", args.height)
    cloud = read_ply(args.cloud)
    kw = {"fused_adam": not args.plain_adam, "compiled_loss": not args.torch_loss}
    profile_step(cloud, views, steps=args.warmup, **kw)  # kernels loaded, memory touched
    load = os.getloadavg()[0]
    out = profile_step(cloud, views, steps=args.steps, **kw)
    print(f"{len(cloud)} Gaussians, {len(views)} views of {views.cameras[0].width}x{views.cameras[0].height}, "
          f"{args.steps} steps, 1 thread, {'plain' if args.plain_adam else 'fused'} Adam, "
          f"{'torch' if args.torch_loss else 'compiled'} loss, load {load:.1f} at start, "
          f"{os.getloadavg()[0]:.1f} at end")
    print("| part | CPU ms per step | share |")
    print("|---|---:|---:|")
    for part in (*STEP_PARTS, "other", "step"):
        print(f"| {part} | {1000 * out[part]:.1f} | {out[part] / out['step']:.0%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
