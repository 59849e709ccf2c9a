"""Will a refine fit in memory? An estimate of its peak from the cloud's size, and the memory free.

`refine` calls `check_refine_memory` before any work, so a cloud too large for the machine is
refused at once with the estimate in the message, instead of being killed (or swapping the
machine to a halt) minutes later. The estimate is linear in the counts it depends on, with the
coefficients measured by `python -m gvae_core.benchmarks refine` (which prints the estimate
beside the measured peak), rounded up. numpy only.
"""

from __future__ import annotations

import os
import sys

from .conventions import SH_REST_COUNTS

__all__ = ["NotEnoughMemoryError", "available_memory", "estimate_refine_memory", "check_refine_memory"]

#: Bytes of the Python process with torch and the models loaded, before any cloud.
BASE_BYTES = 600 << 20
#: Bytes per Gaussian, per float32 value it holds (14 + 3 K for SH rest K, plus its extra
#: properties): the input, its checked copy and the output cloud.
PER_VALUE = 3 * 4
#: Bytes per Gaussian of the Hessian scoring (Morton-ordered copy, float64 blocks and moments,
#: per-view projection, tile pairs and tables).
HESSIAN_PER_GAUSSIAN = 1500
#: Bytes per pixel of one scoring view (per-tile transmittance, colour, blocks of the sweep).
HESSIAN_PER_PIXEL = 400
#: Bytes per lineage given to the models, per step (features, model activations, children).
MODEL_PER_LINEAGE = 4000
#: Measured (`python -m gvae_core.benchmarks refine`, example clouds, SH degree 3, budget auto,
#: three refines in one process): peaks of 0.74 GiB at 100k Gaussians, 2.40 GiB at 1M, 5.3 GiB at
#: 3M; with the counts the budget selected these give 0.82, 2.67 and 6.8 GiB (3.1 GiB for 1M before
#: scoring, when half the cloud is the most 'auto' can select).


class NotEnoughMemoryError(ValueError):
    """A refine that would need more memory than the machine has free (the message says how much)."""


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
                           steps: int = 1, scoring: bool = True) -> int:
    """Estimated peak bytes of `refine` on `n` Gaussians of SH degree `sh_degree` with
    `extra_values` extra float properties each: scoring over `views` views of `resolution` pixels
    high (`width` wide, default square), then `steps` model steps on `selected` lineages (default:
    half the cloud, the most the 'auto' budget takes)."""
    k = SH_REST_COUNTS[min(int(sh_degree), 3)]
    values = 14 + 3 * k + int(extra_values)
    hessian = 0
    if scoring:
        pixels = int(resolution) * int(width or resolution)
        hessian = n * HESSIAN_PER_GAUSSIAN + pixels * HESSIAN_PER_PIXEL
    lineages = (n + 1) // 2 if selected is None else int(selected)
    model = lineages * MODEL_PER_LINEAGE * min(int(steps), 2)  # later steps: the lineages that grew
    # scoring is over (its buffers freed) before the models run: the peak is the larger of the two
    return int(BASE_BYTES + n * values * PER_VALUE + max(hessian, model))


def _gib(b: int) -> str:
    return f"{b / (1 << 30):.1f} GiB"


def check_refine_memory(n: int, sh_degree: int = 3, **kwargs) -> int:
    """The estimate of `estimate_refine_memory`; raises NotEnoughMemoryError when it exceeds the
    memory available now (skipped where that cannot be told)."""
    need = estimate_refine_memory(n, sh_degree, **kwargs)
    free = available_memory()
    if free is not None and need > free:
        raise NotEnoughMemoryError(
            f"refining {n:,} Gaussians (SH degree {sh_degree}) needs about {_gib(need)} of memory, but only "
            f"{_gib(free)} is available; refine a smaller part of the cloud (or a lower SH degree), use a smaller "
            f"budget or fewer/smaller Hessian views, or close other programs")
    return need
