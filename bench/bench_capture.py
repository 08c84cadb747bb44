"""Training on a real capture: test PSNR against the number of training views.

cup_colmap (77 hand-held photos, COLMAP) at 80x60 px, 600 iterations, LLFF hold-out (every
8th image by name is a test view, 10 views), `--views` evenly spaced training views out of
the other 67. Each initialisation is one run of the same trainer:

    before      the trainer before this change (uniform random grey splats in the bounds, white
                background), loaded with --before FILE (`git show 9061413:phd_core/train/gs3d.py`
                with its relative imports made absolute); skipped without it
    sfm         the default for a COLMAP capture: the SfM points (points3D), kNN-sized,
                mean-colour background, camera-spread extent
    sfm+shell   the same plus a far shell of 2000 background splats (TrainConfig.background_splats)

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_capture --out bench/results/capture.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from bench import _harness
from phd_core.data import load_dataset
from phd_core.eval import psnr
from phd_core.renderers.gs3d import rasterize
from phd_core.train.gs3d import TrainConfig, fit, training_background

DATA = _harness.DATA / "cup_colmap"


def run(views: int, mode: str, iterations: int, downscale: float, seed: int, before=None) -> dict:
    train = load_dataset(DATA, "train", downscale=downscale, views=views)
    test = load_dataset(DATA, "test", downscale=downscale)
    started = time.perf_counter()
    if mode == "before":
        model, _ = before.fit(train, before.TrainConfig(iterations=iterations, seed=seed), progress=False)
        background = torch.tensor(train.background)
    else:
        config = TrainConfig(iterations=iterations, seed=seed, background_splats=0 if mode == "sfm" else 2000)
        model, _ = fit(train, config, progress=False)
        background = torch.tensor(training_background(train))
    seconds = time.perf_counter() - started
    with torch.no_grad():
        scores = [psnr(rasterize(model, cam, background).rgb[0].clamp(0, 1), image)
                  for cam, image in zip(test.cameras, test.images)]
    return {"views": views, "mode": mode, "test_psnr": sum(scores) / len(scores), "splats": model.num_splats,
            "seconds": round(seconds, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", default="4,8,12,16")
    parser.add_argument("--modes", default="before,sfm,sfm+shell")
    parser.add_argument("--before", type=Path, help="the previous trainer's source file (mode 'before')")
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--downscale", type=float, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    before = None
    if args.before is not None:
        import importlib.util

        spec = importlib.util.spec_from_file_location("gs3d_before", args.before)
        before = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = before        # its dataclasses look themselves up there
        spec.loader.exec_module(before)
    rows = []
    for views in [int(v) for v in args.views.split(",")]:
        for mode in args.modes.split(","):
            if mode == "before" and before is None:
                continue
            row = run(views, mode, args.iterations, args.downscale, args.seed, before)
            rows.append(row)
            print(json.dumps(row), flush=True)
    result = {"data": "cup_colmap", "downscale": args.downscale, "iterations": args.iterations, "seed": args.seed,
              "machine": _harness.machine(), "runs": rows}
    if args.out:
        _harness.write_result(args.out, result)


if __name__ == "__main__":
    main()
