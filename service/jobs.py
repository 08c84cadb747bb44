"""A bounded pool of worker threads that runs PH-Dropout work as jobs.

Every calibrate/rank/select request becomes a `JobRecord`; a synchronous request simply
awaits its job's future. `workers` threads take jobs from a waiting line of at most
`queue_size` jobs; a submission past that raises `QueueFull` (the API answers 429 with
Retry-After) instead of waiting. Cancelling a waiting job removes it from the line;
cancelling a running job sets a flag that the engine's progress callback checks between
views, raising `JobCancelled` inside the engine. Every state change is handed to `on_change`
(the service persists it, `service.jobstore`); once a final state is persisted, the job's
result and artefacts leave memory (`on_disk`: they are served from the store, so finished
jobs hold no memory outside the budget). The last `retention` finished jobs are remembered.
A shutdown fails unfinished jobs with the code `interrupted`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import traceback
import uuid
from collections import OrderedDict, deque
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

from .errors import ServiceError, from_exception
from .jobstore import FINAL_STATES, INTERRUPTED
from .schemas import Job
from .store import utc_now

log = logging.getLogger("phd.service")


class JobProgress(Protocol):
    """What a job's work reports through: the fraction done and, where the work can tell, its
    seconds left (an estimate and a bound, `phd_core.train.clock`; None: not known)."""

    def __call__(self, fraction: float, eta: tuple[float, float] | None = None) -> None: ...


# A job's work: gets a progress callback, returns (result, artefacts by name).
Work = Callable[[JobProgress], tuple[Any, dict[str, bytes]]]


class QueueFull(Exception):
    """The waiting line is full."""


class JobCancelled(Exception):
    """Raised from the progress callback to stop a job that was cancelled."""


@dataclass
class JobRecord:
    id: str
    kind: str
    work: Work
    estimated_pixels: float
    owner: str | None = None                 # the API key name that submitted it (None: no keys)
    state: str = "queued"
    progress: float = 0.0
    eta: tuple[float, float] | None = None   # seconds left: estimate, bound (the work's last word)
    created_at: str = field(default_factory=utc_now)
    started_at: str | None = None
    finished_at: str | None = None
    result: Any = None                       # a pydantic result model
    error: ServiceError | None = None
    artifacts: dict[str, bytes] = field(default_factory=dict)
    cancel_requested: threading.Event = field(default_factory=threading.Event)
    cancelled_by_user: bool = False
    on_disk: bool = False                    # final, persisted, result and artefacts dropped from memory
    done: Future = field(default_factory=Future)   # resolves to the result when final

    def to_schema(self) -> Job:
        eta = self.eta if self.state == "running" else None          # a final job has nothing left
        return Job(id=self.id, kind=self.kind, state=self.state, progress=self.progress,
                   eta_seconds=None if eta is None else round(eta[0], 1),
                   eta_max_seconds=None if eta is None else round(eta[1], 1),
                   created_at=self.created_at, started_at=self.started_at, finished_at=self.finished_at,
                   estimated_pixels=self.estimated_pixels, result=self.result,
                   error=None if self.error is None else self.error.detail(),
                   artifacts=sorted(self.artifacts))


class JobManager:
    def __init__(self, workers: int, queue_size: int, retention: int, on_change: Callable[[JobRecord], None]):
        self.queue_size = queue_size
        self.retention = retention
        self.on_change = on_change
        self._waiting: deque[JobRecord] = deque()
        self._jobs: OrderedDict[str, JobRecord] = OrderedDict()
        self._cond = threading.Condition()
        self._stopping = False
        self._threads = [threading.Thread(target=self._worker, name=f"phd-worker-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    # ------------------------------------------------------------------ API

    @staticmethod
    def new_id() -> str:
        return uuid.uuid4().hex[:16]

    def submit(self, job_id: str, kind: str, work: Work, estimated_pixels: float,
               owner: str | None = None) -> JobRecord:
        """Queue a job; raises QueueFull when `queue_size` jobs are already waiting."""
        job = JobRecord(id=job_id, kind=kind, work=work, estimated_pixels=estimated_pixels, owner=owner)
        with self._cond:
            if self._stopping:
                raise QueueFull("the service is shutting down")
            if len(self._waiting) >= self.queue_size:
                raise QueueFull(f"{len(self._waiting)} jobs are already waiting")
            self.on_change(job)      # on disk before anyone can see its id
            self._waiting.append(job)
            self._jobs[job.id] = job
            self._cond.notify()
        return job

    def get(self, job_id: str) -> JobRecord | None:
        with self._cond:
            return self._jobs.get(job_id)

    def cancel(self, job_id: str) -> JobRecord | None:
        """Cancel a waiting job at once, or ask a running one to stop at its next view."""
        with self._cond:
            job = self._jobs.get(job_id)
            if job is None or job.state in FINAL_STATES:
                return job
            job.cancel_requested.set()
            job.cancelled_by_user = True
            if job.state == "queued":
                self._waiting.remove(job)
                self._finish(job, "cancelled")
        return job

    def waiting(self) -> int:
        with self._cond:
            return len(self._waiting)

    def shutdown(self) -> None:
        """Cancel everything and stop the threads (running work stops at its next view)."""
        with self._cond:
            self._stopping = True
            for job in list(self._jobs.values()):
                if job.state not in FINAL_STATES:
                    job.cancel_requested.set()
            while self._waiting:
                job = self._waiting.popleft()
                job.error = ServiceError(503, *INTERRUPTED)
                self._finish(job, "failed")
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout=30)

    # ------------------------------------------------------------------ workers

    def _worker(self) -> None:
        while True:
            with self._cond:
                while not self._waiting and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                job = self._waiting.popleft()
                job.state, job.started_at = "running", utc_now()
            try:
                self.on_change(job)
            except ServiceError as exc:     # a full disk (507): no work whose result could not be kept
                with self._cond:
                    job.error = exc
                    self._finish(job, "failed")
                continue
            self._run(job)

    def _run(self, job: JobRecord) -> None:
        def progress(fraction: float, eta: tuple[float, float] | None = None) -> None:
            if job.cancel_requested.is_set():
                raise JobCancelled()
            job.progress = max(job.progress, min(1.0, float(fraction)))
            job.eta = eta

        try:
            result, artifacts = job.work(progress)
        except JobCancelled:
            state, result, artifacts, error = "cancelled", None, {}, None
            if not job.cancelled_by_user:   # stopped by a shutdown
                state, error = "failed", ServiceError(503, *INTERRUPTED)
        except BaseException as exc:  # a job never takes its worker thread down
            error = from_exception(exc)
            if error is None:
                log.error("job %s (%s) failed:\n%s", job.id, job.kind, traceback.format_exc())
                error = ServiceError(500, "internal_error", f"the {job.kind} job failed unexpectedly "
                                     f"({type(exc).__name__}); see the server log")
            state, result, artifacts = "failed", None, {}
        else:
            state, error = "succeeded", None
        with self._cond:
            job.result, job.artifacts, job.error = result, artifacts, error
            if state == "succeeded":
                job.progress = 1.0
            self._finish(job, state)

    def _finish(self, job: JobRecord, state: str) -> None:
        """Mark a job final and forget the oldest finished jobs past `retention` (lock held)."""
        job.state, job.finished_at = state, utc_now()
        job.work = None  # type: ignore[assignment]  # drop references to renderers and inputs
        try:
            self.on_change(job)          # artefacts and result on disk before anyone is told
            job.on_disk = True
        except ServiceError as exc:      # a full disk (507): a result that cannot be kept is not given
            log.warning("job %s: its %s state could not be stored: %s", job.id, state, exc.message)
            if state == "succeeded":
                job.state, job.result, job.artifacts, job.error = "failed", None, {}, exc
                with contextlib.suppress(ServiceError):     # its failed row may fit where the result did not
                    self.on_change(job)
                    job.on_disk = True
        except Exception:  # a bug must not leave a job unfinished in memory
            log.error("job %s: could not persist its final state:\n%s", job.id, traceback.format_exc())
        job.done.set_result(job.result)
        if job.on_disk:
            job.result, job.artifacts = None, {}
        finished = [j for j in self._jobs.values() if j.state in FINAL_STATES]
        for old in finished[:max(0, len(finished) - self.retention)]:
            del self._jobs[old.id]
