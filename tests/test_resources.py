"""The allocator scope of capture-scale work: freed memory is kept while it lasts and handed back
when the outermost scope ends."""

import numpy as np
import pytest

from gvae_core import resources


def _resident() -> int:
    with open("/proc/self/statm", encoding="ascii") as fh:
        return int(fh.read().split()[1]) * 4096


def _touch_and_free(mib: int) -> None:
    a = np.ones(mib << 18, np.float32)  # mib MiB, every page written
    assert a[-1] == 1.0
    del a


def test_freed_memory_is_kept_in_the_scope_and_handed_back_after_it():
    with resources.reuse_freed_memory() as active:
        if not active:
            pytest.skip("glibc's allocator only (the scope does nothing elsewhere)")
        base = _resident()
        _touch_and_free(256)
        with resources.reuse_freed_memory():  # nested: ending it hands nothing back yet
            _touch_and_free(256)
        kept = _resident() - base
    after = _resident() - base
    assert kept > 200 << 20, kept >> 20
    assert after < 64 << 20, after >> 20
    assert resources.reuse_freed_memory.depth == 0


def test_the_scope_does_nothing_without_glibc(monkeypatch):
    monkeypatch.setattr(resources, "_glibc", lambda: None)
    with resources.reuse_freed_memory() as active:
        assert active is False
        _touch_and_free(8)


@pytest.mark.parametrize("n", [0, 5, 70_000, 200_003])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_in_threads_is_the_work_done_at_once(n, threads):
    """Rows split into ranges run in threads give what one call over all of them gives, every row
    once (elementwise numpy work: bit for bit)."""
    x = np.random.default_rng(n).normal(size=(n, 3))
    out = np.full(n, np.nan)
    calls = []

    def work(a, b):
        calls.append((a, b))
        out[a:b] = np.log1p(np.abs(x[a:b])).sum(1) / (x[a:b, 0] ** 2 + 1.0)
        return b - a

    sizes = resources.in_threads(n, work, threads=threads, chunk=4096)
    assert sum(sizes) == n and sorted(calls) == calls_sorted(calls) and not np.isnan(out).any()
    np.testing.assert_array_equal(out, np.log1p(np.abs(x)).sum(1) / (x[:, 0] ** 2 + 1.0))
    assert len(calls) == (0 if n == 0 else max(1, -(-n // 4096)))
    assert resources.cpu_threads() >= 1


def calls_sorted(calls):
    """The ranges in order, each starting where the one before ended."""
    ranges = sorted(calls)
    assert all(b0 == a1 for (_, b0), (a1, _) in zip(ranges[:-1], ranges[1:]))
    return ranges
