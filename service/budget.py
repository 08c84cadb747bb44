"""Memory: one budget (PHD_MEMORY_BUDGET_BYTES) for everything large the service holds, kept by
one `MemoryLedger`: the models in memory, the running jobs and the upload parses.

A model in memory holds MODEL_BYTES_PER_FILE_BYTE x its file size (the loaded tensors are at
most the file for every built-in family, tests/service/test_budget.py) from its load until it is
evicted, and LOAD_BYTES_PER_FILE_BYTE x the file while it is parsed; reading an uploaded
trainer's folder takes READ_BYTES_PER_MODEL_BYTE x what its model inflates to (a checkpoint's
records, not its bytes on disk: service.folders.folder_bytes). The ledger keeps idle models
(at most PHD_CACHE_SIZE, least recently used out first) while nothing else needs their room, and
evicts them when something does; a model a job is using is never evicted. A job takes its models
and its own estimate together or waits for both, so no job holds memory while it waits.

A job's own estimate (`plan_work`) comes from its inputs and, once its models are loaded, from
each render's `RenderMemory` (bounds a model family computes by projecting the model into the
camera: how many splats cover each pixel decides most of it, and no request size tells that):

    masks          samples x units x MASK_SAMPLE_UNIT_BYTES per model (uniform draws, keep-masks)
    + accumulators pixels of the largest view x channels x ACCUMULATOR_CHANNEL_BYTES (the streamed std)
    + kept         what the job keeps across views (references, heat-map peaks, images, and the
                   prepared views calibration re-uses, at most VIEW_CACHE_BYTES)
    + the largest render's fixed part (projection, tile and fragment lists)
    + batch x max(the largest render's per-mask part + pixels x (channels - 3) x 4
                  + pixels x channels x CHUNK_CHANNEL_BYTES, pixels x channels x ENGINE_CHANNEL_BYTES)

where channels are the signal's (3 composited; 4 premultiplied, whose images are one float32
channel larger than the composited ones the families' bounds count).

The masks, accumulators, kept bytes, the engine's per-mask terms and 3DGS's are sums of the
shapes alive at a job's worst moment (the constants beside the code that allocates them:
phd_core.uq.sampling, gs3d/render.py); the families' mask-independent parts, 2DGS's per-mask
term and NeRF's bounds are still measured envelopes (docs/reliability.md, Limits). Resident
memory is what is alive because the service unmaps large blocks as they are freed
(`phd_core.allocator.bounded_heap`) and trims the heap when a reservation ends: the same
request peaks the same in a fresh server and after earlier jobs (bench_memory.py runs one 10
times in a server).

The std is streamed over mask batches (`phd_core.uq.limit_mask_batch`), so N enters through the
masks only: the plan picks the largest batch (<= 64 masks) that fits. It is made twice: before
the job is queued, without the renders (a lower bound: over the budget is a 413 naming the field
to lower), and when a worker takes the job, with them (over the budget: the job fails with that
413). bench/bench_memory.py checks the peaks against the plans.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Sequence

from phd_core.allocator import release_freed_memory
from phd_core.renderers import Renderer, RenderMemory, memory_probe_bytes
from phd_core.uq import MAX_MASKS_PER_RENDER
from phd_core.uq.sampling import CHUNK_CHANNEL_BYTES, ENGINE_CHANNEL_BYTES

from .errors import ServiceError

MODEL_BYTES_PER_FILE_BYTE = 1       # a loaded model over its file (tensors <= the file: 0.88 PLY, 1.00 NeRF)
MODEL_BYTES_OVERHEAD = 1 << 20      # and the objects around them
LOAD_BYTES_PER_FILE_BYTE = 4        # loading: the file read and its parse (ASCII PLY measured 2.5x)
READ_BYTES_PER_MODEL_BYTE = 5       # reading a trainer's folder, over what its model inflates to: the checkpoint's
                                    # tensors, the model moved into the user's frame (float64 temporaries), the PLY
                                    # written from it (1 M splats from a checkpoint: 4.6x through the server)
MASK_SAMPLE_UNIT_BYTES = 5          # a float32 uniform and a keep flag per sample and unit
ACCUMULATOR_CHANNEL_BYTES = 64      # RunningStd's float64 shift, mean, M2 [H, W, C] (24 a channel) and at
                                    # most five [H, W, C] float64 merge terms at once (40); then zeta, the
                                    # mean and the maps measured from them, less
DEFAULT_MASK_PIXEL_BYTES = 8192     # a family that gives no RenderMemory: per mask and pixel, assumed
PNG_PIXEL_BYTES = 8                 # a result image kept as PNG (<= 3 bytes a pixel stored) or its base64 text


def model_bytes(size: int) -> int:
    """What a loaded model of `size` file bytes holds while it stays in memory."""
    return MODEL_BYTES_PER_FILE_BYTE * size + MODEL_BYTES_OVERHEAD


def load_bytes(size: int) -> int:
    """What loading a model of `size` file bytes takes at its peak (always >= model_bytes)."""
    return LOAD_BYTES_PER_FILE_BYTE * size + MODEL_BYTES_OVERHEAD


def taking(amount: int, sizes: Iterable[int]) -> int:
    """What a job of `amount` bytes takes with the models it must load (their file sizes): each
    stays at model_bytes, and a load's parse peak is over before the job's own bytes are used
    (models load one after another, before the work starts)."""
    sizes = list(sizes)
    extra = max((load_bytes(size) - model_bytes(size) for size in sizes), default=0)
    return sum(model_bytes(size) for size in sizes) + max(amount, extra)


def read_bytes(size: int) -> int:
    """What reading a trainer's folder whose model inflates to `size` bytes takes at its peak."""
    return READ_BYTES_PER_MODEL_BYTE * size + MODEL_BYTES_OVERHEAD


