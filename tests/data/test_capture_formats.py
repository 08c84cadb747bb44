"""COLMAP (text and binary), LLFF and the reference 3DGS trainer's output folder: round trips
through files written by the tests, known poses from the real cup_colmap capture, and a clear
error naming the file and the field for anything malformed."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from phd_core.data import FORMATS, load_cameras, load_dataset, split_size
from phd_core.data.colmap import image_camera, read_model
from phd_core.data.inria import read_output_folder
from phd_core.errors import InputError
from phd_core.renderers import load_model
from phd_core.scene import Camera, look_at
from support.captures import inria_entries, write_colmap, write_llff, write_output_folder

CUP = Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap"


def capture_cameras(count: int = 9, width: int = 12, height: int = 8) -> list[Camera]:
    """Look-at cameras around the origin with fx != fy and an off-centre principal point."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        c = look_at((3 * math.cos(a), 3 * math.sin(a), 1 + 0.2 * i), (0.1, -0.2, 0.3), width=width, height=height,
                    fov_x=0.9)
        cams.append(Camera(c.c2w, c.fx, c.fx * 1.1, c.cx + 0.7, c.cy - 0.4, width, height))
    return cams


def images_for(cameras: list[Camera]) -> list[np.ndarray]:
    return [np.full((c.height, c.width, 3), 0.1 * (i % 9)) for i, c in enumerate(cameras)]


def assert_same_cameras(loaded: list[Camera], expected: list[Camera], atol: float = 1e-9) -> None:
    assert len(loaded) == len(expected)
    for a, b in zip(loaded, expected):
        assert torch.allclose(a.c2w, b.c2w, atol=atol)
        assert (a.width, a.height) == (b.width, b.height)
        assert [a.fx, a.fy, a.cx, a.cy] == pytest.approx([b.fx, b.fy, b.cx, b.cy], abs=1e-9)


# ----------------------------------------------------------------------------- COLMAP

@pytest.mark.parametrize("binary", [False, True])
def test_colmap_round_trip_with_splits_images_and_points(tmp_path, binary) -> None:
    cameras = capture_cameras()
    points = np.array([[0.0, 0.1, 0.2], [0.5, -0.5, 0.25]])
    write_colmap(tmp_path, cameras, binary=binary, points=points, images=images_for(cameras))
    everything = load_dataset(tmp_path, "all")
    assert_same_cameras(everything.cameras, cameras)
    assert everything.names == [f"{i:03d}.png" for i in range(9)]
    assert torch.allclose(everything.points, torch.from_numpy(points))
    assert torch.allclose(everything.point_colors, torch.tensor([200, 100, 50]) / 255.0)
    images = torch.stack(everything.images)
    assert everything.alphas is None and images.shape == (9, 8, 12, 3)
    assert torch.allclose(images[:, 0, 0, 0], torch.tensor([0.1 * i for i in range(9)]), atol=1 / 255)
    # LLFF-style hold-out: every 8th image by name is a test view.
    assert load_dataset(tmp_path, "test", with_images=False).names == ["000.png", "008.png"]
    train = load_dataset(tmp_path / "sparse" / "0", "train", with_images=False, downscale=2)
    assert train.names == [f"{i:03d}.png" for i in range(1, 8)] and train.cameras[0].width == 6
    assert split_size(tmp_path, "train") == 7
    # The SfM points decide near/far: both lie in front of every camera.
    assert 0 < everything.near < everything.far


def test_colmap_known_pose_written_by_hand(tmp_path) -> None:
    """Identity rotation, t = (0, 0, 4): the camera sits at (0, 0, -4) looking down +z (OpenCV)."""
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 SIMPLE_PINHOLE 40 30 50 20 15\n")
    (sparse / "images.txt").write_text("# comment\n1 1 0 0 0 0 0 4 1 a.jpg\n10 12 -1\n")
    (camera,) = load_dataset(tmp_path, "all", with_images=False).cameras
    assert camera.center.tolist() == [0, 0, -4]
    assert camera.c2w[:3, 2].tolist() == [0, 0, -1]                   # OpenGL looks down -z: world +z
    assert camera.c2w[:3, 1].tolist() == [0, -1, 0]                   # up = -y (COLMAP's y points down)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (50, 50, 20, 15)
    uv, depth = camera.project(torch.tensor([[0.4, 0.3, 1.0]], dtype=torch.float64))
    assert uv[0].tolist() == pytest.approx([20 + 50 * 0.4 / 5, 15 + 50 * 0.3 / 5]) and depth.item() == 5


