"""Budgets: which Gaussians refinement spends its effort on, and what users may type."""

import numpy as np
import pytest

from gvae_core.budget import _top_rows, otsu_threshold, parse_budget, select_budget


def test_budget_selection():
    scores = np.array([5.0, 1.0, 9.0, 3.0, 7.0, 0.0, 2.0, 8.0])
    np.testing.assert_array_equal(select_budget(scores, "all"), np.arange(8))
    np.testing.assert_array_equal(select_budget(scores, 3), [2, 4, 7])
    np.testing.assert_array_equal(select_budget(scores, 0.25), [2, 7])
    assert len(select_budget(scores, 100)) == 8 and len(select_budget(scores, 0)) == 0
    assert len(select_budget(scores, 0.01)) == 1
    for bad in (-1, 1.5, "most", True, None):
        with pytest.raises(ValueError):
            select_budget(scores, bad)
    # auto: a clear high-score mode is found, within 1%..50% of the rows
    rng = np.random.default_rng(0)
    bimodal = np.r_[rng.normal(1, 0.2, 900), rng.normal(6, 0.3, 100)]
    auto = select_budget(bimodal, "auto")
    assert set(auto.tolist()) == set(range(900, 1000))
    assert 10 <= len(select_budget(rng.uniform(size=1000), "auto")) <= 500
    unimodal = rng.normal(10, 4, 10000)  # no separate mode: the upper tail beyond one robust sigma
    assert 1000 < len(select_budget(unimodal, "auto")) < 2500
    assert len(select_budget(np.zeros(50), "auto")) == 1
    assert 1.0 < otsu_threshold(bimodal) < 6.0


def test_parse_budget_is_what_users_type():
    assert parse_budget("10%") == 0.1 and parse_budget("0.2") == 0.2 and parse_budget("500") == 500
    assert parse_budget("ALL") == "all" and parse_budget("") == parse_budget(" auto ") == "auto"
    assert parse_budget("1") == 1 and parse_budget("1.0") == 1.0
    for bad in ("lots", "0", "-3", "0%", "0.0", "150%", "1e3"):  # nothing selected, or out of range
        with pytest.raises(ValueError, match="budget"):
            parse_budget(bad)


def test_top_rows_matches_a_stable_sort():
    rng = np.random.default_rng(3)
    for n in (1, 7, 100, 1000):
        scores = rng.integers(0, 5, n).astype(np.float64)  # many ties
        order = np.argsort(-scores, kind="stable")
        for count in (0, 1, n // 3, n - 1, n, n + 5):
            np.testing.assert_array_equal(_top_rows(scores, count), np.sort(order[:count]))
