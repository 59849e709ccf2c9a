"""Every compiled CPU kernel made ready before the first real job: the renderer's and the Hessian's
(`rendering.compiled.compile_kernels`), the detail model's (its inputs and its network on a tiny
cloud), compaction's (a tiny compact) and the training loss's (`train.photometric`), called with
the argument types real jobs give them. The first run on a machine compiles them (about a minute on
one core) and says so; later runs load them from the on-disk cache
(`rendering.kernels.kernel_cache_dir`). `make test` runs `main` first, so that no test process
compiles its own; Blender's Refine and Compact call `compile_kernels` with their progress."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .antialias import with_dilation_3d
from .capture import default_views
from .compaction import compact
from .detail import detail_inputs, load_detail
from .examples import example_cloud
from .rendering import compiled
from .train.photometric import loss_and_gradient


def kernels_cached() -> bool:
    """Whether every kernel of every room is in the on-disk cache (Numba installed)."""
    if compiled.numba_missing() is not None:
        return True
    from .compaction import kernels as compaction_kernels  # noqa: PLC0415 - these import Numba
    from .detail import kernels as detail_kernels  # noqa: PLC0415
    from .rendering import kernels  # noqa: PLC0415
    from .train import photometric_kernels  # noqa: PLC0415

    return all(kernels.is_cached(d) for room in (kernels, detail_kernels, compaction_kernels, photometric_kernels)
               for d in kernels.module_kernels(room))


def compile_kernels(progress: Callable[[float, str], None] | None = None) -> float:
    """Make every compiled kernel ready in this process; progress(0, message) first when some must be
    compiled. Returns the seconds it took (0 without Numba: the torch and numpy code run then)."""
    if compiled.numba_missing() is not None:
        return 0.0
    t0 = time.perf_counter()
    if progress is not None and not kernels_cached():
        progress(0.0, "Compiling the CPU kernels (first run only, a minute or two)")
    compiled.compile_kernels()
    tiny = example_cloud(64, seed=0)
    model = load_detail(None)
    drawn = with_dilation_3d(tiny, default_views(tiny, 2, 64))
    model.changes(detail_inputs(drawn, None, neighbours=model.config.inputs_neighbours))
    compact(tiny, keep=0.5, distill=0, check_memory=False)
    loss_and_gradient(np.zeros((16, 16, 3), np.float32), np.ones((16, 16, 3), np.float32), 0.2)
    return time.perf_counter() - t0


def main() -> None:
    """Make every kernel ready and say where they are kept (`make test` runs this first)."""
    if compiled.numba_missing():
        print(f"compiled kernels: {compiled.numba_missing()}; the torch and numpy code run")
        return
    seconds = compile_kernels(lambda _, message: print(message, flush=True))
    print(f"compiled kernels ready in {seconds:.1f} s ({compiled.kernels().kernel_cache_dir()})")