def test_colmap_cup_reprojects_its_own_sfm_points() -> None:
    """The real capture: projecting each SfM point with our camera lands on COLMAP's keypoint."""
    model = read_model(CUP / "sparse" / "0")
    assert len(model.images) == 77 and len(model.points) == 9262
    index = {int(p): k for k, p in enumerate(model.point_ids)}
    errors = []
    for image in model.images[::7]:
        camera = image_camera(model, image, "images.bin")
        seen = image.point3d_ids >= 0
        points = torch.from_numpy(model.points[[index[int(p)] for p in image.point3d_ids[seen]]])
        uv, depth = camera.project(points)
        assert (depth > 0).all()
        errors.append((uv - torch.from_numpy(image.xys[seen])).norm(dim=1))
    errors = torch.cat(errors)
    assert len(errors) > 1000 and errors.median() < 1.0 and torch.quantile(errors, 0.95) < 3.0


def test_cup_loads_as_colmap_and_as_llff_with_the_same_poses() -> None:
    colmap = load_dataset(CUP, "all", with_images=False)
    llff = load_dataset(CUP / "poses_bounds.npy", "all", with_images=False)
    assert colmap.names == llff.names and len(colmap.cameras) == 77
    for a, b in zip(colmap.cameras, llff.cameras):
        assert torch.allclose(a.c2w, b.c2w, atol=1e-9)
    assert (colmap.cameras[0].width, colmap.cameras[0].height) == (800, 600)
    assert colmap.cameras[0].fx == pytest.approx(llff.cameras[0].fx)
    assert split_size(CUP, "train") == 67 and split_size(CUP, "test") == 10
    test = load_dataset(CUP, "test", downscale=10, views=[0])
    assert torch.stack(test.images).shape == (1, 60, 80, 3) and test.names == ["1.jpg"]


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_models_with_zero_distortion_are_pinholes(tmp_path, binary) -> None:
    """Zero coefficients: the camera as written, no undistortion (which would crop a pixel); a
    fisheye with zero coefficients is still a fisheye (tests/data/test_undistort.py)."""
    write_colmap(tmp_path, capture_cameras(2), binary=binary, model="OPENCV", extra=(0, 0, 0, 0))
    assert_same_cameras(load_dataset(tmp_path, "all", with_images=False).cameras, capture_cameras(2))
    write_colmap(tmp_path, capture_cameras(2), binary=binary, model="OPENCV_FISHEYE", extra=(0, 0, 0, 0))
    fisheye = load_dataset(tmp_path, "all", with_images=False).cameras
    assert (fisheye[0].width, fisheye[0].height) != (12, 8)


def test_malformed_colmap_files_name_the_file(tmp_path) -> None:
    sparse = write_colmap(tmp_path, capture_cameras(3), binary=True)
    data = (sparse / "images.bin").read_bytes()
    (sparse / "images.bin").write_bytes(data[:-20])
    with pytest.raises(InputError) as info:
        load_dataset(tmp_path, "all", with_images=False)
    assert info.value.field == "images.bin" and "ends early" in info.value.reason
    (sparse / "images.bin").write_bytes(data)
    (sparse / "cameras.bin").write_bytes(struct.pack("<QiiQQ", 1, 1, 99, 8, 8))
    with pytest.raises(InputError, match="unknown camera model id 99"):
        load_dataset(tmp_path, "all", with_images=False)

    text = tmp_path / "text"
    sparse = write_colmap(text, capture_cameras(3), binary=False)
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 x 1 a.png\n\n")
    with pytest.raises(InputError) as info:
        load_dataset(text, "all", with_images=False)
    assert info.value.field == "images.txt" and "line 1" in info.value.reason
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 4 7 a.png\n\n")
    with pytest.raises(InputError, match="camera_id 7"):
        load_dataset(text, "all", with_images=False)
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 4 1 a.png\n\n")
    with pytest.raises(InputError) as info:
        load_dataset(text, "all")                        # no images folder beside the model
    assert info.value.field == "images"
    with pytest.raises(InputError) as info:
        load_dataset(text, "val", with_images=False)
    assert info.value.field == "split"


