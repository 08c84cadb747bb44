"""Render speed of a 2DGS model against a 3DGS one, both sides in one process.

    python -m bench.bench_gs2d_speed runs/lego16/model.ply runs/lego16_2dgs/model.ply [--masks 16]

For each model: one render at 100x100 and 200x200 (the first lego test pose), and one batched
render of N keep-masks against N separate renders; best of 3 wall times, 1 torch thread.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from bench._harness import DATA, timed
from phd_core.data import load_blender
from phd_core.renderers import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+", type=Path)
    parser.add_argument("--masks", type=int, default=16)
    args = parser.parse_args()
    torch.set_num_threads(1)
    pose = load_blender(DATA / "lego_200", "test", views=[0], with_images=False).cameras[0]
    for path in args.models:
        renderer = load_model(path)
        row = {"model": str(path), "kind": renderer.kind, "units": renderer.num_units}
        keep = torch.rand(args.masks, renderer.num_units, generator=torch.Generator().manual_seed(0)) >= 0.2
        for size in (100, 200):
            cam = pose.resized(size, size)
            row[f"render_{size}_s"] = round(timed(lambda: renderer.render(cam), 3).best, 4)
            row[f"batched_{args.masks}_{size}_s"] = round(timed(lambda: renderer.render(cam, keep), 3).best, 3)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
