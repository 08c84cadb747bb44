"""The wrong capture caught: how far another capture's photos fit below a model's own.

For each model (a `phd train` output whose sidecar names its capture) the fit
(`phd_core.renderers.provenance.measure_fit`: 4 views at 64 px, PSNR against their photos):

    own       its training views on its own capture: what `phd train` records
    as is     other captures as they are (their own poses and photos): `held` is its capture's
              test split (the same scene from views it was not trained on), the rest are other
              scenes; what a refusal of a capture that holds none of the training views reports
    replaced  its own capture's training views with other photos (a capture with the model's
              names and poses, which its fingerprint cannot tell apart): its own photos written
              again as PNG (`png`), as JPEG at quality 70 (`jpeg70`) and at half size (`half`),
              and every other capture's photos resized to the views' size: what FIT_MARGIN is
              chosen from (between the largest drop of the first three and the smallest of the rest)

Captures the loader refuses (distortion, image sizes) are reported with the reason.

    OMP_NUM_THREADS=1 nice -n 10 python -m bench.bench_capture_check --models M1.ply M2.nerf ... \\
        [--captures lego_200 /path/to/capture ...] --out bench/results/capture_check.json
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from bench import _harness
from phd_core.data import load_dataset
from phd_core.data.nerfstudio import write_transforms
from phd_core.errors import InputError
from phd_core.renderers import Renderer, load_model
from phd_core.renderers.provenance import fit_frames, measure_fit
from phd_core.scene import Camera

CAPTURES = ["lego_200", "donut_200", "chain_200", "cup_colmap", "real/flask_desk", "real/imac_chair",
            "real/meeting_room_a", "real/drone_flight1"]
OWN_VARIANTS = ("png", "jpeg70", "half")


def fit_or_reason(renderer: Renderer, capture: Path, split: str = "train") -> dict:
    """The fit of `renderer` on a split of `capture`, with its cost, or why it could not be measured."""
    started = time.perf_counter()
    try:
        fit = measure_fit(renderer, capture, name=split)
    except InputError as exc:
        return {"refused": str(exc)}
    return {"psnr": fit.psnr, "frames": fit.frames, "size": [fit.width, fit.height],
            "seconds": round(time.perf_counter() - started, 2)}


def photos_of(capture: Path, count: int, background: tuple[float, ...]) -> list[torch.Tensor] | None:
    """`count` photos of a capture's train split (evenly spaced) over `background`, or None if refused."""
    try:
        images = load_dataset(capture, "train", views=count, background=background).images
    except InputError:
        return None
    assert images is not None
    return images


def write_capture(folder: Path, cameras: list[Camera], photos: list[torch.Tensor], jpeg: int | None = None) -> Path:
    """A nerfstudio capture of `cameras` with `photos` ([H, W, 3] each, resized to its camera's size)."""
    names = [f"{i:03d}.{'jpg' if jpeg else 'png'}" for i in range(len(cameras))]
    for camera, photo, name in zip(cameras, photos, names):
        image = F.interpolate(photo.permute(2, 0, 1)[None], size=(camera.height, camera.width), mode="bilinear",
                              antialias=True, align_corners=False)[0].permute(1, 2, 0)
        pixels = (image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        (folder / "images").mkdir(parents=True, exist_ok=True)
        iio.imwrite(folder / "images" / name, pixels, **({"quality": jpeg} if jpeg else {}))
    write_transforms(folder / "transforms.json", cameras, names)
    return folder


def replaced(renderer: Renderer, own: Path, captures: list[Path]) -> dict:
    """The fit on the model's own training views with their photos replaced (module docstring)."""
    split = load_dataset(own, "train", with_images=False)
    frames = fit_frames(split.cameras, renderer.training_cameras or [])
    cameras = [split.cameras[i] for i in frames]
    background = tuple(renderer.describe().get("background") or (1.0, 1.0, 1.0))
    own_photos = load_dataset(own, "train", views=frames, background=background).images
    assert own_photos is not None
    rows = {}
    with tempfile.TemporaryDirectory(prefix="capture-check-") as tmp:
        variants = {"png": (cameras, None), "jpeg70": (cameras, 70), "half": ([c.scaled(2) for c in cameras], None)}
        for name, (views, jpeg) in variants.items():
            rows[name] = fit_or_reason(renderer, write_capture(Path(tmp) / name, views, list(own_photos), jpeg))
        for capture in captures:
            if capture.resolve() == own.resolve():
                continue
            photos = photos_of(capture, len(cameras), background)
            if photos is None:
                rows[capture.name] = {"refused": "its photos could not be read"}
                continue
            rows[capture.name] = fit_or_reason(renderer, write_capture(Path(tmp) / capture.name, cameras, list(photos)))
    return rows


def measure(model: Path, captures: list[Path]) -> dict:
    renderer = load_model(model)
    own_path = Path(renderer.describe()["trained_on"]["dataset"])
    row = {"model": model.name, "kind": renderer.kind, "units": renderer.num_units, "capture": own_path.name,
           "training_views": len(renderer.training_cameras or [])}
    row["own"] = fit_or_reason(renderer, own_path)
    row["as_is"] = {"held": fit_or_reason(renderer, own_path, "test"),
                    **{capture.name: fit_or_reason(renderer, capture)
                       for capture in captures if capture.resolve() != own_path.resolve()}}
    row["replaced"] = replaced(renderer, own_path, captures)
    own = row["own"].get("psnr")
    for part in ("as_is", "replaced"):
        row[f"{part}_drops"] = {name: round(own - fit["psnr"], 2) for name, fit in row[part].items()
                                if "psnr" in fit and own is not None}
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", type=Path, required=True)
    parser.add_argument("--captures", nargs="+", default=CAPTURES,
                        help="captures to measure every model on: folders under ../shared/data or paths")
    parser.add_argument("--out", type=Path, default=_harness.RESULTS / "capture_check.json")
    args = parser.parse_args()
    captures = [_harness.DATA / name for name in args.captures]     # an absolute path stays itself
    rows = []
    for model in args.models:
        rows.append(measure(model, captures))
        print(rows[-1]["model"], rows[-1]["own"].get("psnr"), rows[-1]["as_is_drops"], rows[-1]["replaced_drops"],
              flush=True)
    drops = [row["replaced_drops"] for row in rows]
    summary = {"largest_own_drop": max((d[v] for d in drops for v in OWN_VARIANTS if v in d), default=None),
               "smallest_other_drop": min((x for d in drops for k, x in d.items() if k not in OWN_VARIANTS),
                                          default=None)}
    print(summary)
    _harness.write_result(args.out, {"command": _harness.command(), "machine": _harness.machine(),
                                     "summary": summary, "models": rows})


if __name__ == "__main__":
    main()
