"""Dataset loading: the bundled lego_200 scene, small Blender and nerfstudio scenes written
here as real PNG + JSON files, and every input error."""

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from phd_core.data import load_blender, load_dataset, load_nerfstudio, select_views, split_size
from phd_core.errors import InputError
from support.fixtures import LEGO

POSE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]


def lego_frames(split: str = "train") -> dict:
    return json.loads((LEGO / f"transforms_{split}.json").read_text())


def write_blender(root: Path, images: list, split: str = "train", **top) -> Path:
    """A Blender-layout scene: one PNG per array (None = no file), file_path without extension."""
    (root / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for k, image in enumerate(images):
        if image is not None:
            iio.imwrite(root / split / f"r_{k}.png", image)
        frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": POSE})
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.7, **top, "frames": frames}))
    return root


def rgba(height: int = 8, width: int = 8, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 4), dtype=np.uint8)


def write_nerfstudio(root: Path, images: list, **top) -> Path:
    """A nerfstudio scene: images/ holds the PNGs (file_path with extension), shared intrinsics."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k, image in enumerate(images):
        if image is not None:
            iio.imwrite(root / "images" / f"frame_{k:03d}.png", image)
        frames.append({"file_path": f"images/frame_{k:03d}.png", "transform_matrix": POSE})
    meta = {"camera_model": "OPENCV", "fl_x": 10.0, "fl_y": 11.0, "cx": 4.5, "cy": 2.5, "w": 8, "h": 6,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, **top, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


# --- lego_200 -------------------------------------------------------------------------

def test_lego_downscaled_by_2_and_4_has_the_right_shapes_and_focal():
    focal_200 = 0.5 * 200 / math.tan(0.5 * lego_frames()["camera_angle_x"])    # 277.78
    ds = load_blender(LEGO, "train", downscale=2)
    images = torch.stack(ds.images)
    assert images.shape == (100, 100, 100, 3) and images.dtype == torch.float32
    assert torch.stack(ds.alphas).shape == (100, 100, 100)
    assert 0 <= images.min() and images.max() <= 1
    assert ds.indices == list(range(100)) and ds.split == "train"
    assert (ds.near, ds.far) == (2.0, 6.0)
    cam = ds.cameras[0]
    assert (cam.width, cam.height) == (100, 100)
    assert cam.fx == pytest.approx(focal_200 / 2) and cam.fy == pytest.approx(focal_200 / 2)
    assert (cam.cx, cam.cy) == (50, 50)
    small = load_blender(LEGO, "train", downscale=4, views=16)
    assert torch.stack(small.images).shape == (16, 50, 50, 3)
    assert small.cameras[0].fx == pytest.approx(focal_200 / 4)


def test_compositing_averages_premultiplied_colour_then_adds_the_background():
    bg = np.array([0.2, 0.4, 0.6])
    raw = iio.imread(LEGO / "train" / "r_0.png").astype(np.float64) / 255      # [200, 200, 4]
    rgb, alpha = raw[..., :3], raw[..., 3:]

    full = load_blender(LEGO, views=[0], background=bg.tolist())
    i, j = np.argwhere((alpha[..., 0] > 0.2) & (alpha[..., 0] < 0.8))[0]        # an edge pixel
    expected = rgb[i, j] * alpha[i, j] + bg * (1 - alpha[i, j])
    assert np.allclose(full.images[0][i, j].numpy(), expected, atol=1e-6)
    assert full.alphas[0][i, j].item() == pytest.approx(alpha[i, j, 0], abs=1e-6)

    half = load_blender(LEGO, views=[0], downscale=2, background=bg.tolist())
    blocks_alpha = alpha[..., 0].reshape(100, 2, 100, 2)
    spread = blocks_alpha.max(axis=(1, 3)) - blocks_alpha.min(axis=(1, 3))
    bi, bj = np.unravel_index(np.argmax(spread), spread.shape)    # the block whose alpha varies most
    block = (slice(2 * bi, 2 * bi + 2), slice(2 * bj, 2 * bj + 2))
    block_rgb, block_alpha = rgb[block], alpha[block]
    mean_alpha = block_alpha.mean()
    expected = (block_rgb * block_alpha).mean(axis=(0, 1)) + bg * (1 - mean_alpha)
    assert np.allclose(half.images[0][bi, bj].numpy(), expected, atol=1e-6)
    assert half.alphas[0][bi, bj].item() == pytest.approx(mean_alpha, abs=1e-6)
    # Averaging straight (not premultiplied) colour would give a visibly different pixel here.
    straight = block_rgb.mean(axis=(0, 1)) * mean_alpha + bg * (1 - mean_alpha)
    assert np.abs(straight - expected).max() > 0.01


def test_views_16_takes_evenly_spaced_frames_with_their_poses():
    ds = load_blender(LEGO, views=16, with_images=False)
    assert ds.indices == [0, 6, 13, 19, 25, 31, 38, 44, 50, 56, 63, 69, 75, 81, 88, 94]
    frames = lego_frames()["frames"]
    for camera, i in zip(ds.cameras, ds.indices):
        assert torch.equal(camera.c2w, torch.tensor(frames[i]["transform_matrix"], dtype=torch.float64))
    assert select_views(10, 3) == [0, 3, 7]
    assert select_views(4, 4) == [0, 1, 2, 3]
    assert select_views(5, None) == [0, 1, 2, 3, 4]
    assert select_views(5, [4, 1]) == [4, 1]


def test_seeded_selection_is_deterministic_and_depends_on_the_seed():
    a, b, c = (select_views(100, 10, seed=s) for s in (1, 1, 2))
    assert a == b and a != c
    assert a == sorted(set(a)) and len(a) == 10 and all(0 <= i < 100 for i in a)
    assert load_blender(LEGO, views=10, seed=1, with_images=False).indices == a


def test_split_size_and_dispatch_read_the_json_only():
    assert split_size(LEGO, "train") == 100 and split_size(LEGO, "test") == 200
    ds = load_dataset(LEGO, "val", views=[3], downscale=4)
    assert ds.split == "val" and torch.stack(ds.images).shape == (1, 50, 50, 3)
    assert torch.equal(ds.cameras[0].c2w, torch.tensor(lego_frames("val")["frames"][3]["transform_matrix"],
                                                       dtype=torch.float64))


def test_lego_cameras_without_images():
    ds = load_blender(LEGO, "test", downscale=2, with_images=False)
    assert ds.images is None and ds.alphas is None
    assert len(ds.cameras) == 200 and (ds.cameras[5].width, ds.cameras[5].height) == (100, 100)


# --- small scenes written here --------------------------------------------------------

def test_nerfstudio_scene_loads_with_its_intrinsics(tmp_path):
    rng = np.random.default_rng(1)
    pictures = [rng.integers(0, 256, (6, 8, 3), dtype=np.uint8) for _ in range(2)]
    json_path = write_nerfstudio(tmp_path, pictures)
    meta = json.loads(json_path.read_text())
    meta["frames"][1].update(fl_x=12.0, cx=3.5)                 # per-frame intrinsics override the top level
    json_path.write_text(json.dumps(meta))

    for ds in (load_nerfstudio(json_path), load_nerfstudio(tmp_path), load_dataset(tmp_path)):
        assert ds.alphas is None and (ds.near, ds.far) == (None, None) and ds.split == "all"
        assert torch.allclose(torch.stack(ds.images), torch.tensor(np.stack(pictures) / 255, dtype=torch.float32))
        first, second = ds.cameras
        assert (first.fx, first.fy, first.cx, first.cy, first.width, first.height) == (10, 11, 4.5, 2.5, 8, 6)
        assert (second.fx, second.fy, second.cx) == (12, 11, 3.5)

    half = load_nerfstudio(json_path, downscale=2)
    assert torch.stack(half.images).shape == (2, 3, 4, 3)
    blocks = np.stack(pictures).astype(np.float64).reshape(2, 3, 2, 4, 2, 3).mean(axis=(2, 4)) / 255
    assert np.allclose(torch.stack(half.images).numpy(), blocks, atol=1e-6)
    assert (half.cameras[0].fx, half.cameras[0].cx, half.cameras[0].width) == (5, 2.25, 4)


def test_json_near_far_override_the_blender_convention(tmp_path):
    write_blender(tmp_path, [rgba()], near=0.5, far=3.0)
    ds = load_blender(tmp_path, with_images=False)
    assert (ds.near, ds.far) == (0.5, 3.0)


def test_sixteen_bit_grey_png_is_scaled_by_65535(tmp_path):
    grey = (np.arange(64).reshape(8, 8) * 1000).astype(np.uint16)
    write_blender(tmp_path, [grey])
    ds = load_blender(tmp_path)
    assert ds.alphas is None
    expected = torch.tensor(grey / 65535, dtype=torch.float32)[..., None].expand(8, 8, 3)
    assert torch.allclose(ds.images[0], expected, atol=1e-7)


def test_non_integer_downscale_matches_the_camera_and_keeps_flat_colour(tmp_path):
    flat = np.zeros((8, 8, 4), dtype=np.uint8)
    flat[...] = (255, 0, 51, 128)                                # alpha 128/255 everywhere
    write_blender(tmp_path, [flat])
    ds = load_blender(tmp_path, downscale=3, background=(0, 1, 0))
    cam = ds.cameras[0]
    assert (cam.width, cam.height) == (3, 3) and torch.stack(ds.images).shape == (1, 3, 3, 3)
    a = 128 / 255
    expected = torch.tensor([a, 1 - a, 0.2 * a], dtype=torch.float32)
    assert torch.allclose(ds.images[0], expected.expand(3, 3, 3), atol=1e-6)


def test_cameras_only_never_read_the_images(tmp_path, monkeypatch):
    # Blender: no w/h in the JSON, so only the first image is opened (for its size).
    write_blender(tmp_path / "b", [rgba(6, 10), None, None])
    ds = load_blender(tmp_path / "b", with_images=False)
    assert ds.images is None and [(c.width, c.height) for c in ds.cameras] == [(10, 6)] * 3
    with pytest.raises(InputError) as info:
        load_blender(tmp_path / "b")
    assert info.value.field == "frames[1].file_path"
    # nerfstudio: w/h in the JSON, so no image is opened at all.
    json_path = write_nerfstudio(tmp_path / "n", [None, None])
    monkeypatch.setattr(iio, "imread", lambda *a, **k: pytest.fail("read an image"))
    monkeypatch.setattr(iio, "improps", lambda *a, **k: pytest.fail("read an image"))
    ds = load_nerfstudio(json_path, with_images=False, downscale=2)
    assert ds.images is None and (ds.cameras[1].width, ds.cameras[1].height, ds.cameras[1].fx) == (4, 3, 5)


def edit_json(name: str, change):
    def apply(root: Path):
        path = root / name
        meta = json.loads(path.read_text())
        change(meta)
        path.write_text(json.dumps(meta))
    return apply


@pytest.mark.parametrize("breakage, kwargs, field", [
    (lambda root: None, {"split": "val"}, "data"),
    (lambda root: (root / "transforms_train.json").write_text("{not json"), {}, "transforms_train.json"),
    (lambda root: (root / "transforms_train.json").write_text('{"frames": []}'), {}, "transforms_train.json"),
    (lambda root: (root / "train" / "r_1.png").unlink(), {}, "frames[1].file_path"),
    (lambda root: (root / "train" / "r_1.png").write_bytes(b"not a png"), {}, "frames[1].file_path"),
    (lambda root: iio.imwrite(root / "train" / "r_2.png", rgba(8, 9)), {}, "frames[2]"),
    (edit_json("transforms_train.json", lambda m: m["frames"][0].update(file_path="../../etc/x")), {},
     "frames[0].file_path"),
    (edit_json("transforms_train.json", lambda m: m["frames"][2].update(transform_matrix=[[2, 0, 0, 0]] * 4)), {},
     "frames[2].transform_matrix"),
    (edit_json("transforms_train.json", lambda m: m.update(near=5, far=1)), {}, "far"),
    (lambda root: None, {"views": 4}, "views"),
    (lambda root: None, {"views": 0}, "views"),
    (lambda root: None, {"views": [0, 0]}, "views"),
    (lambda root: None, {"views": [3]}, "views"),
    (lambda root: None, {"views": True}, "views"),
    (lambda root: None, {"views": "2"}, "views"),
    (lambda root: None, {"downscale": 0}, "downscale"),
    (lambda root: None, {"downscale": float("nan")}, "downscale"),
    (lambda root: None, {"background": (2, 0, 0)}, "background"),
    (lambda root: None, {"background": (1, 1)}, "background"),
    (lambda root: None, {"split": "../train"}, "split"),
])
def test_blender_input_errors_name_the_field(tmp_path, breakage, kwargs, field):
    write_blender(tmp_path, [rgba(seed=k) for k in range(3)])
    breakage(tmp_path)
    split = kwargs.pop("split", "train")
    with pytest.raises(InputError) as info:
        load_blender(tmp_path, split, **kwargs)
    assert info.value.field == field


def test_missing_data_and_nerfstudio_errors_name_the_field(tmp_path):
    cases = [
        (lambda: load_blender(tmp_path / "absent"), "data"),
        (lambda: load_dataset(tmp_path / "absent"), "data"),
        (lambda: load_dataset(tmp_path), "data"),                  # a directory without any transforms JSON
        (lambda: load_nerfstudio(tmp_path), "data"),
    ]
    json_path = write_nerfstudio(tmp_path / "n", [rgba(6, 8)[..., :3]])
    cases.append((lambda: load_dataset(json_path.parent, "test"), "split"))
    meta = json.loads(json_path.read_text())
    distorted = tmp_path / "distorted.json"
    distorted.write_text(json.dumps({**meta, "k1": 0.1}))
    cases.append((lambda: load_nerfstudio(distorted), "frames[0].k1"))
    fisheye = tmp_path / "fisheye.json"
    fisheye.write_text(json.dumps({**meta, "camera_model": "OPENCV_FISHEYE"}))
    cases.append((lambda: load_nerfstudio(fisheye), "frames[0].camera_model"))
    wrong_size = tmp_path / "n" / "wrong_size.json"
    wrong_size.write_text(json.dumps({**meta, "w": 16}))
    cases.append((lambda: load_nerfstudio(wrong_size), "frames[0]"))
    for load, field in cases:
        with pytest.raises(InputError) as info:
            load()
        assert info.value.field == field, load


def test_a_capture_format_is_one_registry_entry(tmp_path):
    """A format registered in FORMATS is sniffed and loaded by load_dataset with no other change."""
    from phd_core.data import FORMATS, DataFormat, load_nerfstudio

    folder = tmp_path / "capture"
    folder.mkdir()
    (folder / "cameras.toy").write_text("a toy capture: its frames live in frames.json")
    frame = {"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
             "fl_x": 10.0, "w": 8, "h": 6}
    (folder / "frames.json").write_text(json.dumps({"frames": [frame, frame]}))

    def locate(path, split):
        return path / "frames.json" if (path / "cameras.toy").is_file() else None

    FORMATS.register(DataFormat("toy", locate, lambda file, split, **kw: load_nerfstudio(file, **kw)))
    try:
        dataset = load_dataset(folder, "train", with_images=False)
        assert len(dataset.cameras) == 2 and dataset.cameras[0].width == 8
        assert split_size(folder, "train") == 2
    finally:
        del FORMATS["toy"]
    with pytest.raises(InputError) as info:
        load_dataset(folder, "train", with_images=False)
    assert info.value.field == "data"


def test_camera_projection_matches_the_pinhole_model():
    from phd_core.scene import look_at

    camera = look_at((0.0, -4.0, 1.0), (0.0, 0.0, 1.0), (0, 0, 1), width=40, height=30, fov_x=0.8)
    points = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 1.25], [0.0, -6.0, 1.0]], dtype=torch.float64)
    uv, depth = camera.project(points)
    assert depth.tolist() == pytest.approx([4.0, 4.0, -2.0])
    assert uv[0].tolist() == pytest.approx([20.0, 15.0])                   # on the axis: the principal point
    # +x in the world is +x (right) in the image, +z (up) is -y (image rows grow downwards).
    assert uv[1].tolist() == pytest.approx([20.0 + camera.fx * 0.5 / 4, 15.0 - camera.fy * 0.25 / 4])
    assert torch.isfinite(uv[2]).all()                                       # behind the camera: finite
