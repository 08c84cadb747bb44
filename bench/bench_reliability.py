"""Reliability figures of the service (issues 17 and 46, docs/reliability.md), against `phd serve`
run as a separate process, as users run it:

- fuzz: `--requests` mutated requests (tests/support/fuzz.py) over one keep-alive
  connection: how many got a 5xx, how many connections were dropped (a transport error or
  `Connection: close`), and whether any accepted job failed with internal_error;
- folders: the uploads issue 46's probe inflated (tests/support/archives.BOMBS), each with the
  server's peak RSS over its RSS before it, then `--folders` mutated trainer folders
  (`mutated_folder`) over one connection, counted as the fuzz is, with the server's peak RSS
  over the whole run against its memory budget (`--folder-budget`);
- ASCII PLY: peak RSS of parsing a `--splats`-splat ASCII PLY held in memory, over the
  RSS once the file is read, next to the file size.

    nice -n 10 .venv/bin/python -m bench.bench_reliability [--requests 10000] [--folders 3000]

Writes bench/results/reliability.json (reliability_folders_<budget>mib.json with
`--skip fuzz ascii`). Memory under every kind of request (the attack's 800x800, samples=256 rank
included) is bench/bench_memory.py's sweep.
"""

from __future__ import annotations

import argparse
import json
import random
import resource
import subprocess
import sys
import tempfile
import time
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import httpx

from bench._harness import RESULTS, machine, write_result
from client import PHDClient
from phd_core.renderers.gs3d import write_ply
from tests.support.archives import BOMBS, zero_checkpoint, zip_of
from tests.support.fixtures import SvcProcess, proc_bytes, svc_cameras, svc_random_gaussians
from tests.support.fuzz import FuzzRequest, mutated_folder, mutated_request, send, trainer_folders


def fuzz(requests: int, root: Path, ply: Path, ply_b: Path) -> dict:
    env = {"PHD_MAX_SAMPLES": "8", "PHD_MAX_IMAGE_SIZE": "32", "PHD_MAX_CANDIDATES": "4",
           "PHD_MAX_TRAINING_CAMERAS": "4", "PHD_MAX_JSON_BYTES": "100000", "PHD_MEMORY_BUDGET_BYTES": str(256 << 20)}
    server = SvcProcess(root / "fuzz", **env)
    try:
        with PHDClient(server.url) as phd:
            a = phd.upload_model(ply, cameras=svc_cameras(2, size=16))
            b = phd.upload_model(ply_b, cameras=svc_cameras(2, size=16))
            job = phd.rank(a.id, svc_cameras(1, size=16), samples=2, dropout_ratio=0.1, heatmaps="files",
                           run_async=True, wait=False)
            phd.wait_job(job.id, timeout=60)
        ids = {"model": a.id, "model_b": b.id, "job": job.id}
        data = ply.read_bytes()
        rng = random.Random(17)
        counted = send_all(server, (mutated_request(rng, ids, data) for _ in range(requests)))
    finally:
        server.kill()
    return {"requests": requests, **counted}


def send_all(server: SvcProcess, requests: Iterable[FuzzRequest],
             answered: Callable[[httpx.Client, httpx.Response], None] = lambda client, response: None) -> dict:
    """Send `requests` to `server` over one keep-alive connection (`answered` sees each answer):
    the statuses, the 5xx and the dropped connections (a transport error or `Connection: close`)."""
    statuses: dict[int, int] = {}
    server_errors, dropped, failures = 0, 0, []
    client = httpx.Client(base_url=server.url, timeout=300)
    start = time.perf_counter()
    for request in requests:
        try:
            response = send(client, request)
        except httpx.TransportError as exc:
            dropped += 1
            failures.append(f"{request.method} {request.path}: {type(exc).__name__}")
            continue
        statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
        if response.status_code >= 500:
            server_errors += 1
            failures.append(f"{request.method} {request.path}: {response.status_code} {response.text[:200]}")
        if response.headers.get("connection") == "close":
            dropped += 1
        answered(client, response)
    seconds = time.perf_counter() - start
    connections = len(client._transport._pool.connections)
    client.close()
    return {"seconds": round(seconds, 1), "server_errors": server_errors, "dropped_connections": dropped,
            "connections_used": connections, "server_alive_after": server.proc.poll() is None,
            "statuses": dict(sorted(statuses.items())), "failures": failures[:20]}


