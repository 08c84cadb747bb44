"""Time left in a training run: what a training job's ETA says (issue 49).

Extrapolating the run's rate so far runs short on a splat run: its steps slow as densification
adds splats (issue 48 saw tqdm's time left go from 3:19 to 7:53 in one run). The clock gives two
numbers after every step:

- `seconds_left`: the steps left at the pace of the last `window` steps: fair once the model
  stops growing (after densification; always for NeRF, whose size is fixed);
- `seconds_left_max`: a bound while the model may still grow: every step left as if the model
  were at its budget already, i.e. the pace times budget / size now. It holds when a step costs
  a + b * size with a, b >= 0 (then a + b * budget <= (a + b * size) * budget / size), which is
  how a rasteriser's work grows with the splats it sorts and blends.

Measured against what the run then took (bench/bench_train_eta.py, docs/gaussians.md).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

WINDOW = 20       # steps the pace is measured over


@dataclass(frozen=True)
class TrainStep:
    """Where a run is, passed to `on_step` after every step."""

    step: int                            # steps done, 1..total
    total: int
    seconds_left: float                  # at the pace of the last steps
    seconds_left_max: float              # the bound while the model may grow (= seconds_left once it cannot)


class TrainClock:
    """Times a run's steps (`tick` after each) and says how long the rest will take (module docstring)."""

    def __init__(self, total: int, *, window: int = WINDOW, now: Callable[[], float] = time.perf_counter):
        self.total = total
        self.now = now
        self.last = now()
        self.seconds: deque[float] = deque(maxlen=window)      # the last steps' durations
        self.per_unit: deque[float] = deque(maxlen=window)     # each divided by the model's size then

    def tick(self, done: int, *, size: int | None = None, budget: int | None = None) -> TrainStep:
        """After `done` steps of `total`. `size`: the model's size now (None: it never changes);
        `budget`: the most it may still grow to (None: it cannot grow any more)."""
        stamp = self.now()
        self.seconds.append(stamp - self.last)
        self.per_unit.append((stamp - self.last) / size if size else 0.0)
        self.last = stamp
        steps_left = self.total - done
        left = sum(self.seconds) / len(self.seconds) * steps_left
        if size is None:
            return TrainStep(done, self.total, left, left)
        # Each timed step bounds a step at the largest size to come by itself (its seconds x that
        # size / its size), also when the model grew inside the window; so does their mean.
        largest = size if budget is None else max(size, budget)
        most = largest * sum(self.per_unit) / len(self.per_unit) * steps_left
        return TrainStep(done, self.total, left, max(left, most))
