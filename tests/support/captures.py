"""Tiny captures written by the tests themselves, in every format the project reads: a COLMAP
model (text or binary), an LLFF poses_bounds.npy, a reference-trainer output folder. Each
is made from `Camera`s with conversions written here from the formats' definitions (not with
the library's writers), so a reader that got a convention wrong disagrees with them."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Sequence

import imageio.v3 as iio
import numpy as np
import torch

from phd_core.renderers.gs3d import GaussianModel, write_ply
from phd_core.scene import Camera


def opencv_c2w(camera: Camera) -> np.ndarray:
    """[4, 4] camera-to-world with OpenCV camera axes (x right, y down, z forward)."""
    c2w = camera.c2w.numpy().copy()
    c2w[:3, 1:3] *= -1
    return c2w


def rotation_to_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix (Shepperd's method, the largest diagonal term first)."""
    trace = np.trace(r)
    candidates = [trace, r[0, 0], r[1, 1], r[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = math.sqrt(1 + trace) * 2
        q = (s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    elif k == 1:
        s = math.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        q = ((r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s)
    elif k == 2:
        s = math.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        q = ((r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s)
    else:
        s = math.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        q = ((r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4)
    return tuple(float(v) for v in q)


def colmap_pose(camera: Camera) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """COLMAP's (qvec, tvec): the world-to-camera rotation and translation."""
    w2c = np.linalg.inv(opencv_c2w(camera))
    return rotation_to_quaternion(w2c[:3, :3]), tuple(float(v) for v in w2c[:3, 3])


def write_colmap(root: Path, cameras: Sequence[Camera], *, binary: bool, points: np.ndarray | None = None,
                 model: str = "PINHOLE", extra: Sequence[float] = (), images: Sequence[np.ndarray] | None = None,
                 names: Sequence[str] | None = None) -> Path:
    """root/sparse/0/{cameras,images,points3D}.{txt,bin} (+ root/images/*.png): one camera per image."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    names = list(names or [f"{i:03d}.png" for i in range(len(cameras))])
    model_ids = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "OPENCV": 4, "OPENCV_FISHEYE": 5}
    cam_rows, image_rows = [], []
    for i, c in enumerate(cameras):
        params = ([c.fx, c.cx, c.cy] if model.startswith("SIMPLE") else [c.fx, c.fy, c.cx, c.cy]) + list(extra)
        cam_rows.append((i + 1, model, c.width, c.height, params))
        qvec, tvec = colmap_pose(c)
        image_rows.append((i + 1, qvec, tvec, i + 1, names[i]))
    pts = np.zeros((0, 3)) if points is None else points
    if binary:
        out = struct.pack("<Q", len(cam_rows))
        for cid, m, w, h, params in cam_rows:
            out += struct.pack(f"<iiQQ{len(params)}d", cid, model_ids[m], w, h, *params)
        (sparse / "cameras.bin").write_bytes(out)
        out = struct.pack("<Q", len(image_rows))
        for iid, q, t, cid, name in image_rows:
            out += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\0" + struct.pack("<Q", 0)
        (sparse / "images.bin").write_bytes(out)
        out = struct.pack("<Q", len(pts))
        for k, p in enumerate(pts):
            out += struct.pack("<Q3d3BdQ", k + 1, *p, 200, 100, 50, 0.5, 1) + struct.pack("<ii", 1, 0)
        (sparse / "points3D.bin").write_bytes(out)
    else:
        (sparse / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
            f"{cid} {m} {w} {h} {' '.join(map(repr, params))}\n" for cid, m, w, h, params in cam_rows))
        (sparse / "images.txt").write_text("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n" + "".join(
            f"{iid} {' '.join(map(repr, q))} {' '.join(map(repr, t))} {cid} {name}\n\n"
            for iid, q, t, cid, name in image_rows))
        (sparse / "points3D.txt").write_text("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n" + "".join(
            f"{k + 1} {p[0]} {p[1]} {p[2]} 200 100 50 0.5 1 0\n" for k, p in enumerate(pts.tolist())))
    if images is not None:
        write_images(root / "images", images, names)
    return sparse


def write_images(folder: Path, images: Sequence[np.ndarray], names: Sequence[str]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for image, name in zip(images, names):
        iio.imwrite(folder / name, np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8))


def write_llff(root: Path, cameras: Sequence[Camera], bounds: Sequence[float] = (1.0, 6.0),
               images: Sequence[np.ndarray] | None = None) -> Path:
    """root/poses_bounds.npy (centred principal points) and root/images/."""
    rows = []
    for c in cameras:
        c2w = c.c2w.numpy()
        right, up, back = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2]
        pose = np.stack([-up, right, back, c2w[:3, 3], [c.height, c.width, c.fx]], axis=1)   # [down, right, back]
        rows.append(np.concatenate([pose.reshape(-1), bounds]))
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", np.array(rows))
    if images is not None:
        write_images(root / "images", images, [f"{i:03d}.png" for i in range(len(cameras))])
    return root / "poses_bounds.npy"


def inria_entries(cameras: Sequence[Camera], names: Sequence[str] | None = None) -> list[dict]:
    """cameras.json entries as the reference trainer writes them."""
    entries = []
    for i, c in enumerate(cameras):
        c2w = opencv_c2w(c)
        entries.append({"id": i, "img_name": names[i] if names else f"{i:03d}", "width": c.width, "height": c.height,
                        "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
                        "fy": c.fy, "fx": c.fx})
    return entries


def write_output_folder(root: Path, model: GaussianModel, cameras: Sequence[Camera], *,
                        iterations: Sequence[int] = (7000, 30000), eval_split: bool = False,
                        white: bool = False) -> Path:
    """A reference-trainer output folder: cameras.json, cfg_args, point_cloud/iteration_N/point_cloud.ply.
    The earlier iterations get a one-splat model, so loading the wrong one shows."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "cameras.json").write_text(json.dumps(inria_entries(cameras)))
    (root / "cfg_args").write_text(f"Namespace(data_device='cuda', eval={eval_split}, images='images', "
                                   f"model_path='{root}', resolution=-1, sh_degree=3, source_path='/data/x', "
                                   f"white_background={white})")
    for k, it in enumerate(sorted(iterations)):
        folder = root / "point_cloud" / f"iteration_{it}"
        folder.mkdir(parents=True, exist_ok=True)
        last = k == len(iterations) - 1
        write_ply(model if last else model.subset(torch.arange(model.num_splats) < 1), folder / "point_cloud.ply")
    return root
