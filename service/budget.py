"""Memory: every unit of work gets an estimate from its inputs BEFORE it is queued, and runs
only while its estimate is reserved from one budget shared by all workers and upload parsing.

    estimate = model in memory + pixels of the largest view x (accumulators + masks per render
               call x bytes per mask and pixel) + what the work keeps (calibration references)

The std is streamed over mask batches (`phd_core.uq.limit_mask_batch`), so N never enters:
the plan picks the largest batch (<= 64 masks) that fits the budget. Work whose single-mask
estimate exceeds the budget is refused with 413 naming the request field to lower. The per
mask-pixel costs were measured with bench/bench_reliability.py (peak RSS of one render call;
docs/reliability.md): they are upper envelopes of those measurements, not exact.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

from phd_core.uq import MAX_MASKS_PER_RENDER

from .errors import ServiceError

ACCUMULATOR_PIXEL_BYTES = 160       # float64 shift, mean, M2, one chunk's offsets per channel; float32 maps
MODEL_BYTES_PER_FILE_BYTE = 4       # a loaded model and its per-view projections over its file size
SPLAT_MASK_PIXEL_BYTES = 2          # 3DGS: fragments grow with the splats a pixel sees (capped below)
SPLAT_DEPTH_CAP = 8192
MASK_PIXEL_BYTES = {"3dgs": 512, "nerf": 6144}        # renderer temporaries per mask and pixel
DEFAULT_MASK_PIXEL_BYTES = 8192     # a family without a measurement: assume the worst measured
PARSE_BYTES_PER_FILE_BYTE = 4       # upload parse peak over the file size (ASCII PLY measured 2.1x)


def mask_pixel_bytes(kind: str, units: int) -> int:
    if kind == "3dgs":
        return MASK_PIXEL_BYTES["3dgs"] + SPLAT_MASK_PIXEL_BYTES * min(units, SPLAT_DEPTH_CAP)
    return MASK_PIXEL_BYTES.get(kind, DEFAULT_MASK_PIXEL_BYTES)


@dataclass(frozen=True)
class MemoryPlan:
    bytes: int          # reserved from the budget while the work runs
    mask_batch: int     # masks per render call


def plan_work(models: list[tuple[str, int, int]], view_pixels: int, samples: int, kept_bytes: int, budget: int,
              *, size_field: str, kept_field: str) -> MemoryPlan:
    """The memory plan of one job over `models` [(kind, units, file bytes)], or 413 naming what to lower.

    view_pixels: pixels of the largest view; kept_bytes: what the work holds across views.
    """
    fixed = sum(MODEL_BYTES_PER_FILE_BYTE * size for _, _, size in models)
    fixed += view_pixels * ACCUMULATOR_PIXEL_BYTES
    if kept_bytes and fixed + kept_bytes > budget:
        raise over_budget(kept_field, fixed + kept_bytes, budget, "fewer cameras or a lower resolution")
    per_mask = view_pixels * max(mask_pixel_bytes(kind, units) for kind, units, _ in models)
    room = budget - fixed - kept_bytes
    batch = min(MAX_MASKS_PER_RENDER, samples, room // per_mask if per_mask else MAX_MASKS_PER_RENDER)
    if batch < 1:
        raise over_budget(size_field, fixed + kept_bytes + per_mask, budget,
                          "a lower resolution (downscale, or width/height)")
    return MemoryPlan(bytes=fixed + kept_bytes + batch * per_mask, mask_batch=int(batch))


def over_budget(field: str, need: int, budget: int, advice: str) -> ServiceError:
    return ServiceError(413, "over_memory_budget", f"this request needs an estimated {need / 2**20:.0f} MiB, "
                        f"above the service's memory budget of {budget / 2**20:.0f} MiB: ask for {advice} "
                        f"(field '{field}')", field)


class MemoryLedger:
    """The budget shared by every worker and upload parse: reserve before, release after."""

    def __init__(self, budget: int):
        self.budget = budget
        self.used = 0
        self._cond = threading.Condition()

    @contextmanager
    def reserve(self, amount: int, timeout: float | None = None) -> Iterator[None]:
        """Hold `amount` bytes of the budget for the block; waits while others hold too much.

        Raises TimeoutError after `timeout` seconds without room (None: wait as long as it takes).
        """
        amount = min(amount, self.budget)
        with self._cond:
            if not self._cond.wait_for(lambda: self.used + amount <= self.budget, timeout):
                raise TimeoutError(f"{self.used} of {self.budget} bytes are reserved")
            self.used += amount
        try:
            yield
        finally:
            with self._cond:
                self.used -= amount
                self._cond.notify_all()
