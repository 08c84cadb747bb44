"""COLMAP captures as cameras and phones make them: every distorted camera model, photos at
another size than their cameras, views of several sizes. The captures are real files: COLMAP
binary models written by pycolmap, photos rendered from a known scene through the camera
model's distortion (tests/support/distorted.py), and the four real captures in
../shared/data/real/. Undistorted photos are compared with the scene rendered directly at the
undistorted camera pycolmap gives."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import pytest
import torch
import torch.nn.functional as F

from phd_core.data import frames as frames_module
from phd_core.data import load_dataset
from phd_core.data import undistort as undistort_module
from phd_core.data.colmap import read_model
from phd_core.errors import InputError, ModelNote, ModelWarning
from phd_core.eval import psnr
from support.captures import write_llff
from support.cli import run
from support.distorted import (
    CAMERA_MODELS,
    HEIGHT,
    WIDTH,
    View,
    pinhole_render,
    ring_pose,
    scene,
    undistorted,
    write_capture,
)

REAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "real"
# Beside the nine distorted models, a portrait and a landscape pinhole: views of several sizes.
PINHOLES = {"PINHOLE": (72, 96, [70, 70, 36, 48]), "SIMPLE_PINHOLE": (96, 72, [70, 48, 36])}


def capture_views() -> list[View]:
    cameras = [pycolmap.Camera(model=m, width=WIDTH, height=HEIGHT, params=p) for m, p in CAMERA_MODELS.items()]
    cameras += [pycolmap.Camera(model=m, width=w, height=h, params=p) for m, (w, h, p) in PINHOLES.items()]
    return [View(f"{i:02d}_{c.model.name}.png", ring_pose(i, len(cameras)), c) for i, c in enumerate(cameras)]


@pytest.fixture(scope="module")
def renderer():
    return scene()


@pytest.fixture(scope="module")
def capture(tmp_path_factory, renderer) -> Path:
    """Eleven views, one per camera model (nine distorted, two pinholes), with SfM points."""
    root = tmp_path_factory.mktemp("distorted")
    write_capture(root, renderer, capture_views(), renderer.model.means.double().numpy()[::5])
    return root


def loaded(path: Path, split: str = "all", **kw):
    """load_dataset, and the texts of the notes it issued."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = load_dataset(path, split, **kw)
    return data, [str(w.message) for w in caught if w.category is ModelNote]


def test_every_camera_model_is_undistorted_onto_pycolmaps_pinhole(capture, renderer) -> None:
    """Each view's camera is the PINHOLE pycolmap undistorts its COLMAP camera to, and its
    photo matches the scene rendered directly at that camera: measured 44.2-46.0 dB for the nine
    distorted models (8-bit photos, two bilinear resamplings; 46.2 for the pinholes), where the
    render shifted by half a pixel gives 35-37 dB and the distorted photo merely resized to the
    undistorted size 26-35 dB."""
    data, notes = loaded(capture)
    views = capture_views()
    assert data.names == [v.name for v in views]
    for view, camera, image in zip(views, data.cameras, data.images):
        expected = undistorted(view.camera)
        assert (camera.width, camera.height) == (expected.width, expected.height), view.name
        assert [camera.fx, camera.fy, camera.cx, camera.cy] == pytest.approx(list(expected.params), abs=1e-9)
        assert image.shape == (camera.height, camera.width, 3)
        truth = pinhole_render(renderer, view.c2w, camera.fx, camera.fy, camera.cx, camera.cy, camera.width,
                               camera.height)
        measured = psnr(image, truth)
        assert measured > 40, view.name
        if view.camera.model.name not in PINHOLES:        # without undistortion the photo is far off
            photo = torch.from_numpy(iio.imread(capture / "images" / view.name)).float() / 255
            resized = F.interpolate(photo.permute(2, 0, 1)[None], size=image.shape[:2], mode="bilinear",
                                    antialias=True)[0].permute(1, 2, 0)
            assert psnr(resized, truth) < measured - 8, view.name
    assert len({tuple(image.shape) for image in data.images}) > 5            # the views differ in size
    (note,) = notes
    assert "THIN_PRISM_FISHEYE" in note and "PINHOLE (" not in note and str(undistort_module.cache_root()) in note


