"""Issue 36's full-disk case, as the reliability probe ran it: the data directory on a 12 MB
tmpfs and 2.5 MB uploads one after another, with and without a free-space reserve. Prints each
answer, what is stored, whether a delete and the next upload then work, and the tracebacks in
the service's log (needs root to mount the tmpfs).

    sudo nice -n 10 .venv/bin/python -m bench.bench_full_disk [--keep-free 0 4194304]

Writes bench/results/full_disk.json (docs/reliability.md, Figures).
"""

from __future__ import annotations

import argparse
import io
import logging
import subprocess
import tempfile
from pathlib import Path

import httpx

from bench._harness import RESULTS, command, machine, write_result
from phd_core.renderers.gs3d import write_ply
from service.runner import BackgroundServer
from service.settings import Settings
from tests.support.fixtures import svc_random_gaussians

UPLOADS = 7


def run(keep_free: int, ply: Path, root: Path) -> dict:
    disk = root / f"disk-{keep_free}"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=12m", "tmpfs", str(disk)], check=True)
    log = io.StringIO()
    handler = logging.StreamHandler(log)
    logging.getLogger("phd.service").addHandler(handler)
    try:
        with BackgroundServer(Settings(data_dir=disk / "data", keep_free_bytes=keep_free)) as server:
            answers = [httpx.post(f"{server.url}/v1/models", files={"file": ("m.ply", ply.read_bytes())}, timeout=60)
                       for _ in range(UPLOADS)]
            stored = [m["id"] for m in httpx.get(f"{server.url}/v1/models").json()["models"]]
            deleted = httpx.delete(f"{server.url}/v1/models/{stored[0]}").status_code
            after = httpx.post(f"{server.url}/v1/models", files={"file": ("m.ply", ply.read_bytes())}, timeout=60)
        refused = [a.json()["error"] for a in answers if a.status_code >= 400]
        return {"keep_free_bytes": keep_free, "statuses": [a.status_code for a in answers], "stored": len(stored),
                "first_refusal": refused[0] if refused else None, "delete": deleted,
                "upload_after_delete": after.status_code, "tracebacks": log.getvalue().count("Traceback")}
    finally:
        logging.getLogger("phd.service").removeHandler(handler)
        subprocess.run(["umount", "-l", str(disk)], check=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep-free", type=int, nargs="+", default=[0, 4 << 20], help="PHD_KEEP_FREE_BYTES values")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="phd-full-disk-"))
    ply = root / "m.ply"
    write_ply(svc_random_gaussians(24_000, seed=0), ply)         # 2.5 MB
    runs = [run(keep, ply, root) for keep in args.keep_free]
    for r in runs:
        print(r)
    write_result(RESULTS / "full_disk.json", {"command": command(), "machine": machine(), "file_bytes":
                                              ply.stat().st_size, "disk": "tmpfs size=12m", "runs": runs})


if __name__ == "__main__":
    main()
