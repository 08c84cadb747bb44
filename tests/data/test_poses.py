"""Poses handed back in their source's convention (`phd_core.data.POSES`): each converter
round-trips through the project's own loader to 1e-9, agrees with the conventions as the
test captures write them (tests/support/captures.py, written from the formats' definitions),
and a batch exported as files loads back as the same cameras."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from phd_core.data import POSES, export_cameras, export_convention, load_blender, load_cameras, source_pose
from phd_core.data.colmap import qvec_to_rotation, rotation_to_qvec
from phd_core.data.inria import camera_from_entry
from phd_core.errors import InputError
from phd_core.scene import Camera, camera_from_frame
from support.captures import colmap_pose as written_colmap_pose
from support.captures import inria_entries

GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def random_cameras(count: int, seed: int = 0, centred: bool = False) -> list[Camera]:
    """Cameras with random rotations (QR of a Gaussian matrix), among them rotations by nearly
    180 degrees, where w of the quaternion is near 0 and a careless inverse loses digits."""
    g = torch.Generator().manual_seed(seed)
    cameras = []
    for i in range(count):
        q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        rotation = q * torch.sign(torch.diagonal(r))
        if torch.det(rotation) < 0:
            rotation[:, 0] *= -1
        if i % 3 == 2:                                  # a half turn about a random axis, nudged by 1e-7
            axis = torch.randn(3, generator=g, dtype=torch.float64)
            axis = axis / axis.norm()
            rotation = 2 * torch.outer(axis, axis) - torch.eye(3, dtype=torch.float64)
            angle = 1e-7
            twist = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0],
                                  [0, 0, 1]], dtype=torch.float64)
            rotation = rotation @ twist
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3], c2w[:3, 3] = rotation, torch.randn(3, generator=g, dtype=torch.float64) * 5
        width, height = 64 + 8 * i, 48 + 4 * i
        cx, cy = (width / 2, height / 2) if centred else (width / 2 + 3.25, height / 2 - 1.5)
        cameras.append(Camera(c2w, 50.0 + i, 51.5 + i, cx, cy, width, height))
    return cameras


def assert_same_cameras(got: list[Camera], expected: list[Camera], tol: float = 1e-9) -> None:
    assert len(got) == len(expected)
    for a, b in zip(got, expected):
        assert (a.c2w - b.c2w).abs().max().item() <= tol
        assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == pytest.approx((b.fx, b.fy, b.cx, b.cy, b.width,
                                                                             b.height), abs=tol)


def test_colmap_qvec_and_tvec_round_trip_to_1e9() -> None:
    for camera in random_cameras(12):
        pose = source_pose(camera, "colmap")
        assert pose["format"] == "colmap" and pose["qvec"][0] >= 0
        assert sum(v * v for v in pose["qvec"]) == pytest.approx(1.0, abs=1e-12)
        rotation = qvec_to_rotation(pose["qvec"])                          # world -> camera, as the loader reads it
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = rotation.T
        c2w[:3, 3] = -rotation.T @ torch.tensor(pose["tvec"], dtype=torch.float64)
        assert ((c2w @ GL_TO_CV) - camera.c2w).abs().max().item() < 1e-9
        assert pose["camera"] == {"model": "PINHOLE", "width": camera.width, "height": camera.height,
                                  "params": [camera.fx, camera.fy, camera.cx, camera.cy]}
        # The same pose as the test captures write COLMAP files (q and -q are one rotation).
        qvec, tvec = written_colmap_pose(camera)
        sign = 1.0 if qvec[0] >= 0 else -1.0
        assert np.allclose(pose["qvec"], sign * np.array(qvec), atol=1e-9)
        assert np.allclose(pose["tvec"], tvec, atol=1e-9)


def test_rotation_to_qvec_of_known_rotations() -> None:
    quarter_z = torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)   # +90 degrees about z
    assert rotation_to_qvec(quarter_z) == pytest.approx([math.sqrt(0.5), 0, 0, math.sqrt(0.5)], abs=1e-15)
    half_x = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))            # 180 degrees about x
    assert rotation_to_qvec(half_x) == pytest.approx([0, 1, 0, 0], abs=1e-15)
    assert rotation_to_qvec(torch.eye(3, dtype=torch.float64)) == [1.0, 0.0, 0.0, 0.0]


def test_cameras_json_and_transforms_entries_round_trip() -> None:
    cameras = random_cameras(6, seed=1, centred=True)              # cameras.json has no principal point
    for camera, written in zip(cameras, inria_entries(cameras)):
        entry = source_pose(camera, "3dgs-output")
        assert entry.pop("format") == "3dgs-output"
        assert np.allclose(entry["rotation"], written["rotation"], atol=1e-12)
        assert np.allclose(entry["position"], written["position"], atol=1e-12)
        assert_same_cameras([camera_from_entry(entry)], [camera])
    frames = [source_pose(c, "nerfstudio") for c in cameras]
    assert {f.pop("format") for f in frames} == {"nerfstudio"}
    assert_same_cameras([camera_from_frame(f) for f in frames], cameras, tol=0.0)
    blender = [source_pose(c, "blender") for c in cameras]             # a field of view, not a focal length
    assert {f.pop("format") for f in blender} == {"blender"} and not any("fl_x" in f for f in blender)
    assert_same_cameras([camera_from_frame(f) for f in blender], cameras)
    assert source_pose(cameras[0], None) is None and source_pose(cameras[0], "llff") is None


@pytest.mark.parametrize("name, convention, split", [
    ("transforms.json", "nerfstudio", "train"), ("cameras.json", "3dgs-output", "train"),
    ("next_batch", "colmap", "all"),
])
def test_an_exported_batch_loads_back_as_the_same_cameras(tmp_path, name, convention, split) -> None:
    cameras = random_cameras(9, seed=2, centred=convention == "3dgs-output")
    names = [f"rank{k:03d}_candidate{k * 7:04d}.png" for k in range(len(cameras))]
    written = export_cameras(tmp_path / name, cameras, names)
    assert written.name == convention
    # COLMAP's "train" split would hold every 8th image out: the whole batch is "all".
    assert_same_cameras(load_cameras(tmp_path / name, split=split), cameras)
    if convention == "nerfstudio":
        frames = json.loads((tmp_path / name).read_text())["frames"]
        assert [f["file_path"] for f in frames] == [f"images/{n}" for n in names]
    if convention == "colmap":
        assert sorted(p.name for p in (tmp_path / name).iterdir()) == ["cameras.txt", "images.txt", "points3D.txt"]


def test_a_blender_export_is_what_the_blender_loader_reads(tmp_path) -> None:
    """transforms_train.json as NeRF-synthetic has it: camera_angle_x = 2 atan(W / (2 fx)) once
    at the top (no fl_x), the project's OpenGL camera-to-world matrices, ./images/<name>
    without the suffix; `load_blender` reads back the same cameras; lenses that one
    camera_angle_x cannot state are refused, naming the pose."""
    width, height, fx = 80, 60, 55.0
    cameras = [Camera(c.c2w, fx, fx, width / 2, height / 2, width, height) for c in random_cameras(5, seed=3)]
    names = [f"rank{k:03d}_candidate{k * 3:04d}.png" for k in range(1, 6)]
    written = export_cameras(tmp_path / "transforms_train.json", cameras, names)     # the name says Blender
    assert written.name == "blender"
    data = json.loads((tmp_path / "transforms_train.json").read_text())
    assert data["camera_angle_x"] == pytest.approx(2 * math.atan(width / (2 * fx)), abs=1e-15)
    assert "fl_x" not in data and "camera_model" not in data and all(set(f) == {"file_path", "transform_matrix"}
                                                                     for f in data["frames"])
    assert [f["file_path"] for f in data["frames"]] == [f"./images/rank{k:03d}_candidate{k * 3:04d}" for k in
                                                        range(1, 6)]
    assert_same_cameras(load_blender(tmp_path, "train", with_images=False).cameras, cameras)
    odd = [Camera(c.c2w, 50.0, 52.0, 41.0, 29.5, width, height) for c in cameras[:2]]   # kept, not squared up
    export_cameras(tmp_path / "odd" / "transforms_train.json", odd, names[:2])
    assert_same_cameras(load_blender(tmp_path / "odd", "train", with_images=False).cameras, odd)
    with pytest.raises(InputError) as info:
        export_cameras(tmp_path / "mixed.json", [cameras[0], odd[0]], names[:2], "blender")
    assert info.value.field == "cameras[1]" and "camera_angle_x" in info.value.reason


def test_the_export_format_comes_from_the_name_or_the_flag(tmp_path) -> None:
    assert export_convention(tmp_path / "plan.json").name == "nerfstudio"
    assert export_convention(tmp_path / "Cameras.json").name == "3dgs-output"
    assert export_convention(tmp_path / "sparse0").name == "colmap"
    assert export_convention(tmp_path / "plan.json", "blender").name == "blender"
    assert export_convention(tmp_path / "transforms_train.json").name == "blender"
    with pytest.raises(InputError) as info:
        export_convention(tmp_path / "plan.yaml")
    assert info.value.field == "export" and "plan.yaml" in info.value.reason
    with pytest.raises(InputError) as info:
        export_convention(tmp_path / "plan.json", "ply")
    assert info.value.field == "export_format" and "colmap" in info.value.reason
    with pytest.raises(InputError) as info:
        export_cameras(tmp_path / "x.json", random_cameras(2), ["a.png"])
    assert info.value.field == "export"
    assert set(POSES) >= {"colmap", "3dgs-output", "nerfstudio", "blender"}