def test_poses_only_loading_reads_headers_and_no_pixels(capture, monkeypatch) -> None:
    """with_images=False decodes no photo and undistorts nothing: one header per camera gives
    its photos' size, and the cameras are those loaded with the images."""
    with_images, _ = loaded(capture)
    headers = []
    monkeypatch.setattr(iio, "imread", lambda *a, **k: pytest.fail("decoded a photo"))
    monkeypatch.setattr(pycolmap, "undistort_image", lambda *a, **k: pytest.fail("undistorted a photo"))
    size = frames_module.image_size
    monkeypatch.setattr("phd_core.data.colmap.image_size",
                        lambda path, field: headers.append(path) or size(path, field))
    data, notes = loaded(capture, with_images=False)
    assert data.images is None and notes == []
    assert len(headers) == len(data.cameras) == 11                            # one camera per photo here
    assert [c.to_frame() for c in data.cameras] == [c.to_frame() for c in with_images.cameras]


def test_the_cache_is_reused_and_follows_the_photos_and_the_size(capture, tmp_path, monkeypatch) -> None:
    root = tmp_path / "capture"
    shutil.copytree(capture, root)
    monkeypatch.setenv("PHD_CACHE_DIR", str(tmp_path / "cache"))
    calls = []
    warp = pycolmap.undistort_image
    monkeypatch.setattr(pycolmap, "undistort_image", lambda *a: calls.append(1) or warp(*a))

    first, notes = loaded(root, "train")                   # 9 views, 7 of them distorted
    assert len(calls) == 7 and "7 undistorted now, 0 reused" in notes[0]
    entries = sorted((tmp_path / "cache" / "undistorted").iterdir())
    assert len(entries) == 7 and all(e.suffix == ".png" for e in entries)
    again, notes = loaded(root, "train")
    assert len(calls) == 7 and "0 undistorted now, 7 reused" in notes[0]
    assert all(torch.equal(a, b) for a, b in zip(first.images, again.images))       # the same pixels, both times

    photo = root / "images" / first.names[1]               # another photo under the same name: undistorted anew
    iio.imwrite(photo, 255 - iio.imread(photo))
    changed, notes = loaded(root, "train")
    assert len(calls) == 8 and "1 undistorted now, 6 reused" in notes[0]
    assert psnr(changed.images[1], 1 - first.images[1]) > 40
    half, notes = loaded(root, "train", downscale=2)       # another loaded size: other entries
    assert len(calls) == 15 and "7 undistorted now" in notes[0]
    assert [tuple(i.shape[:2]) for i in half.images] == [(c.height, c.width) for c in half.cameras]


def test_a_cache_that_cannot_be_written_is_skipped_with_the_reason(capture, tmp_path, monkeypatch) -> None:
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("PHD_CACHE_DIR", str(tmp_path / "file"))
    data, notes = loaded(capture, "test")
    assert "not kept" in notes[0] and str(tmp_path / "file") in notes[0]
    monkeypatch.setenv("PHD_CACHE_DIR", str(tmp_path / "cache"))
    cached, _ = loaded(capture, "test")
    assert all(torch.equal(a, b) for a, b in zip(data.images, cached.images))


