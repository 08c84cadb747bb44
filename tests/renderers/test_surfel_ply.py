"""The 2DGS PLY layout (two scale columns): read from hand-made files, written, and told
apart from a 3DGS PLY by content in both directions."""

from __future__ import annotations

import json

import pytest
import torch

from phd_core.errors import InputError
from phd_core.renderers import FAMILIES, SNIFF_BYTES, load_model, load_model_bytes, model_kind
from phd_core.renderers.gs2d import SurfelModel, SurfelRenderer, parse_surfel_ply, read_surfel_ply, write_surfel_ply
from phd_core.renderers.gs3d import SIDECAR_FORMAT, GaussianModel, GaussianRenderer, parse_ply, sidecar_path, write_ply
from phd_core.scene.rotations import quaternion_to_rotation
from support.surfels import random_surfels, reference_layout_ply


def assert_same(a: SurfelModel, b: SurfelModel) -> None:
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def gaussians(count: int = 7) -> GaussianModel:
    g = torch.Generator().manual_seed(1)
    return GaussianModel(torch.randn(count, 3, generator=g), torch.randn(count, 3, generator=g) - 3,
                         torch.randn(count, 4, generator=g), torch.randn(count, generator=g),
                         torch.randn(count, 4, 3, generator=g))


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("degree", [0, 3])
def test_reads_the_reference_layout(fmt: str, degree: int) -> None:
    model = random_surfels(9, seed=degree, degree=degree)
    data = reference_layout_ply(model, fmt=fmt)
    assert model_kind(data[:SNIFF_BYTES]) == "2dgs"
    parsed = parse_surfel_ply(data)
    assert type(parsed) is SurfelModel and parsed.log_scales.shape == (9, 2) and parsed.sh_degree == degree
    assert_same(parsed, model)
    renderer = load_model_bytes(data, "hand.ply")
    assert isinstance(renderer, SurfelRenderer) and renderer.kind == "2dgs" and renderer.num_units == 9


def test_write_read_round_trip_and_the_written_header(tmp_path) -> None:
    model = random_surfels(11, seed=2, degree=2)
    path = tmp_path / "surfels.ply"
    write_surfel_ply(model, path)
    assert_same(read_surfel_ply(path), model)
    header = path.read_bytes().split(b"end_header")[0].decode()
    scales = [line for line in header.splitlines() if "scale_" in line]
    assert scales == ["property float scale_0", "property float scale_1"]
    assert path.read_bytes() == reference_layout_ply(model, comments=0), "the writer writes the reference layout"
    with pytest.raises(TypeError):
        write_surfel_ply(gaussians(), tmp_path / "x.ply")


def test_a_3dgs_ply_is_never_read_as_2dgs(tmp_path) -> None:
    path = tmp_path / "gaussians.ply"
    write_ply(gaussians(), path)
    data = path.read_bytes()
    assert model_kind(data[:SNIFF_BYTES]) == "3dgs"
    assert type(load_model(path)) is GaussianRenderer
    with pytest.raises(InputError) as info:
        parse_surfel_ply(data, "gaussians.ply")
    assert info.value.field == "ply.scale_2" and "gaussians.ply" in str(info.value)


def test_a_2dgs_ply_is_never_read_as_3dgs() -> None:
    data = reference_layout_ply(random_surfels(5))
    assert not FAMILIES["3dgs"].sniff(data[:SNIFF_BYTES])
    with pytest.raises(InputError) as info:
        parse_ply(data, "surfels.ply")
    assert info.value.field == "ply.scale_2"


def test_the_sniffs_are_exclusive() -> None:
    heads = [reference_layout_ply(random_surfels(3)), reference_layout_ply(random_surfels(3), fmt="ascii"),
             b"ply\n", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float scale_0\n",   # header cut short
             b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float scale_0\nend_header\n",
             b"ply\nformat ascii 1.0\nelement face 0\nproperty float scale_0\nproperty float scale_1\n"
             b"element vertex 0\nproperty float x\nend_header\n",     # scale columns on another element
             b"\x00\x01 random", b"PK\x03\x04"]
    with_ply = [reference_layout_ply(random_surfels(3)), b"ply\n"]
    kinds = []
    for head in heads:
        claims = [kind for kind, family in FAMILIES.items() if family.sniff(head[:SNIFF_BYTES])]
        assert len(claims) <= 1, (head[:60], claims)
        kinds.append(claims[0] if claims else None)
    assert kinds == ["2dgs", "2dgs", "3dgs", "3dgs", "3dgs", "3dgs", None, None]
    assert all(model_kind(h) for h in with_ply)


def test_a_2dgs_ply_with_a_sidecar_loads_its_training_cameras(tmp_path) -> None:
    from support.fixtures import svc_cameras
    path = tmp_path / "trained.ply"
    path.write_bytes(reference_layout_ply(random_surfels(20)))
    cameras = svc_cameras(3)
    sidecar_path(path).write_text(json.dumps({"format": SIDECAR_FORMAT, "background": [0.0, 0.0, 0.0],
                                              "training_cameras": [c.to_frame() for c in cameras]}))
    renderer = load_model(path)
    assert isinstance(renderer, SurfelRenderer) and len(renderer.training_cameras) == 3
    assert all(torch.allclose(a.c2w, b.c2w) and a.fx == b.fx for a, b in zip(renderer.training_cameras, cameras))
    assert renderer.background.tolist() == [0.0, 0.0, 0.0]


def test_bad_2dgs_content_names_the_field() -> None:
    data = reference_layout_ply(random_surfels(4))
    with pytest.raises(InputError) as info:
        parse_surfel_ply(data.replace(b"property float rot_3\n", b""), "cut.ply")
    assert info.value.field in ("ply.rot_3", "ply.vertex")
    nan = random_surfels(4)
    nan.log_scales[2, 1] = float("nan")
    with pytest.raises(InputError) as info:
        parse_surfel_ply(reference_layout_ply(nan))
    assert info.value.field == "ply.scale_1" and "vertex 2" in str(info.value)


def test_surfel_covariances_are_flat_along_the_normal() -> None:
    """Viewers draw 2DGS surfels from `covariances()`: rank 2, the normal (third rotation
    axis) in its null space, the two tangent axes scaled by the surfel's scales."""
    model = random_surfels(20, seed=3)
    cov = model.covariances()                                                   # [G, 3, 3]
    rot = quaternion_to_rotation(model.quats.double())
    scales = model.log_scales.double().exp()
    assert cov.shape == (20, 3, 3) and torch.allclose(cov, cov.transpose(1, 2))
    normal = rot[:, :, 2]
    assert (cov @ normal[..., None]).abs().max() < 1e-12
    for axis in (0, 1):
        along = (cov @ rot[:, :, axis, None])[..., 0]
        assert torch.allclose(along, scales[:, axis, None] ** 2 * rot[:, :, axis], atol=1e-12)
