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


GIB = 1 << 30


def test_a_render_too_large_is_refused_saying_the_height_that_fits(monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: 2 * GIB)
    with pytest.raises(resources.NotEnoughMemoryError) as refused:
        resources.check_render_memory(10_000, 20_000, 30_000, 3, threads=4)
    message = str(refused.value)
    assert "rendering 10,000 Gaussians at 30000x20000 px needs about" in message and "only 2.0 GiB" in message
    fits = int(message.split("--height ")[1].split(")")[0])
    assert resources.estimate_render_memory(10_000, fits, fits * 3 // 2, 3, threads=4) <= 2 * GIB
    assert resources.estimate_render_memory(10_000, fits + 2, (fits + 2) * 3 // 2, 3, threads=4) > 2 * GIB
    assert resources.check_render_memory(10_000, 400, 600, 3, threads=4) < 2 * GIB  # a normal size passes


def test_the_render_estimate_grows_with_what_it_holds():
    base = resources.estimate_render_memory(100_000, 1000, 1000, 3, threads=2)
    assert resources.estimate_render_memory(100_000, 2000, 2000, 3, threads=2) > 3 * (base - (1 << 30))
    assert resources.estimate_render_memory(100_000, 1000, 1000, 3, threads=2, pairs_per_pixel=1.0) < base
    assert resources.estimate_render_memory(100_000, 1000, 1000, 3, threads=2, compiled=False) > base
    assert resources.estimate_render_memory(100_000, 1000, 1000, 3, threads=16) > base


def test_a_training_stage_too_large_is_refused_saying_what_would_fit(monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: 4 * GIB)
    with pytest.raises(resources.NotEnoughMemoryError) as refused:
        resources.check_train_memory(500_000, 30, 1200, 1600, 3)
    message = str(refused.value)
    assert "training 500,000 Gaussians (SH degree 3) on 30 images of 1600x1200 px needs about" in message
    height = int(message.split("--image-height ")[1].split()[0])
    count = int(message.split("at most ")[1].split()[0].replace(",", ""))
    assert resources.estimate_train_memory(500_000, 30, height, height * 4 // 3) <= 4 * GIB
    assert resources.estimate_train_memory(count, 30, 1200, 1600) <= 4 * GIB < resources.estimate_train_memory(
        count + 1000, 30, 1200, 1600)
    assert resources.check_train_memory(50_000, 80, 200, 300) < 4 * GIB  # a normal stage passes


def test_memory_checks_pass_where_the_memory_free_cannot_be_told(monkeypatch):
    monkeypatch.setattr(resources, "available_memory", lambda: None)
    assert resources.check_render_memory(10_000, 10 ** 6, 10 ** 6) > 1 << 40
    assert resources.check_train_memory(10 ** 8, 1000, 4000, 6000) > 1 << 40