# ----------------------------------------------------------------------------- LLFF

def test_llff_round_trip_bounds_and_downscaled_images(tmp_path) -> None:
    cameras = [Camera(c.c2w, c.fx, c.fx, 6, 4, 12, 8) for c in capture_cameras()]
    npy = write_llff(tmp_path, cameras, bounds=(1.5, 7.0), images=images_for(cameras))
    data = load_dataset(tmp_path, "all")
    assert_same_cameras(data.cameras, cameras)
    assert (data.near, data.far) == (1.5, 7.0) and torch.stack(data.images).shape == (9, 8, 12, 3)
    assert load_dataset(npy, "test", with_images=False).indices == [0, 1]
    # poses_bounds made for images twice as large: intrinsics follow the image files.
    big = [Camera(c.c2w, 2 * c.fx, 2 * c.fx, 12, 8, 24, 16) for c in cameras]
    write_llff(tmp_path, big)
    assert_same_cameras(load_dataset(tmp_path, "all").cameras, cameras)


def test_malformed_llff_files_name_the_field(tmp_path) -> None:
    cameras = [Camera(c.c2w, c.fx, c.fx, 6, 4, 12, 8) for c in capture_cameras(3)]
    npy = write_llff(tmp_path, cameras)
    rows = np.load(npy)
    for bad, field in ((rows[:, :15], "poses_bounds.npy"), (np.where(np.arange(17) == 3, np.nan, rows), "[0]"),
                       (np.concatenate([rows[:, :15], [[5, 1]] * 3], 1), "[0].bounds")):
        np.save(npy, bad)
        with pytest.raises(InputError) as info:
            load_dataset(tmp_path, "all", with_images=False)
        assert info.value.field.startswith("poses_bounds.npy") and info.value.field.endswith(field)
    np.save(npy, np.array([{"a": 1}], dtype=object))      # a pickle is never loaded
    with pytest.raises(InputError, match="cannot read"):
        load_dataset(tmp_path, "all", with_images=False)
    skew = rows.copy()
    skew[0, 0] = 3.0                                       # not a rotation
    np.save(npy, skew)
    with pytest.raises(InputError) as info:
        load_dataset(tmp_path, "all", with_images=False)
    assert info.value.field == "poses_bounds.npy[0].pose"


# ----------------------------------------------------------------------------- reference 3DGS output folder

def test_output_folder_latest_iteration_cameras_and_eval_split(tmp_path) -> None:
    from support.fixtures import svc_random_gaussians

    cameras = capture_cameras(9)
    centred = [Camera(c.c2w, c.fx, c.fy, c.width / 2, c.height / 2, c.width, c.height) for c in cameras]
    folder = write_output_folder(tmp_path / "out", svc_random_gaussians(30), cameras, iterations=(7000, 30000, 500))
    found = read_output_folder(folder)
    assert found.iteration == 30000 and found.ply.parent.name == "iteration_30000"
    assert_same_cameras(found.cameras, centred)        # the trainer assumes a centred principal point
    assert found.background == (0.0, 0.0, 0.0)
    renderer = load_model(folder)
    assert renderer.num_units == 30 and renderer.background.tolist() == [0, 0, 0]
    assert_same_cameras(renderer.training_cameras, centred)
    assert read_output_folder(folder, iteration=7000).ply.parent.name == "iteration_7000"
    with pytest.raises(InputError) as info:
        read_output_folder(folder, iteration=1)
    assert info.value.field == "iteration" and "7000" in info.value.reason
    assert load_dataset(folder, "train", with_images=False).cameras[0].width == 12
    assert FORMATS["3dgs-output"].locate(folder, "train") == folder

    # An --eval run: cameras.json lists the test views too; every 8th name is left out.
    write_output_folder(tmp_path / "eval", svc_random_gaussians(30), cameras, eval_split=True, white=True)
    found = read_output_folder(tmp_path / "eval")
    assert len(found.cameras) == 7 and found.names == [f"{i:03d}" for i in range(1, 8)]
    assert found.background == (1.0, 1.0, 1.0)


