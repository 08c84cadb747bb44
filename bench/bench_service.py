"""Benchmark of the service: `rank` with 10 candidates at 100x100, N = 16.

Measures, in one run on this machine:
- the latency of `phd_core.uq.rank_views` called directly (the floor), on a worker
  thread like the service's,
- requests per second and latency p50/p95 of POST /v1/models/{id}/rank against `phd serve`
  (a separate process, as users run it) with 1 and with 4 concurrent clients,
- the service's overhead: 1-client requests interleaved with direct calls, as the median of
  the per-pair ratios (the machine's load hits both halves of a pair alike) and as the
  ratio of the p50s.

    .venv/bin/python -m bench.bench_service [--model runs/lego16/model.ply] [--workers 1]

The model is --model, else runs/lego16/model.ply when the trainer has produced it, else a
seeded random 3DGS model (the output says which). Candidates are test-split views of
lego_200 at 100x100 (or hemisphere poses if the data is missing). Writes
bench/results/service.json and prints a Markdown table for docs/service.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx

from bench._harness import RESULTS, ROOT, candidates, machine, random_model, write_result
from client import PHDClient
from phd_core import uq
from phd_core.renderers import load_model

TRAINED = ROOT / "runs" / "lego16" / "model.ply"


def percentile(values: list[float], q: float) -> float:
    """Linear-interpolated percentile (q in [0, 100])."""
    ordered = sorted(values)
    k = (len(ordered) - 1) * q / 100
    lo, hi = math.floor(k), math.ceil(k)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (k - lo)


def start_server(data_dir: Path, workers: int) -> tuple[subprocess.Popen, str]:
    """`phd serve` in its own process on a free port."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = ("import argparse, sys; from phd_cli import serve; p = argparse.ArgumentParser(); "
            "serve.register(p.add_subparsers()); a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))")
    proc = subprocess.Popen([sys.executable, "-c", code, "serve", "--port", str(port), "--data-dir", str(data_dir),
                             "--workers", str(workers), "--queue-size", "32", "--log-level", "warning"],
                            cwd=ROOT, stdout=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/health", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("phd serve did not start")


def load_test(url: str, model_id: str, frames: list[dict], args, clients: int, requests: int) -> dict:
    """`requests` rank calls spread over `clients` threads, each with its own client."""
    latencies: list[float] = []
    lock = threading.Lock()
    per_client = [requests // clients + (i < requests % clients) for i in range(clients)]
    barrier = threading.Barrier(clients)

    def client(count: int) -> None:
        with PHDClient(url, timeout=3600) as phd:
            barrier.wait()
            for _ in range(count):
                start = time.perf_counter()
                phd.rank(model_id, frames, samples=args.samples, dropout_ratio=args.ratio, seed=0)
                with lock:
                    latencies.append(time.perf_counter() - start)

    start = time.perf_counter()
    with ThreadPoolExecutor(clients) as pool:
        list(pool.map(client, per_client))
    wall = time.perf_counter() - start
    return {"clients": clients, "requests": len(latencies), "wall_s": wall, "rps": len(latencies) / wall,
            "p50_s": percentile(latencies, 50), "p95_s": percentile(latencies, 95), "latencies_s": latencies}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--random-splats", type=int, default=10_000, help="size of the fallback random model")
    parser.add_argument("--candidates", type=int, default=10)
    parser.add_argument("--size", type=int, default=100)
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--ratio", type=float, default=0.2, help="dropout ratio (fixed, so no calibration)")
    parser.add_argument("--requests-1", type=int, default=5,
                        help="requests with 1 client (each paired with one direct call)")
    parser.add_argument("--requests-4", type=int, default=8, help="requests with 4 clients")
    parser.add_argument("--workers", type=int, nargs="+", default=[1], help="server worker threads to try")
    parser.add_argument("--out", type=Path, default=RESULTS / "service.json")
    args = parser.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="phd-bench-service-"))
    if args.model is not None:
        model_path, model_source = args.model, f"given: {args.model}"
    elif TRAINED.is_file():
        model_path, model_source = TRAINED, f"trained: {TRAINED.relative_to(ROOT)}"
    else:
        model_path = tmp / "random.ply"
        model_source = f"random: {args.random_splats} seeded splats (no trained model found)"
        random_model(model_path, args.random_splats)
    cameras, camera_source = candidates(args.candidates, args.size)
    frames = [c.to_frame() for c in cameras]
    renderer = load_model(model_path)
    print(f"model {model_source}, {renderer.num_units} units; candidates: {camera_source}; "
          f"{args.size}x{args.size}, N = {args.samples}, ratio {args.ratio}", flush=True)

    # The library called directly, on a worker thread as the service's workers call it: with
    # libgomp's default active waiting, 2-thread torch on the MAIN thread of a process on
    # shared cores runs ~3x slower than on a worker thread (unless OMP_WAIT_POLICY=passive),
    # which would flatter the service.
    worker = ThreadPoolExecutor(1)
    expected = worker.submit(uq.rank_views, renderer, cameras, ratio=args.ratio, samples=args.samples,
                             seed=0).result()  # warm-up and the reference answer

    def direct_call() -> float:
        start = time.perf_counter()
        worker.submit(uq.rank_views, renderer, cameras, ratio=args.ratio, samples=args.samples,
                      seed=0).result()
        return time.perf_counter() - start

    direct: list[float] = []
    pair_ratios: list[float] = []
    runs = []
    for workers in args.workers:
        proc, url = start_server(tmp / f"data-w{workers}", workers)
        try:
            with PHDClient(url, timeout=3600) as phd:
                model_id = phd.upload_model(model_path).id
                check = phd.rank(model_id, frames, samples=args.samples, dropout_ratio=args.ratio, seed=0)  # warm-up
                matches = ([v.index for v in check.views] == [r.index for r in expected]
                           and all(math.isclose(v.sigma_max, r.sigma_max, rel_tol=1e-6)
                                   for v, r in zip(check.views, expected)))
                # 1 client, interleaved with direct calls: the machine's load (shared cores) hits both alike.
                latencies = []
                start = time.perf_counter()
                for _ in range(args.requests_1):
                    direct.append(direct_call())
                    began = time.perf_counter()
                    phd.rank(model_id, frames, samples=args.samples, dropout_ratio=args.ratio, seed=0)
                    latencies.append(time.perf_counter() - began)
                    pair_ratios.append(latencies[-1] / direct[-1])
                wall = time.perf_counter() - start - sum(direct[-args.requests_1:])
            runs.append({"workers": workers, "clients": 1, "requests": len(latencies), "wall_s": wall,
                         "rps": len(latencies) / wall, "p50_s": percentile(latencies, 50),
                         "p95_s": percentile(latencies, 95), "latencies_s": latencies,
                         "results_match_library": matches})
            result = load_test(url, model_id, frames, args, 4, args.requests_4)
            result.update(workers=workers, results_match_library=matches)
            runs.append(result)
            for r in runs[-2:]:
                print(f"workers {workers}, {r['clients']} client(s): {r['rps']:.3f} req/s, "
                      f"p50 {r['p50_s']:.3f} s, p95 {r['p95_s']:.3f} s", flush=True)
        finally:
            proc.kill()
            proc.wait()

    direct_p50 = percentile(direct, 50)
    single = [r for r in runs if r["clients"] == 1]
    report = {
        "benchmark": "service rank: POST /v1/models/{id}/rank vs uq.rank_views",
        "machine": machine(),
        "settings": {"model": model_source, "num_units": renderer.num_units, "cameras": camera_source,
                     "candidates": args.candidates, "size": args.size, "samples": args.samples, "ratio": args.ratio},
        "direct": {"calls": len(direct), "p50_s": direct_p50, "latencies_s": direct},
        "service": runs,
        "overhead_ratio_p50_1_client": {str(r["workers"]): r["p50_s"] / direct_p50 for r in single},
        "overhead_ratio_median_of_pairs": statistics.median(pair_ratios),
    }
    write_result(args.out, report)

    print("\n| server workers | clients | requests | req/s | p50 (s) | p95 (s) | p50 / direct p50 |")
    print("|---|---|---|---|---|---|---|")
    for r in runs:
        print(f"| {r['workers']} | {r['clients']} | {r['requests']} | {r['rps']:.3f} | {r['p50_s']:.3f} | "
              f"{r['p95_s']:.3f} | {r['p50_s'] / direct_p50:.3f} |")
    print(f"\ndirect rank_views p50: {direct_p50:.3f} s; service/direct, median of interleaved pairs: "
          f"{statistics.median(pair_ratios):.3f}; results written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
