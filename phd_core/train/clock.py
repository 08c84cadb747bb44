"""Time left in a training run: what a training job's ETA says (issue 49).

Extrapolating the run's rate so far runs short on a splat run: its steps slow as densification
adds splats (issue 48 saw tqdm's time left go from 3:19 to 7:53 in one run). The clock gives two
numbers after every step:

- `seconds_left`: the steps left at the pace of the last `window` steps: fair once the model
  stops growing (after densification; always for NeRF, whose size is fixed);
- `seconds_left_max`: a bound while the model may still grow: each step left priced at the
  largest size the model can have by then. Densification at most doubles the splats at each of
  its steps (`grows_at`; every grown splat adds one) and never passes the budget, so the size at
  a later step is at most min(budget, size now x 2^(densifications before it)). A step's price at
  a size is the recent steps' seconds per splat times that size: an upper bound when a step costs
  a + b * size with a, b >= 0 (then a + b * S <= (a + b * s) * S / s for S >= s), which is how a
  rasteriser's work grows with the splats it sorts and blends.

Measured against what the run then took (bench/bench_train_eta.py, docs/gaussians.md).
"""

from __future__ import annotations

import bisect
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Sequence

WINDOW = 20       # steps the pace is measured over


@dataclass(frozen=True)
class TrainStep:
    """Where a run is, passed to `on_step` after every step."""

    step: int                            # steps done, 1..total
    total: int
    seconds_left: float                  # at the pace of the last steps
    seconds_left_max: float              # the bound while the model may grow (= seconds_left once it cannot)


class TrainClock:
    """Times a run's steps (`tick` after each) and says how long the rest will take (module docstring).
    `grows_at`: the steps after which the model may grow (at most doubling), up to `budget`."""

    def __init__(self, total: int, *, grows_at: Sequence[int] = (), budget: int | None = None,
                 window: int = WINDOW, now: Callable[[], float] = time.perf_counter):
        self.total = total
        self.grows_at = sorted(grows_at)
        self.budget = budget
        self.now = now
        self.last = now()
        self.seconds: deque[float] = deque(maxlen=window)      # the last steps' durations
        self.per_unit: deque[float] = deque(maxlen=window)     # each divided by the size it ran at
        self.ran_at: int | None = None                          # the size the next step runs at

    def tick(self, done: int, *, size: int | None = None) -> TrainStep:
        """After `done` steps of `total`; `size`: the model's size now (None: it never changes)."""
        stamp = self.now()
        self.seconds.append(stamp - self.last)
        ran_at = self.ran_at or size          # the model may have grown after the step, before this tick
        self.per_unit.append((stamp - self.last) / ran_at if ran_at else 0.0)
        self.last, self.ran_at = stamp, size
        left = sum(self.seconds) / len(self.seconds) * (self.total - done)
        if size is None:
            return TrainStep(done, self.total, left, left)
        most = sum(self.per_unit) / len(self.per_unit) * self.largest_sizes(done, size)
        return TrainStep(done, self.total, left, max(left, most))

    def largest_sizes(self, done: int, size: int) -> float:
        """The sum over the steps left (done .. total - 1) of the largest size each may run at."""
        cap = max(size, self.budget or 0)
        total, start, current = 0.0, done, size
        for step in self.grows_at[bisect.bisect_left(self.grows_at, done):]:
            if current >= cap:
                break
            total += (step + 1 - start) * current          # steps start .. step run at `current`
            start, current = step + 1, min(cap, 2 * current)
        return total + (self.total - start) * current
