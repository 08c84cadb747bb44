"""`phd capture`: photos or a video in, a capture folder out, which every other command
takes as --data (structure-from-motion with pycolmap on the CPU: phd_core.process).

    phd capture photos/ --out captures/cup
    phd capture walk.mp4 --out captures/walk --fps 3
    phd capture more/ --add-to captures/cup          # registered into it, the earlier poses unchanged
"""

from __future__ import annotations

import argparse
from pathlib import Path

from phd_core.process import capture
from phd_core.process.photos import PHOTO_SUFFIXES, VIDEO_SUFFIXES

from .report import add_progress_args, say, stage_bars


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "capture", help="photos or a video -> a capture folder (structure-from-motion on the CPU)",
        description="Reconstruct the cameras of photos or of a video's frames with COLMAP (pycolmap): features, "
                    "matching, incremental mapping, undistortion to PINHOLE. Writes DIR/images/ and DIR/sparse/0/ "
                    "(what `phd train --data DIR` reads), the distorted reconstruction and COLMAP's database in "
                    "DIR/distorted/, the photos as COLMAP saw them in DIR/input/, and a report in "
                    f"DIR/{capture.REPORT}.")
    p.add_argument("inputs", nargs="+", type=Path, metavar="PHOTOS_OR_VIDEO",
                   help=f"a folder of photos ({', '.join(PHOTO_SUFFIXES)}), photo files, or one video "
                   f"({', '.join(VIDEO_SUFFIXES)})")
    target = p.add_mutually_exclusive_group(required=True)
    target.add_argument("--out", type=Path, help="the capture folder to write (new, or empty)")
    target.add_argument("--add-to", type=Path, metavar="DIR", help="add the photos to this capture instead: their "
                        "features are matched with its photos and they are registered into its reconstruction, whose "
                        "poses and frame stay as they are (photos that do not register are named; if none does, "
                        "nothing changes)")
    p.add_argument("--matcher", choices=capture.MATCHERS, default="auto",
                   help="which photo pairs are matched. auto (default): a video's frames, and photos whose names "
                   "differ only in their numbers (IMG_0001.jpg, ...), are matched with their neighbours "
                   f"(sequential); up to {capture.EXHAUSTIVE_MAX} other photos, every pair (exhaustive); more "
                   "are refused")
    p.add_argument("--max-size", type=int, default=capture.DEFAULT_MAX_SIZE,
                   help=f"photos and frames larger than this many pixels on their longer side are downscaled to it "
                   f"before structure-from-motion (default {capture.DEFAULT_MAX_SIZE})")
    p.add_argument("--max-images", type=int, default=capture.DEFAULT_MAX_IMAGES,
                   help=f"more photos are refused; a video is sampled to at most this many frames "
                   f"(default {capture.DEFAULT_MAX_IMAGES})")
    p.add_argument("--fps", type=float, default=capture.DEFAULT_FPS,
                   help=f"a video's frames sampled per second of video (default {capture.DEFAULT_FPS:g})")
    p.add_argument("--camera-model", choices=capture.CAMERA_MODELS, default="SIMPLE_RADIAL",
                   help="the lens model COLMAP estimates before undistorting (default SIMPLE_RADIAL, COLMAP's: a "
                   "focal length and one radial term; OPENCV for strong distortion, OPENCV_FISHEYE for fisheye lenses)")
    p.add_argument("--min-registered", type=int, default=None,
                   help=f"refuse the capture when fewer images register (default: the larger of {capture.MIN_IMAGES} "
                   "and half the inputs)")
    p.add_argument("--overwrite", action="store_true",
                   help=f"replace an earlier capture at --out (a folder holding {capture.REPORT}; nothing else)")
    p.add_argument("--seed", type=int, default=0, help="COLMAP's random seed (default 0)")
    add_progress_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.add_to is not None:
        return add(args)
    with stage_bars(args) as progress:
        report = capture.run_capture(args.inputs, args.out, matcher=args.matcher, max_size=args.max_size,
                                     max_images=args.max_images, fps=args.fps, camera_model=args.camera_model,
                                     min_registered=args.min_registered, overwrite=args.overwrite, seed=args.seed,
                                     progress=progress)
    for note in report.notes:
        say(args, f"note: {note}")
    kind = "frames" if report.source == "video" else "photos"
    print(f"registered {len(report.registered)} of {report.inputs} {kind} ({report.share:.0%}); {report.matcher} "
          f"matching ({report.matcher_reason}); {report.points:,} points, mean reprojection error "
          f"{report.reprojection_error:.2f} px -> {report.out}")
    print("seconds: " + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in report.seconds.items()))
    return 0


def add(args: argparse.Namespace) -> int:
    with stage_bars(args) as progress:
        report = capture.add_photos(args.add_to, args.inputs, max_size=args.max_size, max_images=args.max_images,
                                    seed=args.seed, progress=progress)
    for note in report.notes:
        say(args, f"note: {note}")
    print(f"registered {len(report.added)} of {len(report.added) + len(report.not_registered)} photos into "
          f"{args.add_to} ({len(report.registered)} in all)" + (
              f"; not registered: {', '.join(report.not_registered)}" if report.not_registered else ""))
    print("seconds: " + ", ".join(f"{stage} {seconds:.1f}" for stage, seconds in report.seconds.items()))
    return 0