def test_photos_smaller_than_their_cameras_scale_the_intrinsics(tmp_path, renderer) -> None:
    """Photos at half their cameras' size (as an images_2 folder): each camera is undistorted at
    its photos' size, and the SfM points project onto their keypoints, halved and undistorted by
    pycolmap, to within 1e-6 pixels."""
    views = [v for v in capture_views() if v.camera.model.name in ("SIMPLE_RADIAL", "OPENCV", "PINHOLE")]
    sparse = write_capture(tmp_path, renderer, views, renderer.model.means.double().numpy()[::5],
                           photo_sizes=[(v.camera.width // 2, v.camera.height // 2) for v in views])
    data, _ = loaded(tmp_path)
    model = read_model(sparse)
    errors = []
    for view, image, camera, pixels in zip(views, model.images, data.cameras, data.images):
        half = (view.camera.width // 2, view.camera.height // 2)
        expected = undistorted(view.camera, half)
        assert (camera.width, camera.height, camera.fx) == (expected.width, expected.height, expected.params[0])
        assert pixels.shape == (camera.height, camera.width, 3)
        at_photo = pycolmap.Camera(model=view.camera.model, width=view.camera.width, height=view.camera.height,
                                   params=view.camera.params)
        at_photo.rescale(*half)
        rays = at_photo.cam_from_img(image.xys / 2)                               # [K, 2] x/z, y/z
        keypoints = expected.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], 1))
        ids = {int(p): k for k, p in enumerate(model.point_ids)}
        points = torch.from_numpy(model.points[[ids[int(p)] for p in image.point3d_ids]])
        errors.append((camera.project(points)[0].numpy() - keypoints))
    errors = np.abs(np.concatenate(errors))
    assert len(errors) > 100 and errors.max() < 1e-6


def test_a_photo_of_another_aspect_ratio_is_refused_naming_it(capture, tmp_path, capsys) -> None:
    root = tmp_path / "capture"
    shutil.copytree(capture, root)
    name = "01_RADIAL.png"
    iio.imwrite(root / "images" / name, np.zeros((48, 96, 3), np.uint8))      # 96x48 for a 96x72 camera
    with pytest.raises(InputError) as info:
        load_dataset(root, "all", with_images=False)
    assert info.value.field == f"images/{name}" and "aspect ratio" in info.value.reason
    code, _, err = run(capsys, "train", "--data", root, "--iterations", 1, "--out", tmp_path / "m.ply", "--quiet")
    assert code == 2 and name in err and "aspect ratio" in err
    # A rounding of one pixel is a downscale: 96x72 -> 33x24 (32.7 x 24 exactly) loads.
    iio.imwrite(root / "images" / name, np.zeros((24, 33, 3), np.uint8))
    camera = load_dataset(root, "all", with_images=False).cameras[1]
    assert camera.width < 33 and camera.height < 24                                # undistorted at 33x24


def test_a_photo_unlike_its_cameras_other_photos_is_refused(tmp_path) -> None:
    """One COLMAP camera, one photo size: the size measured on its first photo binds the rest."""
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 SIMPLE_RADIAL 40 30 50 20 15 0.05\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 4 1 a.png\n\n2 1 0 0 0 0 0 5 1 b.png\n\n")
    (tmp_path / "images").mkdir()
    iio.imwrite(tmp_path / "images" / "a.png", np.zeros((15, 20, 3), np.uint8))
    iio.imwrite(tmp_path / "images" / "b.png", np.zeros((30, 40, 3), np.uint8))
    cameras = load_dataset(tmp_path, "all", with_images=False).cameras
    assert cameras[0].width == cameras[1].width < 20                  # both at a.png's 20x15
    with pytest.raises(InputError) as info:
        load_dataset(tmp_path, "all")
    assert info.value.field == "images/b.png" and "measured on a.png" in info.value.reason


def test_a_capture_of_several_sizes_trains_renders_and_ranks(capture, tmp_path, capsys) -> None:
    """Through the CLI: each view trains and renders at its own size (portrait, landscape and
    the undistorted views' sizes), and the model ranks candidates."""
    model = tmp_path / "model.ply"
    code, _, err = run(capsys, "train", "--data", capture, "--views", 9, "--downscale", 1, "--iterations", 20,
                       "--out", model, "--quiet")
    assert code == 0, err
    trained = json.loads(model.with_suffix(".json").read_text())["training_cameras"]
    assert len({(c["w"], c["h"]) for c in trained}) > 5
    code, out, err = run(capsys, "render", "--model", model, "--data", capture, "--split", "all",
                         "--out", tmp_path / "render", "--quiet")
    assert code == 0, err
    data = load_dataset(capture, "all", with_images=False)
    for index, camera in enumerate(data.cameras):
        assert iio.imread(tmp_path / "render" / f"r_{index}.png").shape == (camera.height, camera.width, 3)
    assert " to " in out.split(":")[0]                                         # "at WxH to WxH"
    code, out, err = run(capsys, "rank", "--model", model, "--candidates", "orbit:8", "--top-k", 3,
                         "--samples", 4, "--json")
    assert code == 0, err
    assert len(json.loads(out)["ranking"]) == 3


@pytest.mark.parametrize("name", ["flask_desk", "imac_chair", "meeting_room_a", "drone_flight1"])
def test_real_captures_project_their_sfm_points_onto_their_keypoints(name) -> None:
    """The real captures (photos downscaled to 240 px, models at the original size, distortion
    as captured): every SfM point projects, through the loaded camera, onto its keypoint scaled
    to the photo and undistorted by pycolmap. Measured median 0.07-0.25 px, 95th percentile
    0.26-0.86 px: COLMAP's own reprojection error at this size."""
    root = REAL / name
    data = load_dataset(root, "all", with_images=False)
    model = read_model(root / "sparse" / "0")
    ids = {int(p): k for k, p in enumerate(model.point_ids)}
    errors = []
    for image, camera in zip(model.images, data.cameras):
        colmap_camera = model.cameras[image.camera_id]
        height, width = iio.improps(root / "images" / image.name).shape[:2]
        seen = image.point3d_ids >= 0
        keypoints = image.xys[seen] * [width / colmap_camera.width, height / colmap_camera.height]
        if colmap_camera.model != "PINHOLE":
            at_photo = pycolmap.Camera(model=colmap_camera.model, width=colmap_camera.width,
                                       height=colmap_camera.height, params=list(colmap_camera.params))
            at_photo.rescale(width, height)
            rays = at_photo.cam_from_img(keypoints)
            keypoints = undistorted(at_photo).img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], 1))
        points = torch.from_numpy(model.points[[ids[int(p)] for p in image.point3d_ids[seen]]])
        uv, depth = camera.project(points)
        assert (depth > 0).all()
        errors.append(np.linalg.norm(uv.numpy() - keypoints, axis=1))
    errors = np.concatenate(errors)
    assert len(errors) > 10_000 and np.median(errors) < 0.4 and np.quantile(errors, 0.95) < 1.2


