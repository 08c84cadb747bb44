"""`phd train`: fit a 3DGS (default), 2DGS or NeRF model to a capture (splats: any format
in `phd_core.data`, COLMAP and LLFF included)."""

from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path

from phd_core.renderers import FAMILIES

from .options import add_background_arg, parse_background


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("train", help="train a 3DGS, 2DGS or NeRF model on a Blender dataset",
                              description="Train on the train split; saves the model with its training cameras.")
    trainable = sorted(kind for kind, family in FAMILIES.items() if family.trainer)
    p.add_argument("--model", choices=trainable, default="3dgs", help="model family (default 3dgs)")
    p.add_argument("--data", required=True, type=Path, help="capture: Blender/nerfstudio transforms, a COLMAP "
                   "scene (images/ + sparse/0), or LLFF poses_bounds.npy (3dgs reads all; its train split)")
    p.add_argument("--views", default="16",
                   help="number of evenly spaced training views, or a comma-separated index list (default 16)")
    p.add_argument("--downscale", type=float, default=2.0, help="image downscale factor (default 2)")
    p.add_argument("--iterations", type=int, default=None, help="optimisation steps (default: the trainer's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, type=Path, help="output file (" + ", ".join(
        f"{FAMILIES[kind].extension} for {kind}" for kind in trainable) + ")")
    p.add_argument("--encoding", choices=("pe", "spe", "hash"), default="pe", help="NeRF input encoding")
    p.add_argument("--freenerf", action="store_true", help="NeRF: FreeNeRF frequency and occlusion regularisation")
    p.add_argument("--depth-distortion", type=float, default=1.0,
                   help="2DGS: depth distortion weight (default 1; 0 off)")
    p.add_argument("--normal-consistency", type=float, default=0.05,
                   help="2DGS: normal consistency weight (default 0.05; 0 off)")
    add_background_arg(p, "the colour to train over (images with alpha are composited on it; the model is "
                       "rendered over it). Default: white for captures with alpha masks; for real captures the "
                       "images' mean colour (3dgs, 2dgs) or white (nerf)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def parse_views(text: str) -> int | list[int]:
    from phd_core.errors import InputError
    try:
        return [int(v) for v in text.split(",")] if "," in text else int(text)
    except ValueError:
        raise InputError("views", f"expected a count or comma-separated indices, got {text!r}") from None


def run(args: argparse.Namespace) -> int:
    views = parse_views(args.views)
    started = time.perf_counter()
    family = FAMILIES[args.model]
    module, function = family.trainer.split(":")
    train = getattr(importlib.import_module(module), function)   # imported only to train
    options = {name: getattr(args, name) for name in family.train_options}
    background = parse_background(args.background)
    if background is not None:
        options["background"] = list(background)
    renderer = train(args.data, views=views, downscale=args.downscale, iterations=args.iterations, seed=args.seed,
                     out=args.out, progress=not args.quiet, **options)
    print(f"trained {renderer.kind} with {renderer.num_units} dropout units in "
          f"{time.perf_counter() - started:.1f} s -> {args.out}")
    return 0
