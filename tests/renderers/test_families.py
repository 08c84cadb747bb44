"""A new model family is one module plus one registry entry.

The toy family below (blobs in a small JSON file behind a magic line) is registered in one
call, and is then recognised, loaded, uploaded, stored, calibrated and ranked by the library,
the real service and the client with no other change.
"""

from __future__ import annotations

import json

import pytest
import torch

from client import PHDClient, UnsupportedModelError
from phd_core import uq
from phd_core.renderers import FAMILIES, Family, load_model, load_model_bytes, model_kind
from support.fixtures import svc_cameras
from support.toy_renderers import BlobRenderer

MAGIC = b"PHD-TOY-BLOBS\n"


def toy_bytes(renderer: BlobRenderer) -> bytes:
    fields = {"means": renderer.means, "colors": renderer.colors, "opacities": renderer.opacities,
              "scales": renderer.scales}
    return MAGIC + json.dumps({k: v.tolist() for k, v in fields.items()}).encode()


def load_toy(data: bytes, name: str, cameras) -> BlobRenderer:
    fields = {k: torch.tensor(v) for k, v in json.loads(data[len(MAGIC):]).items()}
    return BlobRenderer(fields["means"], fields["colors"], fields["opacities"], fields["scales"],
                        training_cameras=cameras)


@pytest.fixture
def toy_family():
    family = FAMILIES.register(Family("toy", "a toy blob file", ".toy", lambda head: head.startswith(MAGIC), load_toy))
    yield family
    del FAMILIES["toy"]


@pytest.fixture
def toy_file(tmp_path):
    path = tmp_path / "blobs.bin"
    path.write_bytes(toy_bytes(BlobRenderer.random(20, seed=3)))
    return path


def test_the_library_loads_a_registered_family(toy_family, toy_file) -> None:
    data = toy_file.read_bytes()
    assert model_kind(data) == "toy" and model_kind(b"ply\n") == "3dgs"
    renderer = load_model(toy_file)
    assert isinstance(renderer, BlobRenderer) and renderer.num_units == 20
    cameras = svc_cameras(2)
    assert load_model_bytes(data, "x", training_cameras=cameras).training_cameras == cameras
    with pytest.raises(ValueError):
        FAMILIES.register(toy_family)


def test_an_unregistered_family_is_refused_by_name(toy_file) -> None:
    with pytest.raises(Exception) as info:
        load_model(toy_file)
    assert "neither a 3DGS PLY nor a phd NeRF checkpoint" in str(info.value)


def test_the_service_and_client_accept_a_registered_family(svc_start, toy_family, toy_file) -> None:
    server = svc_start()
    train, candidates = svc_cameras(3), svc_cameras(4, phase=0.3)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(toy_file, cameras=train)
        assert (info.kind, info.num_units, info.num_training_cameras) == ("toy", 20, 3)
        assert [p.name for p in server.settings.data_dir.rglob(f"{info.id}.*")] == [f"{info.id}.toy"]
        ranking = phd.rank(info.id, candidates, samples=4, dropout_ratio=0.3, top_k=2)
        expected = uq.rank_views(load_toy(toy_file.read_bytes(), "x", train), candidates, ratio=0.3,
                                 samples=4, top_k=2)
        assert [v.index for v in ranking.views] == [r.index for r in expected]
        assert phd.get_model(info.id).kind == "toy"


def test_the_service_refuses_an_unregistered_family(svc_start, toy_file) -> None:
    server = svc_start()
    with PHDClient(server.url) as phd, pytest.raises(UnsupportedModelError):
        phd.upload_model(toy_file, cameras=svc_cameras(2))
