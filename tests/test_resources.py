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
