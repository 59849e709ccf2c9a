"""Will a job fit in memory? An estimate of its peak from its sizes, and the memory free.

`refine`, `compact`, `gvae render` and training call a `check_*_memory` before any work, so a
job too large for the machine is refused at once, with the estimate and what would fit in the
message, instead of being killed by the system (or swapping the machine to a halt) minutes later.
Each estimate is linear in the counts it depends on, with coefficients fitted to measured peaks
and rounded up (the measurements: "Where the code's defaults come from" at the end of the job's
page in docs/benchmarks/). numpy only.

`reuse_freed_memory` is the other half of working at capture scale: a scope in which the memory
of freed arrays is kept for the next ones instead of being handed back to the system and faulted
in again page by page.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
import threading
from collections.abc import Iterator

from . import parallel
from .conventions import SH_REST_COUNTS

__all__ = ["NotEnoughMemoryError", "available_memory", "estimate_refine_memory", "check_refine_memory",
           "estimate_compact_memory", "check_compact_memory", "estimate_image_fit_memory", "check_image_fit_memory",
           "estimate_render_memory", "check_render_memory", "estimate_train_memory", "check_train_memory",
           "train_cap", "reuse_freed_memory"]

#: A refine: bytes of the Python process with torch and the models loaded, before any cloud; the
#: coefficients below are fitted to the peaks `python -m gvae_core.benchmarks refine` prints beside
#: the estimate (docs/benchmarks/refine.md).
BASE_BYTES = 600 << 20
#: Bytes per Gaussian, per float32 value it holds (14 + 3 K for SH rest K, plus its extra
#: properties): the input, its checked copy and the output cloud.
PER_VALUE = 3 * 4
#: Bytes per Gaussian of the Hessian scoring (Morton-ordered copy, float64 blocks and moments,
#: per-view projection, tile pairs and tables).
HESSIAN_PER_GAUSSIAN = 1500
#: Bytes per pixel of one scoring view (per-tile transmittance, colour, blocks of the sweep).
HESSIAN_PER_PIXEL = 400
#: Bytes per lineage given to the lineage VAEs, per step (features, model activations, children).
MODEL_PER_LINEAGE = 4000
#: Bytes per Gaussian given to the detail model (inputs, neighbours, activations in batches, the
#: changes per octave of the output).
DETAIL_PER_GAUSSIAN = 1000

#: Bytes per Gaussian of a compaction's merging, per neighbour in its graph (edge ends, costs and
#: the per-edge 3x3 temporaries of the cost), and per Gaussian (moments: mass, centre, covariance).
MERGE_PER_EDGE = 260
MERGE_PER_GAUSSIAN = 400


#: A fit to the capture's images (`refine(images=...)`): the process before any cloud (it loads no
#: model but the detail model); bytes per value of a Gaussian (14 + 3 K, children included): the
#: cloud as torch tensors, its changes per octave with their gradients and Adam's two moments, the
#: copies each step draws from and the render's per-Gaussian state; per image pixel: the images and
#: their composites (float32 RGB); per pixel a step draws (at 2^octave times the images' size): the
#: render's per-pixel state kept for the backward pass. Fitted to `python -m gvae_core.benchmarks
#: superres` peaks (docs/benchmarks/refine-images.md).
IMAGE_FIT_BASE_BYTES = 400 << 20
IMAGE_FIT_PER_VALUE = 98
IMAGE_FIT_PER_PIXEL = 28
IMAGE_FIT_PER_DRAWN_PIXEL = 440


#: Training (`gvae_core.train`): bytes per Gaussian per value it holds (the parameters, their
#: gradients and Adam's two moments, the densification statistics and the renderer's per-Gaussian
#: buffers of a step), and per pixel of the stage's training images (the images, their composites
#: and one view's render buffers, spread over the views). Fitted to `gvae train` peaks
#: (docs/benchmarks/training.md).
TRAIN_PER_VALUE = 56
TRAIN_PER_PIXEL = 40
#: The share of the available memory a run may fill with Gaussians (`train_cap`).
TRAIN_MEMORY_SHARE = 0.7


#: One render of a view (`gvae render`): the process with torch and the compiled kernels loaded;
#: bytes per Gaussian (its projection, tile footprint and sort keys; the torch renderer's, when the
#: compiled kernels are missing, are larger), plus a copy of its values (a refined cloud's fields as
#: drawn); per pixel (the accumulated features in tiles, the image, alpha and depth, their float
#: and 8-bit copies for the PNG); per pixel and thread (the compiled binning's per-thread tile
#: histograms); per Gaussian-tile pair (its id; the torch renderer also keeps the pair's table row
#: and sort). The pairs a view makes depend on the cloud: RENDER_PAIRS_PER_PIXEL is a dense one's
#: (one pair per Gaussian at least), callers that measure the cloud's pass what they found.
#: Fitted to peaks of renders by both renderers (docs/benchmarks/kernels.md).
RENDER_BASE_BYTES = 512 << 20
RENDER_PER_GAUSSIAN = {"compiled": 256, "torch": 512}
RENDER_PER_PIXEL = 64
RENDER_PER_PIXEL_PER_THREAD = 2
RENDER_PER_PAIR = {"compiled": 8, "torch": 56}
RENDER_PAIRS_PER_PIXEL = 16.0


class NotEnoughMemoryError(ValueError):
    """A job that would need more memory than the machine has free (the message says how much,
    and what would fit)."""


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter of this process (Linux), so that `peak_rss_mb` says the
    peak from here on; False where impossible."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def current_rss_mb() -> float:
    """This process's resident memory now (MiB; Linux), NaN where unknown."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return float("nan")