def test_known_pose_of_a_cameras_json_entry() -> None:
    """position is the centre; rotation's columns are the camera's x right, y down, z forward."""
    entry = {"id": 0, "img_name": "a", "width": 40, "height": 30, "position": [1, 2, 3], "fx": 50, "fy": 40,
             "rotation": [[1, 0, 0], [0, 0, 1], [0, -1, 0]]}   # columns: x, down = world -z, forward = world +y
    (camera,) = load_cameras([entry])
    assert camera.center.tolist() == [1, 2, 3]
    assert (-camera.c2w[:3, 2]).tolist() == [0, 1, 0] and camera.c2w[:3, 1].tolist() == [0, 0, 1]
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (50, 40, 20, 15)


def test_malformed_cameras_json_names_the_entry_and_key(tmp_path) -> None:
    cameras = capture_cameras(2)
    entries = inria_entries(cameras)
    for change, field in (({"rotation": [[1, 0], [0, 1]]}, "frames[1].rotation"),
                          ({"rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}, "frames[1].rotation"),
                          ({"fx": "wide"}, "frames[1].fx"), ({"width": -3}, "frames[1].width")):
        with pytest.raises(InputError) as info:
            load_cameras([entries[0], {**entries[1], **change}])
        assert info.value.field == field
    folder = write_output_folder(tmp_path / "out", __import__("conftest").svc_random_gaussians(5), cameras)
    (folder / "cameras.json").write_text("[{")
    with pytest.raises(InputError) as info:
        load_model(folder)
    assert info.value.field == "cameras.json"
    bad = [entries[0], {k: v for k, v in entries[1].items() if k != "position"}]
    (folder / "cameras.json").write_text(json.dumps(bad))
    with pytest.raises(InputError) as info:
        load_model(folder)
    assert info.value.field == "cameras.json[1].position"
    with pytest.raises(InputError) as info:
        load_model(tmp_path)                                # a folder with no point_cloud/
    assert info.value.field == "model"


def test_load_cameras_reads_every_format(tmp_path) -> None:
    cameras = [Camera(c.c2w, c.fx, c.fx, 6, 4, 12, 8) for c in capture_cameras(3)]
    write_colmap(tmp_path / "colmap", cameras, binary=True)
    write_llff(tmp_path / "llff", cameras)
    (tmp_path / "frames.json").write_text(json.dumps([c.to_frame() for c in cameras]))
    (tmp_path / "cameras.json").write_text(json.dumps(inria_entries(cameras)))
    for source in (tmp_path / "colmap", tmp_path / "llff" / "poses_bounds.npy", tmp_path / "frames.json",
                   tmp_path / "cameras.json"):
        assert_same_cameras(load_cameras(source, split="all"), cameras)


def test_cameras_json_made_from_the_real_cup_model_as_the_trainer_does() -> None:
    """The reference trainer writes cameras.json from COLMAP's pose: R = qvec2rotmat(q)^T,
    T = t, Rt = [R^T | T], and stores inv(Rt)'s rotation and translation. Done here with numpy
    from the raw images.bin values, it must give the COLMAP loader's cameras."""
    model = read_model(CUP / "sparse" / "0", with_points=False)
    entries = []
    for image in model.images[:10]:
        w, x, y, z = np.array(image.qvec) / np.linalg.norm(image.qvec)
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]).T
        rt = np.eye(4)
        rt[:3, :3], rt[:3, 3] = r.T, image.tvec
        c2w = np.linalg.inv(rt)
        cam = model.cameras[image.camera_id]
        entries.append({"id": len(entries), "img_name": image.name, "width": cam.width, "height": cam.height,
                        "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
                        "fy": cam.params[0], "fx": cam.params[0]})
    from_json = load_cameras(entries)
    from_colmap = load_dataset(CUP, "all", with_images=False).cameras[:10]
    assert_same_cameras(from_json, from_colmap, atol=1e-9)
