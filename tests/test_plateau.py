"""The plateau rule (`gvae_core.plateau`): when a measured value stops rising."""

import math

import pytest

from gvae_core.plateau import Plateau


def test_stops_after_patience_without_a_gain():
    rule = Plateau(patience=300, min_gain=0.1)
    # rises by 0.5 a check until step 400, then creeps up by less than min_gain in all
    values = [(100, 20.0), (200, 20.5), (300, 21.0), (400, 21.5), (500, 21.55), (600, 21.58), (700, 21.59)]
    said = [rule.update(step, v) for step, v in values]
    assert said == [False] * 6 + [True]
    assert rule.best == 21.5 and rule.best_step == 400 and rule.stopped and "300 steps" in rule.reason


def test_small_gains_count_once_they_add_up():
    rule = Plateau(patience=200, min_gain=0.1)
    steps = [(100 * i, 20.0 + 0.06 * i) for i in range(1, 12)]  # 0.06 a check: every second check is a gain
    assert not any(rule.update(s, v) for s, v in steps)
    assert rule.best_step == 1100 and rule.best == pytest.approx(20.66)


def test_lower_is_better_and_bad_values():
    rule = Plateau(patience=2, min_gain=0.0, higher_is_better=False)
    assert not rule.update(0, 1.0)
    assert not rule.update(1, math.nan)  # recorded, never a gain
    assert not rule.update(2, 0.5)
    assert rule.best == 0.5 and rule.history[1][0] == 1
    assert not rule.update(3, 0.7) and rule.update(4, 0.6)
    with pytest.raises(ValueError, match="before the last"):
        rule.update(3, 0.1)
    with pytest.raises(ValueError, match="patience"):
        Plateau(patience=0)
    with pytest.raises(ValueError, match="min_gain"):
        Plateau(min_gain=-1.0)
