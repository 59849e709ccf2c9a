"""`gvae_core.parallel`: the thread runners every compiled path and numpy loop shares."""

import numpy as np
import pytest

from gvae_core import parallel


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

    sizes = parallel.in_threads(n, work, threads=threads, chunk=4096)
    assert sum(sizes) == n and sorted(calls) == calls_sorted(calls) and not np.isnan(out).any()
    np.testing.assert_array_equal(out, np.log1p(np.abs(x)).sum(1) / (x[:, 0] ** 2 + 1.0))
    assert len(calls) == (0 if n == 0 else max(1, -(-n // 4096)))
    assert parallel.count() >= 1


def calls_sorted(calls):
    """The ranges in order, each starting where the one before ended."""
    ranges = sorted(calls)
    assert all(b0 == a1 for (_, b0), (a1, _) in zip(ranges[:-1], ranges[1:]))
    return ranges


@pytest.mark.parametrize("parts", [1, 2, 5, 64])
def test_split_covers_every_index_once_in_ranges_of_about_equal_cost(parts):
    cost = np.random.default_rng(parts).exponential(size=1000)
    ranges = parallel.split(cost, parts)
    assert ranges[0][0] == 0 and ranges[-1][1] == 1000 and len(ranges) <= parts
    assert all(b0 == a1 and a1 < b1 for (_, b0), (a1, b1) in zip(ranges[:-1], ranges[1:]))
    sums = [cost[a:b].sum() for a, b in ranges]
    assert max(sums) <= cost.sum() / len(ranges) + cost.max()
    assert parallel.split(np.zeros(0), 4) == []


def test_run_returns_each_task_result_in_order():
    assert parallel.run([lambda i=i: i * i for i in range(9)]) == [i * i for i in range(9)]
    assert parallel.run([]) == []
