"""Test set-up: OpenMP wait policy, and the service fixtures (all named svc_*): real small
models on disk and real uvicorn servers on 127.0.0.1."""

from __future__ import annotations

import math
import os

# Before torch loads: idle OpenMP threads sleep instead of spinning (see phd_cli).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from phd_core.allocator import keep_freed_memory  # noqa: E402

keep_freed_memory()     # as the `phd` command and the service do (phd_core.allocator)
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import pytest
import torch

from phd_core.scene import Camera, look_at
from phd_core.renderers.gs3d import GaussianModel, write_ply

SVC_SIZE = 24  # test render size in pixels: small enough for 2 cores
LEGO = Path(__file__).resolve().parents[2] / "shared" / "data" / "lego_200"  # ../shared beside the checkout


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


@pytest.fixture(scope="session")
def svc_model_files(tmp_path_factory) -> dict[str, Path]:
    """Two random PLYs and a tiny NeRF checkpoint (with training cameras inside)."""
    from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, save_nerf

    root = tmp_path_factory.mktemp("svc_models")
    files = {"ply": root / "splats.ply", "ply_b": root / "splats_b.ply", "nerf": root / "tiny.nerf"}
    write_ply(svc_random_gaussians(300, seed=0), files["ply"])
    write_ply(svc_random_gaussians(200, seed=1), files["ply_b"])
    config = NeRFConfig(depth=2, width=16, color_width=8, pos_freqs=3, dir_freqs=1, samples=12,
                        grid_resolution=8, bounds=[[-1, -1, -1], [1, 1, 1]], near=1.0, far=5.0)
    save_nerf(NeRFRenderer(RadianceField(config, seed=0), training_cameras=svc_cameras(3, size=16)), files["nerf"])
    return files


def svc_free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def svc_start(tmp_path):
    """Factory: svc_start(**settings) -> a running in-process server (data dir under tmp_path by default)."""
    from service.runner import BackgroundServer
    from service.settings import Settings

    servers = []

    def start(**overrides) -> BackgroundServer:
        overrides.setdefault("data_dir", tmp_path / "data")
        server = BackgroundServer(Settings(**overrides))
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.stop()


class SvcProcess:
    """`phd serve` as a separate process (for tests that kill it)."""

    def __init__(self, data_dir: Path, start_timeout: float = 60, **env: str):
        self.port = svc_free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        # `phd serve` through its own CLI module (independent of the other commands' modules).
        code = ("import argparse, sys; from phd_cli import serve; parser = argparse.ArgumentParser(prog='phd'); "
                "serve.register(parser.add_subparsers()); args = parser.parse_args(sys.argv[1:]); "
                "sys.exit(args.func(args))")
        argv = ["serve", "--host", "127.0.0.1", "--port", str(self.port), "--data-dir", str(data_dir),
                "--log-level", "warning"]
        self.log = tempfile.TemporaryFile()
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
                self.log.seek(0)
                raise RuntimeError(f"phd serve did not start: {self.log.read().decode()[-2000:]}")
            time.sleep(0.1)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=30)
