"""`phd render`: render a dataset split with any model, write PNGs, print PSNR and SSIM."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import model_help


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("render", help="render a split and score it against the ground truth")
    p.add_argument("--model", required=True, type=Path, help=model_help())
    p.add_argument("--data", required=True, type=Path, help="dataset directory")
    p.add_argument("--split", default="test")
    p.add_argument("--views", default=None, help="count or comma-separated indices (default: all)")
    p.add_argument("--downscale", type=float, default=None,
                   help="image downscale (default: the resolution the model was trained at)")
    p.add_argument("--out", required=True, type=Path, help="output directory for PNGs and metrics.json")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from phd_core.data import load_dataset, split_size
    from phd_core.eval import psnr, ssim
    from phd_core.io import write_json_atomic, write_png
    from phd_core.renderers import load_model

    from .train import parse_views

    renderer = load_model(args.model)
    downscale = args.downscale
    if downscale is None:
        downscale = training_downscale(renderer, args.data, args.split)
    split_size(args.data, args.split)  # clear error for a missing split before loading images
    views = parse_views(args.views) if args.views else None
    data = load_dataset(args.data, args.split, downscale=downscale, views=views)
    assert data.images is not None  # loaded with its images (the default)
    args.out.mkdir(parents=True, exist_ok=True)
    per_view = []
    for index, camera, target in zip(data.indices, data.cameras, data.images):
        image = renderer.render(camera)[0]
        write_png(args.out / f"r_{index}.png", image)
        per_view.append({"index": index, "psnr": psnr(image, target), "ssim": float(ssim(image, target))})
    mean_psnr = sum(v["psnr"] for v in per_view) / len(per_view)
    mean_ssim = sum(v["ssim"] for v in per_view) / len(per_view)
    write_json_atomic(args.out / "metrics.json", {"model": str(args.model), "split": args.split,
                                                  "downscale": downscale, "psnr": mean_psnr,
                                                  "ssim": mean_ssim, "views": per_view})
    print(f"{len(per_view)} views of {args.split} at {data.cameras[0].width}x{data.cameras[0].height}: "
          f"PSNR {mean_psnr:.2f} dB, SSIM {mean_ssim:.4f} -> {args.out}")
    return 0


def training_downscale(renderer, data: Path, split: str) -> float:
    """The factor that brings the dataset to the model's training resolution (1 if unknown)."""
    from phd_core.data import load_dataset
    cams = renderer.training_cameras
    if not cams:
        return 1.0
    full = load_dataset(data, split, views=[0], with_images=False).cameras[0]
    return full.width / cams[0].width
