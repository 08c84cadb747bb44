"""What the tests share (and bench/bench_memory.py and bench/bench_reliability.py): the data
set beside the checkout, ring cameras, a random splat cloud, free ports, `phd serve` in its own
process, and the check of an error answer's shape. The pytest fixtures built on them are in
tests/conftest.py."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import torch

from phd_core.renderers.gs3d import GaussianModel
from phd_core.scene import Camera, look_at

SVC_SIZE = 24  # test render size in pixels: small enough for 2 cores
LEGO = Path(__file__).resolve().parents[3] / "shared" / "data" / "lego_200"  # ../shared beside the checkout


def svc_cameras(count: int, *, radius: float = 3.0, size: int = SVC_SIZE, phase: float = 0.0) -> list[Camera]:
    """Cameras on a tilted ring around the origin, all looking at it."""
    cams = []
    for i in range(count):
        a = phase + 2 * math.pi * i / count
        eye = (radius * math.cos(a), radius * math.sin(a), 0.8 + 0.3 * math.sin(3 * a))
        cams.append(look_at(eye, (0, 0, 0), (0, 0, 1), width=size, height=size, fov_x=0.7))
    return cams


def svc_random_gaussians(count: int = 300, seed: int = 0) -> GaussianModel:
    """A random SH-degree-1 splat cloud in [-0.6, 0.6]^3, visible from `svc_cameras`."""
    g = torch.Generator().manual_seed(seed)
    return GaussianModel(
        means=(torch.rand(count, 3, generator=g) - 0.5) * 1.2,
        log_scales=torch.log(0.03 + 0.07 * torch.rand(count, 3, generator=g)),
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.rand(count, generator=g) * 4 - 1,
        sh=torch.randn(count, 4, 3, generator=g) * 0.5,
    )


def svc_free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SvcProcess:
    """`phd serve` as a separate process (for tests that kill it or measure its memory), run
    as users run it (`phd_cli.main`); its log (stderr) goes to a temporary file, or to `log`."""

    def __init__(self, data_dir: Path, start_timeout: float = 60, log: Path | None = None, **env: str):
        self.port = svc_free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        code = "import sys; from phd_cli import main; sys.exit(main(sys.argv[1:]))"
        argv = ["serve", "--host", "127.0.0.1", "--port", str(self.port), "--data-dir", str(data_dir),
                "--log-level", "warning"]
        self.log = tempfile.TemporaryFile() if log is None else open(log, "wb")
        self.proc = subprocess.Popen([sys.executable, "-c", code, *argv],
                                     env={**{k: v for k, v in os.environ.items() if not k.startswith("PHD_")}, **env},
                                     stdout=subprocess.DEVNULL, stderr=self.log)
        deadline = time.monotonic() + start_timeout
        while True:
            try:
                if httpx.get(self.url + "/health", timeout=1).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.kill()
                if log is not None:
                    raise RuntimeError(f"phd serve did not start (its log went to {log})")
                self.log.seek(0)
                raise RuntimeError(f"phd serve did not start: {self.log.read().decode()[-2000:]}")
            time.sleep(0.1)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=30)


def proc_bytes(pid: int, key: str) -> int:
    """A /proc/<pid>/status figure in bytes (VmRSS, VmHWM)."""
    line = next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines() if line.startswith(key + ":"))
    return int(line.split()[1]) * 1024


def expect_error(response: httpx.Response, status: int, code: str | None = None, field: str | None = None) -> dict:
    """Assert the status and the error shape; return the error object."""
    assert response.status_code == status, response.text
    body = response.json()
    assert set(body) == {"error"} and set(body["error"]) == {"code", "message", "field"}
    error = body["error"]
    assert isinstance(error["code"], str) and isinstance(error["message"], str) and error["message"]
    if code is not None:
        assert error["code"] == code
    if field is not None:
        assert error["field"] == field
    return error