def largest_model_file(budget: int, per_byte: int = LOAD_BYTES_PER_FILE_BYTE) -> int:
    """The largest model file whose load fits `budget` (an upload past it is cut off); with
    per_byte READ_BYTES_PER_MODEL_BYTE, the largest model a folder's read fits it with."""
    return max(0, budget - MODEL_BYTES_OVERHEAD) // per_byte


@dataclass(frozen=True)
class ModelSize:
    id: str
    units: int          # dropout units (splats, NeRF first-layer width)
    file_bytes: int
    field: str          # the request field that names the model


@dataclass(frozen=True)
class MemoryPlan:
    bytes: int          # reserved from the budget while the job runs (its models apart)
    mask_batch: int     # masks per render call


def plan_work(models: Sequence[ModelSize], pixels: int, samples: int, kept_bytes: int, budget: int, *,
              renders: RenderMemory | None = None, size_field: str, kept_field: str,
              channels: int = 3) -> MemoryPlan:
    """The memory plan of one job, or a 413 naming the field to lower.

    pixels: of the largest view rendered; kept_bytes: what the job holds across views;
    renders: the largest bounds of the job's renders (None: not known yet, a lower bound);
    channels: of the signal's images (phd_core.renderers.SIGNALS).
    The plan fits beside its models in memory, and each model's load fits beside the others
    (`taking`); a model named twice (select a model against itself) is in memory once but
    draws its masks twice.
    """
    distinct: dict[str, ModelSize] = {}
    for model in models:
        distinct.setdefault(model.id, model)
    resident = sum(model_bytes(m.file_bytes) for m in distinct.values())
    for model in distinct.values():
        need = resident + load_bytes(model.file_bytes) - model_bytes(model.file_bytes)
        if need > budget:
            raise OverBudget(model.field, need, budget, "a smaller model")
    room = budget - resident
    fixed = (sum(MASK_SAMPLE_UNIT_BYTES * samples * m.units for m in models)
             + pixels * channels * ACCUMULATOR_CHANNEL_BYTES)
    # Before the renders are known, the projection that will bound them.
    fixed += renders.fixed if renders is not None else max(memory_probe_bytes(m.units) for m in models)
    if fixed + kept_bytes > room and kept_bytes:
        raise OverBudget(kept_field, resident + fixed + kept_bytes, budget, "fewer cameras or a lower resolution")
    # While a batch renders the engine still holds the previous one's images; its renderer
    # temporaries are gone once its images reach the engine's float64 terms.
    render = (renders.per_mask if renders is not None else 0) + pixels * 4 * (channels - 3)
    per_mask = max(pixels * channels * ENGINE_CHANNEL_BYTES, render + pixels * channels * CHUNK_CHANNEL_BYTES)
    batch = min(MAX_MASKS_PER_RENDER, samples, (room - fixed - kept_bytes) // per_mask)
    if batch < 1:
        raise OverBudget(size_field, resident + fixed + kept_bytes + per_mask, budget,
                          "a lower resolution (downscale, or width/height)")
    return MemoryPlan(bytes=fixed + kept_bytes + batch * per_mask, mask_batch=int(batch))


class OverBudget(ServiceError):
    """A 413: the plan of a request (`need` bytes) exceeds the budget."""

    def __init__(self, field: str, need: int, budget: int, advice: str):
        super().__init__(413, "over_memory_budget", f"this request needs an estimated {need / 2**20:.0f} MiB, "
                         f"above the service's memory budget of {budget / 2**20:.0f} MiB: ask for {advice} "
                         f"(field '{field}')", field)
        self.need, self.budget = need, budget


@dataclass(eq=False)
class Resident:
    """A model in memory: its renderer (None while it loads) and the bytes it holds."""

    bytes: int
    renderer: Renderer | None = None
    users: int = 0                  # jobs using it: never evicted while > 0
    failed: BaseException | None = None
    listed: bool = True             # still findable by id (False once evicted, deleted or failed)


class MemoryLedger:
    """The budget shared by models in memory, running jobs and upload parses: reserve before,
    release after, and evict idle models (least recently used first) for room."""

    def __init__(self, budget: int, capacity: int, load: Callable[[str], Renderer]):
        self.budget = budget
        self.capacity = capacity        # idle models kept at most
        self.load = load                # a model by id, from where the models are stored
        self.used = 0
        self._models: OrderedDict[str, Resident] = OrderedDict()   # least recently used first
        self._cond = threading.Condition()

    @contextmanager
    def reserve(self, amount: int, timeout: float | None = None) -> Iterator["Reservation"]:
        """Hold `amount` bytes for the block; waits while they do not fit even with idle models
        evicted. Raises TimeoutError after `timeout` seconds without room (None: no limit)."""
        self._check(amount, {})
        self._take({}, amount, timeout)
        reservation = Reservation(self, amount)
        try:
            yield reservation
        finally:
            self._give({}, reservation.amount)

    @contextmanager
    def models(self, records: dict[str, int], amount: int,
               timeout: float | None = None) -> Iterator[dict[str, Renderer]]:
        """The renderers of the models `records` ({id: file bytes}), in memory for the block,
        and `amount` bytes more, taken together. A model not in memory is loaded with
        `self.load(id)` (its load bytes reserved with the rest, then lowered to what it keeps).
        Raises TimeoutError as `reserve` does; what the load raises, in every job waiting on it."""
        self._check(amount, records)
        held, loading, taken = self._take(records, amount, timeout)
        try:
            for model_id, resident in loading.items():
                self._load(model_id, resident)
            with self._cond:                          # the parse peaks are over: down to the job's own bytes
                self.used -= taken - amount
                taken = amount
                self._cond.notify_all()
            yield {model_id: self._loaded(resident) for model_id, resident in held.items()}
        finally:
            self._give(held, taken)

    def forget(self, model_id: str) -> None:
        """A deleted model: out now if idle, else once its last job is done."""
        with self._cond:
            resident = self._models.pop(model_id, None)
            if resident is not None:
                resident.listed = False
                if resident.users == 0:
                    self.used -= resident.bytes
                self._cond.notify_all()

    def loaded(self) -> list[str]:
        """The ids of the models in memory, least recently used first."""
        with self._cond:
            return [model_id for model_id, r in self._models.items() if r.renderer is not None]

    def _check(self, amount: int, records: dict[str, int]) -> None:
        """What can never fit is a caller's error (plans are checked against the budget first)."""
        if taking(amount, records.values()) > self.budget:
            raise ValueError(f"{amount} bytes and the models {list(records)} exceed the budget of {self.budget}")

    # ------------------------------------------------------------------ under the lock

    def _take(self, records: dict[str, int], amount: int,
              timeout: float | None) -> tuple[dict[str, Resident], dict[str, Resident], int]:
        """Wait until `amount` and every model not in memory fit (`taking`), then take them all
        at once: (the residents held, those this call must load, the bytes taken beyond them)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                missing = {i: size for i, size in records.items() if i not in self._models}
                need = taking(amount, missing.values())
                self._evict(self.used + need - self.budget, keep=records)
                if self.used + need <= self.budget:
                    break
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0 or not self._cond.wait(remaining):
                    raise TimeoutError(f"{self.used} of {self.budget} bytes are reserved")
            self.used += need
            loading = {i: Resident(model_bytes(size)) for i, size in missing.items()}
            self._models.update(loading)
            held = {i: self._models[i] for i in records}
            for model_id, resident in held.items():
                resident.users += 1
                self._models.move_to_end(model_id)
            return held, loading, need - sum(r.bytes for r in loading.values())

    def _give(self, held: dict[str, Resident], amount: int) -> None:
        """Release `amount` and the models held (a model no longer listed goes with its last
        user), and give what the work freed back to the system: the budget counts resident memory."""
        with self._cond:
            self.used -= amount
            for resident in held.values():
                resident.users -= 1
                if resident.users == 0 and not resident.listed:
                    self.used -= resident.bytes
            self._cap_idle()
            self._cond.notify_all()
        release_freed_memory()

    def _evict(self, need: int, keep: dict[str, int] | None = None) -> None:
        """Evict idle loaded models, least recently used first, until `need` bytes are free."""
        for model_id, resident in list(self._models.items()):
            if need <= 0:
                return
            if resident.users == 0 and resident.renderer is not None and model_id not in (keep or {}):
                del self._models[model_id]
                resident.listed = False
                self.used -= resident.bytes
                need -= resident.bytes

    def _cap_idle(self) -> None:
        """Evict the least recently used idle models past `capacity`."""
        idle = [i for i, r in self._models.items() if r.users == 0 and r.renderer is not None]
        for model_id in idle[:max(0, len(idle) - self.capacity)]:
            resident = self._models.pop(model_id)
            resident.listed = False
            self.used -= resident.bytes

    # ------------------------------------------------------------------ loading (outside the lock)

    def _load(self, model_id: str, resident: Resident) -> None:
        try:
            renderer = self.load(model_id)
        except BaseException as exc:
            with self._cond:
                resident.failed = exc
                if self._models.get(model_id) is resident:
                    del self._models[model_id]
                resident.listed = False
                self._cond.notify_all()
            raise
        with self._cond:
            resident.renderer = renderer
            self._cond.notify_all()

    def _loaded(self, resident: Resident) -> Renderer:
        """The renderer once loaded (by this job or another one waiting on the same model)."""
        with self._cond:
            self._cond.wait_for(lambda: resident.renderer is not None or resident.failed is not None)
            if resident.failed is not None:
                raise resident.failed
            assert resident.renderer is not None       # what wait_for waited for, with no failure
            return resident.renderer


class Reservation:
    """Bytes held from a ledger for a block (`MemoryLedger.reserve`)."""

    def __init__(self, ledger: MemoryLedger, amount: int):
        self.ledger, self.amount = ledger, amount

    def keep(self, model_id: str, renderer: Renderer, size: int) -> None:
        """Hand part of these bytes to a model loaded in the block (an upload's parse becomes
        the model in memory; nothing is reserved anew, so nothing waits): it stays in memory
        as an idle model once the block ends. A model the bytes cannot hold is not kept."""
        ledger, need = self.ledger, model_bytes(size)
        with ledger._cond:
            if model_id in ledger._models or need > self.amount:
                return
            self.amount -= need
            ledger._models[model_id] = Resident(need, renderer)
            ledger._cap_idle()
