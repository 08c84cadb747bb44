"""Benchmark of the Ray executor: scaling from 1 to 2 Ray workers on a ranking job, and the
overhead of the Ray path against the local one on a small job.

Measures, in one run on this machine (every round restarts a private Ray instance with 1,
then 2 CPUs; local runs are timed in the same rounds, so load hits both sides alike):
- `rank_views` on a big job (--candidates views at --size pixels, N = --samples) locally
  (torch with 1 thread and with the process's default threads) and on Ray with 1 and 2 CPUs:
  the scaling ratio is time(1 CPU) / time(2 CPUs);
- a small job (--small-candidates views at --small-size pixels, N = 8; one view by default,
  so one chunk and no parallelism) locally and on a warm Ray (workers started): the fixed
  cost of going through Ray;
- the cold first call (Ray workers start and import torch), once per Ray instance;
- that every Ray ranking equals the local one.

    .venv/bin/python -m bench.bench_ray [--model runs/lego16/model.ply] [--rounds 2]

The model is --model, else a seeded random 3DGS model of --random-splats splats. Writes
bench/results/ray.json and prints a Markdown table for docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench._harness import RESULTS, candidates, machine, random_model, timed, write_result
from phd_core import uq
from phd_core.executors.ray import RayExecutor, import_ray
from phd_core.renderers import load_model


def worker_threads(_chunk) -> int:
    """Torch threads of the worker that runs this chunk; the sleep makes Ray start every worker."""
    time.sleep(1.0)
    return torch.get_num_threads()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, default=None)
    parser.add_argument("--random-splats", type=int, default=4_000)
    parser.add_argument("--candidates", type=int, default=32)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--small-candidates", type=int, default=1)
    parser.add_argument("--small-size", type=int, default=16)
    parser.add_argument("--ratio", type=float, default=0.2)
    parser.add_argument("--rounds", type=int, default=3, help="Ray restarts per CPU count")
    parser.add_argument("--reps", type=int, default=2, help="timed calls per measurement (median)")
    parser.add_argument("--out", type=Path, default=RESULTS / "ray.json")
    args = parser.parse_args()

    ray = import_ray()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.model
        if path is None:
            path = Path(tmp) / "random.ply"
            random_model(path, args.random_splats)
        renderer = load_model(path)
    big, big_source = candidates(args.candidates, args.size)
    small, _ = candidates(args.small_candidates, args.small_size)

    def rank(cameras, samples, executor=None):
        kw = {} if executor is None else {"executor": executor}
        return uq.rank_views(renderer, cameras, ratio=args.ratio, samples=samples, seed=0, **kw)

    default_threads = torch.get_num_threads()
    rows: dict[str, list[float]] = {k: [] for k in (
        "local_1thread", "local_default", "ray_1cpu", "ray_2cpu", "small_local", "small_ray_1cpu", "small_ray_2cpu",
        "cold_1cpu", "cold_2cpu", "sleep_map_1cpu", "sleep_map_2cpu")}
    expected = [r.to_dict() for r in rank(big, args.samples)]
    same, threads_in_workers = True, set()
    for round_ in range(args.rounds):
        for cpus in (1, 2):
            ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
            executor = RayExecutor("auto")
            start = time.perf_counter()
            rank(small, 8, executor)                      # a worker starts and imports torch and phd_core
            rows[f"cold_{cpus}cpu"].append(time.perf_counter() - start)
            # Every worker started (and warm) before timing: chunks that sleep occupy all CPUs.
            threads_in_workers |= set(executor.map(worker_threads, executor.split(range(2 * cpus))))
            rank(big, args.samples, executor)
            # Concurrency without CPU contention: 4 chunks that each sleep 1 s (4 s on 1 CPU, 2 s on 2).
            start = time.perf_counter()
            executor.map(worker_threads, [[i] for i in range(4)])
            rows[f"sleep_map_{cpus}cpu"].append(time.perf_counter() - start)
            ranking = timed(lambda: rank(big, args.samples, executor), args.reps)
            rows[f"ray_{cpus}cpu"].append(ranking.median)
            same &= [r.to_dict() for r in ranking.result] == expected
            rows[f"small_ray_{cpus}cpu"].append(timed(lambda: rank(small, 8, executor), args.reps * 3).median)
            ray.shutdown()
            torch.set_num_threads(1)
            rows["local_1thread"].append(timed(lambda: rank(big, args.samples), args.reps).median)
            torch.set_num_threads(default_threads)
            rows["local_default"].append(timed(lambda: rank(big, args.samples), args.reps).median)
            rows["small_local"].append(timed(lambda: rank(small, 8), args.reps * 3).median)
            print(f"round {round_ + 1}, {cpus} CPU(s): ray {rows[f'ray_{cpus}cpu'][-1]:.3f} s, local "
                  f"{rows['local_1thread'][-1]:.3f} s (1 thread), {rows['local_default'][-1]:.3f} s", flush=True)

    med = {k: statistics.median(v) for k, v in rows.items()}
    result = {
        "benchmark": "rank_views on Ray (phd_core.executors.ray) vs local",
        "machine": machine(ray=ray.__version__, local_threads=default_threads,
                           threads_per_ray_worker=sorted(threads_in_workers)),
        "model": str(args.model) if args.model else f"random 3DGS, {args.random_splats} splats",
        "num_units": renderer.num_units,
        "big_job": {"candidates": args.candidates, "size": args.size, "samples": args.samples,
                    "source": big_source},
        "small_job": {"candidates": args.small_candidates, "size": args.small_size, "samples": 8},
        "rounds": args.rounds, "reps": args.reps, "ranking_equal_to_local": same,
        "seconds": rows, "median_s": med,
        "scaling_1_to_2_cpus": med["ray_1cpu"] / med["ray_2cpu"],
        "scaling_per_round": [a / b for a, b in zip(rows["ray_1cpu"], rows["ray_2cpu"])],
        "sleep_map_scaling": med["sleep_map_1cpu"] / med["sleep_map_2cpu"],
        "ray_2cpu_vs_local_default": med["ray_2cpu"] / med["local_default"],
        "ray_1cpu_vs_local_1thread": med["ray_1cpu"] / med["local_1thread"],
        "small_job_overhead_s": med["small_ray_2cpu"] - med["small_local"],
        "small_job_ratio": med["small_ray_2cpu"] / med["small_local"],
        "load_average_after": os.getloadavg(),
    }
    write_result(args.out, result)
    print(f"\n| job | local (1 thread) | local ({default_threads} threads) | Ray, 1 CPU | Ray, 2 CPUs |")
    print("|---|---|---|---|---|")
    print(f"| big: {args.candidates} views {args.size}px N={args.samples} | {med['local_1thread']:.2f} s | "
          f"{med['local_default']:.2f} s | {med['ray_1cpu']:.2f} s | {med['ray_2cpu']:.2f} s |")
    print(f"| small: {args.small_candidates} views {args.small_size}px N=8 | | {med['small_local'] * 1e3:.0f} ms | "
          f"{med['small_ray_1cpu'] * 1e3:.0f} ms | {med['small_ray_2cpu'] * 1e3:.0f} ms |")
    print(f"| cold first call (workers start) | | | {med['cold_1cpu']:.2f} s | {med['cold_2cpu']:.2f} s |")
    print(f"| 4 chunks sleeping 1 s each (no CPU use) | | | {med['sleep_map_1cpu']:.2f} s | "
          f"{med['sleep_map_2cpu']:.2f} s |")
    print(f"\nscaling 1 -> 2 CPUs: {result['scaling_1_to_2_cpus']:.2f}x (per round: "
          f"{', '.join(f'{r:.2f}' for r in result['scaling_per_round'])}); load average after: "
          f"{', '.join(f'{x:.1f}' for x in result['load_average_after'])}; Ray 2 CPUs / local: "
          f"{result['ray_2cpu_vs_local_default']:.2f}; "
          f"small-job overhead {result['small_job_overhead_s'] * 1e3:.0f} ms "
          f"({result['small_job_ratio']:.1f}x); rankings equal to local: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
