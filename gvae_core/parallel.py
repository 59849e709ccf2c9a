"""CPU work in threads: how many, and the runners every compiled path and numpy loop shares.

Compiled kernels (Numba, `nogil`) and large numpy operations release the GIL, so plain threads run
them on all cores; nothing global is set (no threading layer of Numba's, no numpy or BLAS
settings). The count is torch's intra-op count when torch is loaded, which is what its own
operations use, so `torch.set_num_threads` governs all CPU work of a process.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: Rows below which `in_threads` runs in the calling thread (a thread costs more than it saves).
MIN_ROWS_PER_THREAD = 1 << 15


def count() -> int:
    """How many threads CPU work may use: torch's intra-op count when torch is loaded, else the
    CPUs this process may run on."""
    torch = sys.modules.get("torch")
    if torch is not None and hasattr(torch, "get_num_threads"):
        return max(1, int(torch.get_num_threads()))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def run(tasks: list[Callable], name: str = "gvae") -> list:
    """[task() for task in tasks], in `count()` threads when there are several (for work that
    releases the GIL: compiled kernels, large numpy operations)."""
    n = min(count(), len(tasks))
    if n <= 1:
        return [t() for t in tasks]
    with ThreadPoolExecutor(n, thread_name_prefix=name) as pool:
        return list(pool.map(lambda t: t(), tasks))


def split(cost: np.ndarray, parts: int) -> list[tuple[int, int]]:
    """Consecutive ranges of indices of about equal total `cost` (at most `parts`, none empty)."""
    n = len(cost)
    if n == 0:
        return []
    cum = np.cumsum(cost, dtype=np.float64)
    bounds = np.searchsorted(cum, cum[-1] * np.arange(1, parts) / parts, side="right")
    edges = np.unique(np.concatenate([[0], np.clip(bounds, 0, n), [n]]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def chunks(n: int, work: float, small: float) -> list[tuple[int, int]]:
    """Ranges of n items of about equal size doing `work` in all: one range when the work is below
    `small` (a thread costs more than it saves) or there is one thread, else four per thread."""
    parts = 1 if work < small or count() == 1 else 4 * count()
    return split(np.ones(n), min(parts, max(n, 1)))


def in_threads(n: int, fn: Callable[[int, int], object], *, threads: int | None = None,
               chunk: int = 1 << 16) -> list:
    """[fn(a, b) for consecutive ranges a..b covering 0..n], the ranges run in `threads` threads
    (default `count()`), about `chunk` rows each so that their temporaries stay in cache. For
    work whose result per row depends on that row alone (numpy operations and compiled kernels
    that release the GIL): the result is what fn(0, n) gives (bit for bit where the work is elementwise)."""
    threads = count() if threads is None else max(1, int(threads))
    parts = max(1, -(-n // max(1, chunk)))
    edges = [n * i // parts for i in range(parts + 1)]
    ranges = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    if threads == 1 or len(ranges) <= 1 or n < 2 * MIN_ROWS_PER_THREAD:
        return [fn(a, b) for a, b in ranges]
    with ThreadPoolExecutor(min(threads, len(ranges)), thread_name_prefix="gvae-rows") as pool:
        return list(pool.map(lambda ab: fn(*ab), ranges))
