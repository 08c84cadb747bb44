"""`phd render`: render a split with any model, write PNGs, print PSNR and SSIM."""

from __future__ import annotations

import argparse
from pathlib import Path

from phd_core.errors import InputError
from phd_core.scene import Camera

from .models import OpenedModel, model_views, open_model
from .options import add_other_capture_arg, model_help
from .report import add_progress_args, progress_bar


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("render", help="render a split and score it against the ground truth",
                              description="Render every view of a split and compare it with the capture's images. "
                                          "A trainer's output folder brings its own capture and split: "
                                          "`phd render --model RUN --out DIR` renders the frames its run held out.")
    p.add_argument("--model", required=True, type=Path, help=model_help())
    p.add_argument("--data", type=Path, default=None, help="the capture the model was trained on, wherever it lies "
                   "now (default: the one its sidecar or checkpoint names; for a trainer's folder the capture its run "
                   "read); another capture is refused (one in another frame, or whose photos fit the model far worse "
                   "than its training views did)")
    p.add_argument("--split", default="test", help="split to render (default test; a trainer's folder on its own "
                   "capture: the frames its run held out, train the ones it trained on, all every frame)")
    p.add_argument("--views", default=None, help="count or comma-separated indices (default: all)")
    p.add_argument("--downscale", type=float, default=None,
                   help="image downscale (default: the resolution the model was trained at)")
    p.add_argument("--out", required=True, type=Path, help="output directory for PNGs and metrics.json")
    add_other_capture_arg(p)
    add_progress_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from phd_core.eval import psnr, ssim
    from phd_core.io import write_json_atomic, write_png

    from .train import parse_views

    model = open_model(args.model)
    downscale = args.downscale
    if downscale is None:
        downscale = training_downscale(model, args.data, args.split, args.other_capture)
    views = parse_views(args.views) if args.views else None
    data = model_views(model, args.data, args.split, views=views, downscale=downscale,
                       other_capture=args.other_capture)
    assert data.images is not None  # loaded with its images (the default)
    args.out.mkdir(parents=True, exist_ok=True)
    per_view = []
    with progress_bar(args, f"render {len(data.cameras)} views") as progress:
        for index, camera, target in zip(data.indices, data.cameras, data.images):
            image = model.renderer.render(camera)[0]
            write_png(args.out / f"r_{index}.png", image)
            per_view.append({"index": index, "psnr": psnr(image, target), "ssim": float(ssim(image, target))})
            if progress is not None:
                progress(len(per_view) / len(data.cameras))
    mean_psnr = sum(v["psnr"] for v in per_view) / len(per_view)
    mean_ssim = sum(v["ssim"] for v in per_view) / len(per_view)
    write_json_atomic(args.out / "metrics.json", {"model": str(args.model), "data": str(data.root),
                                                  "split": args.split, "downscale": downscale, "psnr": mean_psnr,
                                                  "ssim": mean_ssim, "views": per_view})
    print(f"{len(per_view)} views of {args.split} of {data.root} at {sizes(data.cameras)}: "
          f"PSNR {mean_psnr:.2f} dB, SSIM {mean_ssim:.4f} -> {args.out}")
    return 0


def sizes(cameras: list[Camera]) -> str:
    """The views' size, "240x135", or their range when they differ ("165x220 to 172x229")."""
    widths, heights = [c.width for c in cameras], [c.height for c in cameras]
    low, high = f"{min(widths)}x{min(heights)}", f"{max(widths)}x{max(heights)}"
    return low if low == high else f"{low} to {high}"


def training_downscale(model: OpenedModel, data: Path | None, split: str, other_capture: bool) -> float:
    """The factor that brings the capture to the model's training resolution (1 if unknown):
    the width of the capture's camera nearest the model's first training camera over that
    camera's width. Views may differ in size, so it compares a view with itself: the nearest
    among the train split's views, else (no train split) among the rendered split's."""
    cams = model.renderer.training_cameras
    if not cams:
        return 1.0
    # the split given first: it refuses a capture in another frame
    capture = model_views(model, data, split, with_images=False, other_capture=other_capture).cameras
    try:
        capture = model_views(model, data, "train", with_images=False, other_capture=other_capture).cameras
    except InputError:
        pass
    nearest = min(capture, key=lambda camera: float((camera.center - cams[0].center).norm()))
    return nearest.width / cams[0].width