def folders(count: int, budget: int, root: Path) -> dict:
    """The probe's bombs one by one, then `count` mutated trainer folders, against `phd serve`
    under `budget`: each bomb's answer and peak, the fuzz's counts and its peak over the run."""
    runs = trainer_folders(root / "runs")
    server = SvcProcess(root / "folders", PHD_MEMORY_BUDGET_BYTES=str(budget), OMP_NUM_THREADS="1")
    try:
        with httpx.Client(base_url=server.url, timeout=300) as client:   # every reader warmed up once
            for files in runs.values():
                answer = client.post("/v1/models", files={"archive": ("run.zip", zip_of(files))})
                assert answer.status_code == 201, answer.text
        # Within the ratio rule: the model (56 MB of 1 M zero splats at one point, whose frame-choice
        # renders would hold 7.9 GiB) is read, and refused before its 68 MB PLY is written.
        within = {**runs["gsplat"], "results/garden/ckpts/ckpt_6999_rank0.pt": zero_checkpoint(1_000_000, chunk=8192)}
        bombs = {}
        for name, make in {**BOMBS, "1 M zero splats deflated 280 times, with their capture":
                           lambda: zip_of(within, zipfile.ZIP_STORED)}.items():
            archive = make()
            with peak_rss(server.proc.pid) as peak:
                answer = httpx.post(f"{server.url}/v1/models", files={"archive": ("run.zip", archive)}, timeout=300)
            bombs[name] = {"zip_bytes": len(archive), "status": answer.status_code,
                           "answer": answer.text[:300], "peak_over_before_mib": peak.mib}
            print(json.dumps({name: bombs[name]}), flush=True)
        rng = random.Random(46)

        def forget(client: httpx.Client, response: httpx.Response) -> None:
            if response.status_code == 201:                  # the store stays small: delete what was stored
                client.delete(f"/v1/models/{response.json()['id']}")

        with peak_rss(server.proc.pid) as peak:
            counted = send_all(server, (mutated_folder(rng, runs) for _ in range(count)), forget)
        idle = proc_bytes(server.proc.pid, "VmRSS")
    finally:
        server.kill()
    return {"budget_mib": budget >> 20, "bombs": bombs, "folders": count, **counted,
            "peak_over_before_mib": peak.mib, "peak_mib": peak.total_mib, "rss_after_mib": idle >> 20}


@dataclass
class Peak:
    mib: int = 0        # once the block is done: the peak resident memory over the RSS before it
    total_mib: int = 0  # and the peak itself


@contextmanager
def peak_rss(pid: int) -> Iterator[Peak]:
    """The peak resident memory of process `pid` during the block, over its RSS before it
    (/proc/<pid>/clear_refs restarts VmHWM from VmRSS)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    before, peak = proc_bytes(pid, "VmRSS"), Peak()
    yield peak
    highest = proc_bytes(pid, "VmHWM")
    peak.mib, peak.total_mib = max(0, highest - before) >> 20, highest >> 20


def ascii_ply(root: Path, splats: int) -> dict:
    # The peak is reset (clear_refs 5) after the file is read, so VmHWM - VmRSS is the parse alone.
    code = ("import sys; from pathlib import Path; from phd_core.renderers.gs3d import parse_ply; "
            "from phd_core.allocator import keep_freed_memory; keep_freed_memory(); "     # as `phd` does
            "data = open(sys.argv[1], 'rb').read(); "
            "vm = lambda k: int(next(l for l in Path('/proc/self/status').read_text().splitlines() "
            "if l.startswith(k)).split()[1]) * 1024; "
            "Path('/proc/self/clear_refs').write_text('5'); b = vm('VmRSS'); parse_ply(data); print(vm('VmHWM') - b)")
    path = root / "ascii.ply"
    binary = root / "binary.ply"
    write_ply(svc_random_gaussians(splats, seed=3), binary)
    data = binary.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    import numpy as np
    names = [line.split()[-1] for line in data[:end].decode().splitlines() if line.startswith("property")]
    records = np.frombuffer(data[end:], dtype=[(n, "<f4") for n in names])
    with open(path, "wb") as f:
        f.write(data[:end].replace(b"binary_little_endian", b"ascii"))
        np.savetxt(f, np.stack([records[n] for n in names], 1), fmt="%.9g")
    extra = int(subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                               check=True).stdout)
    size = path.stat().st_size
    return {"splats": splats, "file_bytes": size, "parse_peak_over_file_read_bytes": extra,
            "ratio_to_file": round(extra / size, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=10_000)
    parser.add_argument("--splats", type=int, default=200_000)
    parser.add_argument("--folders", type=int, default=3000)
    parser.add_argument("--folder-budget", type=int, default=1 << 30, help="the folder fuzz's server's memory budget")
    parser.add_argument("--skip", nargs="*", default=[], choices=["fuzz", "ascii", "folders"])
    args = parser.parse_args()
    results = {"machine": machine()}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        ply, ply_b = root / "a.ply", root / "b.ply"
        write_ply(svc_random_gaussians(300, seed=0), ply)
        write_ply(svc_random_gaussians(200, seed=1), ply_b)
        if "ascii" not in args.skip:
            results["ascii_ply"] = ascii_ply(root, args.splats)
            print(json.dumps(results["ascii_ply"]), flush=True)
        if "fuzz" not in args.skip:
            results["fuzz"] = fuzz(args.requests, root, ply, ply_b)
            print(json.dumps(results["fuzz"]), flush=True)
        if "folders" not in args.skip:
            results["folders"] = folders(args.folders, args.folder_budget, root)
            print(json.dumps(results["folders"]), flush=True)
    only_folders = {"fuzz", "ascii"} <= set(args.skip)
    out = RESULTS / (f"reliability_folders_{args.folder_budget >> 20}mib.json" if only_folders else "reliability.json")
    write_result(out, results)
    print(f"wrote {out}; peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss} KiB")


if __name__ == "__main__":
    main()
