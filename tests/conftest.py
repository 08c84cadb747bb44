"""Test set-up: the process settings of the entry points (before torch loads), and the
service fixtures (all named svc_*): real small models on disk and real uvicorn servers on
127.0.0.1. What tests share besides fixtures is in tests/support (no test imports this file)."""

from __future__ import annotations

import os

# Before torch loads: idle OpenMP threads sleep instead of spinning (see phd_cli).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from phd_core.allocator import keep_freed_memory  # noqa: E402

keep_freed_memory()     # as the `phd` command and the service do (phd_core.allocator)

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from phd_core.renderers.gs3d import write_ply  # noqa: E402
from support.fixtures import svc_cameras, svc_random_gaussians  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def phd_cache_dir(tmp_path_factory):
    """Undistorted photos (phd_core.data.undistort) go to a folder of the test session, never to ~/.cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PHD_CACHE_DIR", str(tmp_path_factory.mktemp("phd_cache")))
        yield


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


@pytest.fixture(scope="session")
def svc_trained(tmp_path_factory) -> Path:
    """A 3DGS model written by `phd train` (4 lego views at 100 px, 15 iterations: a few seconds),
    with the sidecar model.json it writes beside the PLY."""
    from phd_cli import main
    from support.fixtures import LEGO

    out = tmp_path_factory.mktemp("svc_trained") / "model.ply"
    assert main(["train", "--data", str(LEGO), "--views", "4", "--downscale", "8", "--iterations", "15",
                 "--out", str(out), "--quiet"]) == 0
    return out


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
