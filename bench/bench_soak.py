"""Soak of the service (issue 36, docs/reliability.md): `phd serve` as its own process with 2
workers and a 1 GiB memory budget, fed a steady mix of uploads, calibrations, ranks (inline and
as jobs with heat-map files), selections and deletes for `--minutes`, by `--clients` threads
that each start one operation every `--interval` seconds (never a burst to catch up).

Every minute it samples the server's resident memory, open files, the data directory's size,
the SQLite files' size and what the store holds (model files and job folders, so that growth
beyond what is stored shows), and scrapes /metrics. It counts every answer by status; a 5xx
or a job failed with internal_error is a server error.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_soak [--minutes 30]

Writes bench/results/soak.json (after every sample, so a cut run keeps its minutes) and, at
the end, the table between the `soak` markers of docs/reliability.md (`--report` redoes it).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable

import httpx
from prometheus_client.parser import text_string_to_metric_families

from bench._harness import DOCS, RESULTS, command, machine, vm, write_doc, write_result
from client import PHDClient
from client.client import JobFailedError, PHDError
from phd_core.renderers.gs3d import write_ply
from tests.support.fixtures import SvcProcess, svc_cameras, svc_random_gaussians

RESULT = RESULTS / "soak.json"
BUDGET = 1 << 30
SIZE = 48                 # render size of every view (pixels a side)
CHURN = 3                 # uploaded models kept at once beside the two fixed ones
SETTLED = 5               # minutes after which the kept jobs (64) and the write-ahead log stop growing


def folder_bytes(path: Path) -> int:
    total = 0
    for item in path.rglob("*"):
        try:
            total += item.stat().st_size if item.is_file() else 0
        except FileNotFoundError:
            pass
    return total


class Soak:
    def __init__(self, server: SvcProcess, data_dir: Path, files: list[Path], fixed: list[str]):
        self.server, self.data_dir, self.files, self.fixed = server, data_dir, files, fixed
        self.statuses: Counter[str] = Counter()
        self.operations: Counter[str] = Counter()
        self.latency: dict[str, list[float]] = {}
        self.server_errors: list[str] = []
        self.churn: list[str] = []                       # uploaded model ids, oldest first
        self.lock = threading.Lock()
        self.uploads = itertools.count()

    # ------------------------------------------------------------------ operations

    def run_op(self, phd: PHDClient, name: str, op: Callable[[PHDClient], Any]) -> None:
        start = time.perf_counter()
        try:
            op(phd)
            status = "ok"
        except JobFailedError as exc:
            status = f"job failed: {exc.code}"
            if exc.code == "internal_error":
                self.server_errors.append(f"{name}: {exc}")
        except PHDError as exc:
            status = f"{exc.status} {exc.code}"
            if exc.status is None or exc.status >= 500:
                self.server_errors.append(f"{name}: {exc}")
        with self.lock:
            self.statuses[status] += 1
            self.operations[name] += 1
            self.latency.setdefault(name, []).append(time.perf_counter() - start)

    def upload(self, phd: PHDClient) -> None:
        n = next(self.uploads)
        model = phd.upload_model(self.files[n % len(self.files)], cameras=svc_cameras(6, size=SIZE, phase=n / 7),
                                 name=f"churn {n}")
        phd.calibrate(model.id, epsilon=0.5, step=0.1, samples=8)
        with self.lock:
            self.churn.append(model.id)

    def delete(self, phd: PHDClient) -> None:
        with self.lock:
            victim = self.churn.pop(0) if len(self.churn) > CHURN else None
        if victim is not None:
            phd.delete_model(victim)

    def newest(self) -> str:
        with self.lock:
            return self.churn[-1] if self.churn else self.fixed[0]

    def rank_inline(self, phd: PHDClient) -> None:
        phd.rank(self.fixed[0], svc_cameras(6, size=SIZE, phase=0.3), samples=16)

    def rank_job(self, phd: PHDClient) -> None:
        job = phd.rank(self.newest(), svc_cameras(8, size=SIZE, phase=0.6), samples=16, heatmaps="files",
                       top_k=3, run_async=True, wait=False)
        ranked = phd.wait_job(job.id, poll_interval=0.5)
        phd.download(ranked.views[0].heatmap_url)          # type: ignore[union-attr]

    def select(self, phd: PHDClient) -> None:
        phd.select(self.fixed[0], self.fixed[1], svc_cameras(4, size=SIZE, phase=0.1), samples=8,
                   rule="sigma_mean", images="files")

    def read(self, phd: PHDClient) -> None:
        for model in phd.list_models():
            phd.get_model(model.id)

    def client(self, index: int, deadline: float, interval: float) -> None:
        mix = [("upload", self.upload), ("rank", self.rank_inline), ("rank job", self.rank_job),
               ("select", self.select), ("read", self.read), ("delete", self.delete)]
        start = time.monotonic() + index * interval / 2          # the clients alternate
        with PHDClient(self.server.url, timeout=600) as phd:
            for step in itertools.count():
                due = start + step * interval
                if due > deadline:
                    return
                time.sleep(max(0.0, due - time.monotonic()))
                name, op = mix[(step + index * 3) % len(mix)]
                self.run_op(phd, name, op)

    # ------------------------------------------------------------------ samples

    def sample(self, minute: float) -> dict[str, Any]:
        pid = self.server.proc.pid
        scraped = httpx.get(f"{self.server.url}/metrics", timeout=60).text
        metrics = {s.name + "".join(f"[{v}]" for v in s.labels.values()): s.value
                   for family in text_string_to_metric_families(scraped) for s in family.samples}
        db = sum(p.stat().st_size for p in self.data_dir.glob("phd.sqlite3*") if ".bak" not in p.name)
        with self.lock:
            done = sum(self.operations.values())
        return {"minute": round(minute, 2), "rss_mib": round(vm(pid, "VmRSS") / 2**20, 1),
                "open_files": len(os.listdir(f"/proc/{pid}/fd")),
                "data_dir_kib": folder_bytes(self.data_dir) // 1024, "sqlite_kib": db // 1024,
                "models_kib": folder_bytes(self.data_dir / "models") // 1024,
                "jobs_kib": folder_bytes(self.data_dir / "jobs") // 1024,
                "models": int(sum(v for k, v in metrics.items() if k.startswith("phd_models["))),
                "jobs_kept": int(sum(v for k, v in metrics.items() if k.startswith("phd_jobs["))),
                "queue_depth": int(metrics["phd_queue_depth"]),
                "memory_reserved_mib": round(metrics["phd_memory_reserved_bytes"] / 2**20, 1),
                "operations": done, "server_errors": len(self.server_errors)}


def run(minutes: float, interval: float, clients: int) -> dict[str, Any]:
    root = Path(tempfile.mkdtemp(prefix="phd-soak-"))
    data_dir = root / "data"
    files = []
    for i in range(4):
        files.append(root / f"churn{i}.ply")
        write_ply(svc_random_gaussians(2000, seed=10 + i), files[-1])
    fixed_files = [root / "a.ply", root / "b.ply"]
    write_ply(svc_random_gaussians(5000, seed=1), fixed_files[0])
    write_ply(svc_random_gaussians(3000, seed=2), fixed_files[1])
    env = {"PHD_WORKERS": "2", "PHD_MEMORY_BUDGET_BYTES": str(BUDGET), "PHD_JOB_RETENTION": "64",
           "PHD_QUEUE_SIZE": "8"}
    server = SvcProcess(data_dir, **env)
    try:
        with PHDClient(server.url, timeout=600) as phd:
            fixed = [phd.upload_model(f, cameras=svc_cameras(8, size=SIZE), name=f.stem).id for f in fixed_files]
            for model_id in fixed:
                phd.calibrate(model_id, epsilon=0.5, step=0.1, samples=8)
        soak = Soak(server, data_dir, files, fixed)
        begin = time.monotonic()
        deadline = begin + minutes * 60
        threads = [threading.Thread(target=soak.client, args=(i, deadline, interval), daemon=True)
                   for i in range(clients)]
        for thread in threads:
            thread.start()
        samples = []
        for minute in itertools.count():
            time.sleep(max(0.0, begin + minute * 60 - time.monotonic()))
            samples.append(soak.sample((time.monotonic() - begin) / 60))
            print(samples[-1], flush=True)
            result = {"command": command(), "machine": machine(), "minutes": minutes, "interval_s": interval,
                      "clients": clients, "settings": env, "samples": samples, "statuses": dict(soak.statuses),
                      "operations": dict(soak.operations),
                      "latency_median_s": {k: round(statistics.median(v), 3) for k, v in soak.latency.items()},
                      "latency_max_s": {k: round(max(v), 3) for k, v in soak.latency.items()},
                      "server_errors": soak.server_errors[:20], "server_error_count": len(soak.server_errors)}
            write_result(RESULT, result)
            if time.monotonic() >= deadline and not any(t.is_alive() for t in threads):
                break
        log = server.log
        log.seek(0)
        result["server_log_tracebacks"] = log.read().decode("utf-8", "replace").count("Traceback")
        write_result(RESULT, result)
        return result
    finally:
        server.kill()


def table(result: dict[str, Any]) -> str:
    """The docs' table: one row per sampled minute, then the totals."""
    rows = ["| minute | RSS MiB | open files | data dir KiB | of it: models + jobs KiB | SQLite KiB | models | "
            "jobs kept | reserved MiB | operations | server errors |", "|" + "---|" * 11]
    for s in result["samples"]:
        rows.append(f"| {s['minute']:.0f} | {s['rss_mib']:.0f} | {s['open_files']} | {s['data_dir_kib']:,} | "
                    f"{s['models_kib'] + s['jobs_kib']:,} | {s['sqlite_kib']:,} | {s['models']} | {s['jobs_kept']} | "
                    f"{s['memory_reserved_mib']:.0f} | {s['operations']:,} | {s['server_errors']} |")
    settled = [s for s in result["samples"] if s["minute"] >= SETTLED]

    def spread(key: str) -> str:
        values = [s[key] for s in settled]
        return f"{min(values):,.0f} to {max(values):,.0f}"

    ops = ", ".join(f"{n:,} {k}" for k, n in sorted(result["operations"].items()))
    statuses = ", ".join(f"{n:,} {k}" for k, n in sorted(result["statuses"].items()))
    latency = ", ".join(f"{k} {v} s" for k, v in sorted(result["latency_median_s"].items()))
    return "\n".join(rows) + (
        f"\n\nFrom minute {SETTLED} on (the kept jobs and SQLite's write-ahead log at their plateau): RSS "
        f"{spread('rss_mib')} MiB, open files {spread('open_files')}, data dir {spread('data_dir_kib')} KiB (models "
        f"and jobs {spread('models_kib')} and {spread('jobs_kib')} KiB), SQLite {spread('sqlite_kib')} KiB. "
        f"{sum(result['operations'].values()):,} operations ({ops}); outcomes: {statuses}; "
        f"{result['server_error_count']} server errors, {result.get('server_log_tracebacks', 'n/a')} tracebacks "
        f"in the server's log. Median latency: {latency}. Settings: {result['settings']}, {result['clients']} "
        f"clients each starting an operation every {result['interval_s']:g} s. Command: `{result['command']}`.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=30)
    parser.add_argument("--interval", type=float, default=4.0, help="seconds between a client's operations")
    parser.add_argument("--clients", type=int, default=2)
    parser.add_argument("--report", action="store_true", help="only redo the docs' table from the result file")
    args = parser.parse_args()
    result = json.loads(RESULT.read_text()) if args.report else run(args.minutes, args.interval, args.clients)
    write_doc(DOCS / "reliability.md", table(result), "soak")
    print(table(result))


if __name__ == "__main__":
    main()