def peak_rss_mb() -> float:
    """This process's peak resident memory (MiB): Linux's high-water mark (since `reset_peak_rss`),
    else the lifetime maximum getrusage gives."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource  # noqa: PLC0415 - (Unix only)

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation without swapping (Linux MemAvailable, the
    free physical memory elsewhere), or None when it cannot be told."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    if sys.platform == "win32":
        try:
            import ctypes  # noqa: PLC0415 - Windows only

            class _Status(ctypes.Structure):
                _fields_ = [("length", ctypes.c_ulong), ("load", ctypes.c_ulong), ("total", ctypes.c_ulonglong),
                            ("avail", ctypes.c_ulonglong), ("total_page", ctypes.c_ulonglong),
                            ("avail_page", ctypes.c_ulonglong), ("total_virtual", ctypes.c_ulonglong),
                            ("avail_virtual", ctypes.c_ulonglong), ("extended", ctypes.c_ulonglong)]

            status = _Status()
            status.length = ctypes.sizeof(_Status)
            if ctypes.windll.kernel32.GlobalMemoryStatusEx(ctypes.byref(status)):
                return int(status.avail)
        except (OSError, AttributeError):
            return None
        return None
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def estimate_refine_memory(n: int, sh_degree: int = 3, *, extra_values: int = 0, views: int = 4,
                           resolution: int = 256, width: int | None = None, selected: int | None = None,
                           steps: int = 1, scoring: bool = True, method: str = "vae") -> int:
    """Estimated peak bytes of `refine` on `n` Gaussians of SH degree `sh_degree` with
    `extra_values` extra float properties each: scoring over `views` views of `resolution` pixels
    high (`width` wide, default square), then `steps` model steps of the lineage VAEs on `selected`
    lineages (default: half the cloud, the most the 'auto' budget takes), or (`method` "detail")
    the detail model on `selected` Gaussians."""
    k = SH_REST_COUNTS[min(int(sh_degree), 3)]
    values = 14 + 3 * k + int(extra_values)
    hessian = 0
    if scoring:
        pixels = int(resolution) * int(width or resolution)
        hessian = n * HESSIAN_PER_GAUSSIAN + pixels * HESSIAN_PER_PIXEL
    lineages = (n + 1) // 2 if selected is None else int(selected)
    if method == "detail":
        model = lineages * DETAIL_PER_GAUSSIAN
    else:
        model = lineages * MODEL_PER_LINEAGE * min(int(steps), 2)  # later steps: the lineages that grew
    # scoring is over (its buffers freed) before the models run: the peak is the larger of the two
    return int(BASE_BYTES + n * values * PER_VALUE + max(hessian, model))


def _gib(b: int) -> str:
    return f"{b / (1 << 30):.1f} GiB"


def check_refine_memory(n: int, sh_degree: int = 3, **kwargs) -> int:
    """The estimate of `estimate_refine_memory`; raises NotEnoughMemoryError when it exceeds the
    memory available now (skipped where that cannot be told)."""
    return _check(estimate_refine_memory(n, sh_degree, **kwargs), f"refining {n:,} Gaussians (SH degree {sh_degree})",
                  "refine a smaller part of the cloud (or a lower SH degree), use a smaller budget or fewer/smaller "
                  "Hessian views")


def _check(need: int, what: str, advice) -> int:
    """`need` bytes, or NotEnoughMemoryError when that is more than is available now. `advice`:
    what to do instead, or a function of the bytes available that says it."""
    free = available_memory()
    if free is not None and need > free:
        advice = advice(free) if callable(advice) else advice
        raise NotEnoughMemoryError(f"{what} needs about {_gib(need)} of memory, but only {_gib(free)} is available; "
                                   f"{advice}, or close other programs")
    return need


def estimate_compact_memory(n: int, sh_degree: int = 3, *, extra_values: int = 0, views: int = 4,
                            resolution: int = 256, width: int | None = None, neighbours: int = 4) -> int:
    """Estimated peak bytes of `compact` on `n` Gaussians: the input and output clouds, then the
    larger of the Hessian scoring (as for a refine) and the merging over a graph of `neighbours`
    edges a Gaussian."""
    k = SH_REST_COUNTS[min(int(sh_degree), 3)]
    values = 14 + 3 * k + int(extra_values)
    pixels = int(resolution) * int(width or resolution)
    hessian = n * HESSIAN_PER_GAUSSIAN + int(views) * pixels * HESSIAN_PER_PIXEL // 4
    merge = n * (MERGE_PER_GAUSSIAN + int(neighbours) * MERGE_PER_EDGE)
    return int(BASE_BYTES + n * values * PER_VALUE + max(hessian, merge))


def check_compact_memory(n: int, sh_degree: int = 3, **kwargs) -> int:
    """The estimate of `estimate_compact_memory`; raises NotEnoughMemoryError when it exceeds the
    memory available now (skipped where that cannot be told)."""
    return _check(estimate_compact_memory(n, sh_degree, **kwargs),
                  f"compacting {n:,} Gaussians (SH degree {sh_degree})",
                  "compact a smaller part of the cloud or use fewer/smaller scoring views")


def estimate_image_fit_memory(n: int, sh_degree: int = 3, *, images: int, height: int, width: int,
                              extra_values: int = 0, children: float = 0.0, octaves: int = 1, patch: int = 0,
                              views_per_step: int = 1) -> int:
    """Estimated peak bytes of refining `n` Gaussians from `images` training images of `height` x
    `width` pixels (`refine(images=...)`) up to `octaves` octaves, drawing `views_per_step` tiles of
    edge `patch` (0: whole images) a step, with up to `children` added Gaussians per input one."""
    k = SH_REST_COUNTS[min(int(sh_degree), 3)]
    values = 14 + 3 * k
    rows = int(n * (1.0 + max(float(children), 0.0)))
    tile = min(patch, width) * min(patch, height) if patch else width * height
    drawn = max(int(views_per_step), 1) * int(tile) * 4 ** max(int(octaves), 1)
    return int(IMAGE_FIT_BASE_BYTES + n * (values + int(extra_values)) * PER_VALUE + rows * values * IMAGE_FIT_PER_VALUE
               + int(images) * int(height) * int(width) * IMAGE_FIT_PER_PIXEL + drawn * IMAGE_FIT_PER_DRAWN_PIXEL)


def check_image_fit_memory(n: int, sh_degree: int = 3, **kwargs) -> int:
    """The estimate of `estimate_image_fit_memory`; raises NotEnoughMemoryError when it exceeds the
    memory available now (skipped where that cannot be told)."""
    return _check(estimate_image_fit_memory(n, sh_degree, **kwargs),
                  f"refining {n:,} Gaussians (SH degree {sh_degree}) from {kwargs.get('images')} images of "
                  f"{kwargs.get('width')}x{kwargs.get('height')} px",
                  "fit at a smaller --image-height, with fewer images or a part of the cloud")


def estimate_train_memory(n: int, views: int, height: int, width: int, sh_degree: int = 3) -> int:
    """Estimated peak bytes of a training stage with `n` Gaussians of SH degree `sh_degree` on
    `views` images of `height` x `width` pixels."""
    values = 14 + 3 * SH_REST_COUNTS[min(int(sh_degree), 3)]
    return int(BASE_BYTES + n * values * TRAIN_PER_VALUE + int(views) * int(height) * int(width) * TRAIN_PER_PIXEL)


def check_train_memory(n: int, views: int, height: int, width: int, sh_degree: int = 3) -> int:
    """The estimate of `estimate_train_memory`; raises NotEnoughMemoryError when it exceeds the
    memory available now (skipped where that cannot be told), saying the largest image height at
    which `n` Gaussians fit and the most Gaussians that fit at this height."""
    values = 14 + 3 * SH_REST_COUNTS[min(int(sh_degree), 3)]

    def advice(free: int) -> str:
        per_height2 = int(views) * TRAIN_PER_PIXEL * int(width) / max(int(height), 1)  # bytes per height²
        fitting_height = _root(free - BASE_BYTES - n * values * TRAIN_PER_VALUE, per_height2)
        fitting_count = (free - estimate_train_memory(0, views, height, width, sh_degree)) // (values * TRAIN_PER_VALUE)
        parts = ([f"train at --image-height {fitting_height} or lower"] if fitting_height >= 8 else []) + (
            [f"grow to at most {fitting_count:,} Gaussians (--max-gaussians)"] if fitting_count >= 1000 else [])
        return ", ".join(parts) or "train on fewer or smaller images"

    return _check(estimate_train_memory(n, views, height, width, sh_degree),
                  f"training {n:,} Gaussians (SH degree {sh_degree}) on {views} images of {width}x{height} px", advice)


def _root(room: float, per_height2: float) -> int:
    """The largest whole height h with h² per_height2 <= room (0 when none)."""
    return int(math.sqrt(room / per_height2)) if room > 0 and per_height2 > 0 else 0


def estimate_render_memory(n: int, height: int, width: int, sh_degree: int = 3, *, extra_values: int = 0,
                           pairs_per_pixel: float | None = None, compiled: bool = True,
                           threads: int | None = None) -> int:
    """Estimated peak bytes of rendering `n` Gaussians of SH degree `sh_degree` into one image of
    `height` x `width` pixels and writing it as a PNG, with the compiled kernels (`compiled`) or
    the torch renderer, in `threads` threads (default: `parallel.count()`). `pairs_per_pixel`:
    Gaussian-tile pairs per pixel (default RENDER_PAIRS_PER_PIXEL, a dense cloud's)."""
    per_pixel, fixed = _render_terms(n, sh_degree, extra_values, pairs_per_pixel, compiled, threads)
    return int(fixed + per_pixel * int(height) * int(width))


def _render_terms(n: int, sh_degree: int, extra_values: int, pairs_per_pixel: float | None, compiled: bool,
                  threads: int | None) -> tuple[float, float]:
    """(bytes per pixel, bytes besides) of `estimate_render_memory`."""
    kind = "compiled" if compiled else "torch"
    values = 14 + 3 * SH_REST_COUNTS[min(int(sh_degree), 3)] + int(extra_values)
    threads = parallel.count() if threads is None else max(1, int(threads))
    density = RENDER_PAIRS_PER_PIXEL if pairs_per_pixel is None else max(float(pairs_per_pixel), 0.0)
    per_pixel = RENDER_PER_PIXEL + RENDER_PER_PIXEL_PER_THREAD * threads + RENDER_PER_PAIR[kind] * density
    fixed = RENDER_BASE_BYTES + n * (RENDER_PER_GAUSSIAN[kind] + 4 * values + RENDER_PER_PAIR[kind])
    return per_pixel, fixed


def check_render_memory(n: int, height: int, width: int, sh_degree: int = 3, **kwargs) -> int:
    """The estimate of `estimate_render_memory` (same arguments); raises NotEnoughMemoryError when
    it exceeds the memory available now (skipped where that cannot be told), saying the largest
    height (the width in proportion) that would fit."""
    def advice(free: int) -> str:
        per_pixel, fixed = _render_terms(n, sh_degree, kwargs.get("extra_values", 0), kwargs.get("pairs_per_pixel"),
                                         kwargs.get("compiled", True), kwargs.get("threads"))
        fitting = _root(free - fixed, per_pixel * int(width) / max(int(height), 1))
        if fitting < 16:
            return "render a smaller part of the cloud"
        return f"render at most {fitting} px high (--height {fitting})"

    return _check(estimate_render_memory(n, height, width, sh_degree, **kwargs),
                  f"rendering {n:,} Gaussians at {width}x{height} px", advice)


def train_cap(views: int, height: int, width: int, sh_degree: int = 3, available: int | None = None) -> int:
    """The most Gaussians a training stage may grow to on this machine: those whose estimated peak
    (`estimate_train_memory`) fits in TRAIN_MEMORY_SHARE of the memory available now (`available`
    bytes where given), at least 10,000; 10 million where the available memory cannot be told."""
    free = available_memory() if available is None else int(available)
    if free is None:
        return 10_000_000
    values = 14 + 3 * SH_REST_COUNTS[min(int(sh_degree), 3)]
    room = TRAIN_MEMORY_SHARE * free - estimate_train_memory(0, views, height, width, sh_degree)
    return max(10_000, int(room // (values * TRAIN_PER_VALUE)))


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
#: What glibc's own adaptive thresholds grow to once large blocks have been freed (64-bit): blocks
#: from 32 MiB on are mapped, the heap is trimmed past twice that. Set on leaving the scope.
_GROWN_MMAP_THRESHOLD = 32 << 20
_DEFAULT_MMAP_MAX = 65536


def _glibc():
    """The C library when it is glibc (which has mallopt and malloc_trim), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except (OSError, AttributeError):
        return None


class _AllocatorScope:
    """The process's one allocator policy: counted, so that nested scopes (a refine inside a
    larger job) hand memory back only when the outermost one ends."""

    def __init__(self):
        self.depth = 0
        self.lock = threading.Lock()

    @contextlib.contextmanager
    def __call__(self) -> Iterator[bool]:
        libc = _glibc()
        if libc is None:
            yield False
            return
        with self.lock:
            self.depth += 1
            if self.depth == 1:
                libc.mallopt(_M_MMAP_MAX, 0)
                libc.mallopt(_M_TRIM_THRESHOLD, 2 ** 31 - 1)
        try:
            yield True
        finally:
            with self.lock:
                self.depth -= 1
                if self.depth == 0:
                    libc.mallopt(_M_MMAP_MAX, _DEFAULT_MMAP_MAX)
                    libc.mallopt(_M_MMAP_THRESHOLD, _GROWN_MMAP_THRESHOLD)
                    libc.mallopt(_M_TRIM_THRESHOLD, 2 * _GROWN_MMAP_THRESHOLD)
                    libc.malloc_trim(0)


#: Within: arrays freed by the C allocator stay in the process for the next ones (no separate
#: mapping per large block, no trimming), so a sequence of large temporaries -- per-view tile
#: pairs, tables and images of a million Gaussians -- faults its pages in once instead of every
#: time (docs/benchmarks/refine.md has the 1M-Gaussian refine with and without it). When
#: the outermost scope ends, the allocator is set to what its adaptive thresholds grow to anyway
#: and the unused memory is handed back (`malloc_trim`), so nothing stays held. The context value
#: says whether it could act (glibc only; elsewhere the scope does nothing). Process-wide: other
#: threads allocate the same way meanwhile (a matter of speed, never of results).
reuse_freed_memory = _AllocatorScope()