def test_real_capture_test_split_loads_undistorted_at_each_views_size() -> None:
    """meeting_room_a: one SIMPLE_RADIAL camera per photo (k1 up to 0.108), so its undistorted
    views differ in size; each loads at its own."""
    data, notes = loaded(REAL / "meeting_room_a", "test")
    assert len(data.images) == 21 and "SIMPLE_RADIAL" in notes[0]
    assert [tuple(i.shape) for i in data.images] == [(c.height, c.width, 3) for c in data.cameras]
    assert len({tuple(i.shape) for i in data.images}) > 5


def test_llff_beside_a_distorted_colmap_model_warns_with_the_fix(capture, tmp_path) -> None:
    root = tmp_path / "capture"
    shutil.copytree(capture, root)
    cameras = load_dataset(root, "all", with_images=False).cameras
    shutil.rmtree(root / "images")
    npy = write_llff(root, cameras)
    with pytest.warns(ModelWarning) as caught:
        load_dataset(npy, "all", with_images=False)
    message = str(caught[0].message)
    assert "OPENCV_FISHEYE" in message and "SIMPLE_RADIAL" in message and f"Give the capture folder {root}" in message
    with warnings.catch_warnings():
        warnings.simplefilter("error")                # a pinhole model beside it: nothing to say
        load_dataset(Path(__file__).resolve().parents[3] / "shared" / "data" / "cup_colmap" / "poses_bounds.npy",
                     "test", with_images=False)
