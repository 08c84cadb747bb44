"""What an operator watches: Prometheus metrics of one service (`GET /metrics`, the text format,
made by the official client library, `prometheus_client`).

Counters and histograms are counted as things happen (error answers by `service.metrics.Counting`,
an ASGI middleware that reads the one error shape every error answer has; uploads and finished
jobs by `service.state`); gauges are read when scraped, from where the truth is: the work queue,
the memory ledger, the store's database and the data directory's files. Each service has its own
registry, so two services in one process (tests, the demo) never mix their counts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Awaitable, Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from .budget import MemoryLedger
from .jobs import JobRecord
from .jobstore import FINAL_STATES, JobStore
from .settings import Settings
from .store import SCHEMA_VERSION, ModelStore

# Job durations from a tiny rank (a tenth of a second) to a heavy calibration (an hour).
DURATION_BUCKETS = (0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800, 3600)


class Metrics:
    """The service's counters and histograms, and the registry `/metrics` renders."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.errors = Counter("phd_error_answers", "Error answers by HTTP status and error code (4xx: refusals, "
                              "507: disk full, 5xx: failures)", ["status", "code"], registry=self.registry)
        self.uploads = Counter("phd_uploads", "Models stored by an upload, by family", ["family"],
                               registry=self.registry)
        self.jobs = Counter("phd_jobs_finished", "Jobs whose final state was stored, by kind and state",
                            ["kind", "state"], registry=self.registry)
        self.duration = Histogram("phd_job_duration_seconds", "Time a job ran (started to final state), by kind",
                                  ["kind"], buckets=DURATION_BUCKETS, registry=self.registry)
        self.wait = Histogram("phd_job_wait_seconds", "Time a job waited in the queue for a worker, by kind",
                              ["kind"], buckets=DURATION_BUCKETS, registry=self.registry)

    def watch(self, settings: Settings, store: ModelStore, job_store: JobStore, ledger: MemoryLedger,
              waiting: Callable[[], int]) -> None:
        """Read the gauges of these at every scrape (`waiting`: the jobs in the queue)."""
        self.registry.register(Scrape(settings, store, job_store, ledger, waiting))

    def job_stored(self, job: JobRecord) -> None:
        """A job's state was stored: a final one is counted, with how long it waited and ran."""
        if job.state not in FINAL_STATES:
            return
        self.jobs.labels(job.kind, job.state).inc()
        created, started, finished = (None if t is None else datetime.fromisoformat(t)
                                      for t in (job.created_at, job.started_at, job.finished_at))
        if started is not None:
            assert created is not None and finished is not None    # a started, final job has all three
            self.wait.labels(job.kind).observe((started - created).total_seconds())
            self.duration.labels(job.kind).observe((finished - started).total_seconds())


@dataclass(eq=False)         # registries keep collectors in a set: hashed by identity
class Scrape(Collector):
    """The gauges, read from the service when `/metrics` is scraped."""

    settings: Settings
    store: ModelStore
    job_store: JobStore
    ledger: MemoryLedger
    waiting: Callable[[], int]

    def collect(self) -> Iterator[Metric]:
        settings, store, ledger = self.settings, self.store, self.ledger
        yield _gauge("phd_queue_depth", "Jobs waiting for a worker", self.waiting())
        yield _gauge("phd_queue_capacity", "Jobs that may wait before work requests get 429", settings.queue_size)
        yield _gauge("phd_workers", "Worker threads running jobs", settings.workers)
        with store._connect() as db:
            jobs = db.execute("SELECT kind, state, COUNT(*) AS n FROM jobs GROUP BY kind, state").fetchall()
            models = db.execute("SELECT kind, COUNT(*) AS n FROM models GROUP BY kind").fetchall()
        yield _gauge("phd_jobs", "Jobs kept by the service (queued, running, and the finished ones retained), by "
                     "kind and state", [((r["kind"], r["state"]), r["n"]) for r in jobs], ["kind", "state"])
        yield _gauge("phd_models", "Models stored, by family", [((r["kind"],), r["n"]) for r in models], ["family"])
        yield _gauge("phd_memory_reserved_bytes", "Memory reserved in the budget: models in memory, running jobs, "
                     "upload parses", ledger.used)
        yield _gauge("phd_memory_budget_bytes", "The memory budget (PHD_MEMORY_BUDGET_BYTES)", ledger.budget)
        yield _gauge("phd_models_in_memory", "Models loaded in memory", len(ledger.loaded()))
        stored = {"models": _size(store.models_dir), "jobs": _size(self.job_store.root),
                  "uploads_in_progress": _size(store.tmp_dir),
                  "database": sum(_size(store.db_path.with_name(store.db_path.name + end))
                                  for end in ("", "-wal", "-shm"))}
        yield _gauge("phd_stored_bytes", "Bytes in the data directory, by what they hold",
                     [((what,), n) for what, n in stored.items()], ["what"])
        yield _gauge("phd_disk_free_bytes", "Free space on the data directory's disk", store.free_bytes())
        yield _gauge("phd_keep_free_bytes", "Free space an upload may not eat into (PHD_KEEP_FREE_BYTES)",
                     settings.keep_free_bytes)
        yield _gauge("phd_store_schema_version", "Schema version of the store", SCHEMA_VERSION)


def _gauge(name: str, documentation: str, value: float | list[tuple[tuple[str, ...], float]],
           labels: list[str] | None = None) -> GaugeMetricFamily:
    """A gauge family: one value, or (label values, value) samples."""
    if labels is None:
        assert not isinstance(value, list)
        return GaugeMetricFamily(name, documentation, value=value)
    family = GaugeMetricFamily(name, documentation, labels=labels)
    for label_values, sample in value:    # type: ignore[union-attr]  # a list whenever labels are given
        family.add_metric(list(label_values), sample)
    return family


def _size(path: Path) -> int:
    """Bytes of a file, or of the files under a folder (0 when missing; files may go while counted)."""
    if path.is_file():
        return path.stat().st_size
    total = 0
    for item in path.rglob("*") if path.is_dir() else ():
        try:
            total += item.stat().st_size if item.is_file() else 0
        except FileNotFoundError:
            pass
    return total


# ----------------------------------------------------------------------------- error answers

Scope = dict[str, Any]
Message = dict[str, Any]
ASGIApp = Callable[[Scope, Callable[[], Awaitable[Message]], Callable[[Message], Awaitable[None]]], Awaitable[None]]


class Counting:
    """ASGI middleware outside the guard: counts every error answer (the guard's own included) by
    status and the `code` of its body, `{"error": {"code", ...}}`."""

    def __init__(self, app: ASGIApp, metrics: Metrics):
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Callable[[], Awaitable[Message]],
                       send: Callable[[Message], Awaitable[None]]) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 0

        async def counting_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            elif message["type"] == "http.response.body" and status >= 400:
                self.metrics.errors.labels(str(status), _code(message.get("body", b""))).inc()
                status = 0                  # counted once, at its first body message
            await send(message)

        await self.app(scope, receive, counting_send)


def _code(body: bytes) -> str:
    """The error code of an error answer's body ("unknown" for a body of another shape)."""
    try:
        code = json.loads(body)["error"]["code"]
    except (ValueError, KeyError, TypeError):
        return "unknown"
    return code if isinstance(code, str) else "unknown"
