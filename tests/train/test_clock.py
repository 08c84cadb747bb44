"""The training clock (`phd_core.train.clock`): its time left against the simulated run's own
remaining time, computed step by step."""

from __future__ import annotations

import pytest

from phd_core.train.clock import TrainClock


class FakeTime:
    """A clock that moves only when told."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_at_a_steady_pace_the_time_left_is_exact_and_the_bound_equals_it() -> None:
    now = FakeTime()
    clock = TrainClock(50, now=now)
    for done in range(1, 51):
        now.t += 0.25
        at = clock.tick(done)
        assert at.seconds_left == pytest.approx(0.25 * (50 - done))
        assert at.seconds_left_max == at.seconds_left


def test_the_pace_is_the_last_window_of_steps() -> None:
    now = FakeTime()
    clock = TrainClock(100, window=10, now=now)
    for done in range(1, 31):
        now.t += 1.0 if done <= 20 else 3.0           # the steps slowed at step 21
        at = clock.tick(done)
    assert at.seconds_left == pytest.approx(3.0 * 70)


@pytest.mark.parametrize("fixed, per_unit", [(0.0, 1e-4), (0.05, 1e-5), (0.2, 0.0)])
def test_while_the_model_grows_the_bound_holds_and_the_estimate_is_exact_once_it_stops(fixed, per_unit) -> None:
    """A splat run as densification drives it at its fastest: doubling after every 100th step up to
    the budget until step 600 of 1,000, each step costing `fixed + per_unit * size` (affine, non-negative)."""
    total, budget, until = 1000, 30_000, 600
    grows_at = [step for step in range(1, until) if step % 100 == 0]
    sizes = []
    size = 1_000
    for step in range(total):
        sizes.append(size)                          # the step runs at this size, then densification
        if step in grows_at:
            size = min(budget, 2 * size)
    costs = [fixed + per_unit * s for s in sizes]
    now = FakeTime()
    clock = TrainClock(total, grows_at=grows_at, budget=budget, now=now)
    for done in range(1, total + 1):
        now.t += costs[done - 1]
        at = clock.tick(done, size=sizes[min(done, total - 1)])     # after the step's densification
        actual = sum(costs[done:])
        assert at.seconds_left_max >= actual - 1e-9
        if fixed == 0 and done >= 20:               # cost in proportion to size: the bound is the run itself
            assert at.seconds_left_max == pytest.approx(actual)
        if done >= until + 20:                      # a whole window after the last growth
            assert at.seconds_left == pytest.approx(actual)
            assert at.seconds_left_max == pytest.approx(at.seconds_left)
