"""`phd candidates`: candidate poses made for the user, as transforms-style JSON that
`phd rank --candidates` (and the service, the page and the client) read.

    phd candidates orbit:64 --model runs/cup/ --out candidates.json
    phd candidates spiral:30 --data ../shared/data/cup_colmap
    phd candidates frames --data ../shared/data/cup_colmap --split test --out test_views.json

The scene (centre, radius, up, intrinsics) comes from the training cameras: those stored
with --model, or the train split of --data, or --cameras; with none of them, from the
model's splats.

`frames` is no generator: generators make poses around a scene from its training cameras,
wherever they run (the service makes them too), while a capture's own frames are read from the
capture, which only the command line holds. So it is a word of this command: the frames of
--split (default all) of --data, or of the capture --model was trained on (a trainer's folder:
its run's own split), at their own size and exactly at their poses.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from phd_core.errors import InputError
from phd_core.scene import Camera
from phd_core.uq.candidates import GENERATORS, candidate_cameras, check_option_names, parse_spec

from .options import add_other_capture_arg, model_help

FRAMES = "frames"           # the spec that writes a capture's own frames instead of generating poses
BLENDER_SPLITS = ("train", "val", "test")   # the split files of a capture without an "all" split


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "candidates", help="make candidate poses for `phd rank` (orbit, sphere, spiral, jitter, ...)",
        description="Write candidate camera poses as transforms-style JSON. SPEC is NAME[:COUNT][,key=value...]; "
                    "generators: " + "; ".join(f"{name}: {g.summary}" for name, g in GENERATORS.items())
                    + f". Or `{FRAMES}[:COUNT]`: the capture's own frames of --split (all, or COUNT evenly spaced), "
                    "from --data or the capture --model was trained on")
    p.add_argument("spec", help=f"e.g. orbit:64, orbit:48,rings=3, spiral:30, jitter:20,angle=10, {FRAMES}")
    p.add_argument("--model", type=Path, help="its training cameras, else its splats, place the poses (with "
                   f"{FRAMES}: the capture it was trained on gives them): " + model_help())
    p.add_argument("--data", type=Path, help="a capture (any format): its train split places the poses (with "
                   f"{FRAMES}: its frames are the poses; with --model too, checked to be the model's capture)")
    p.add_argument("--cameras", type=Path, help="training cameras: transforms JSON or a reference cameras.json")
    p.add_argument("--split", default=None, help=f"with {FRAMES}: the split whose frames to write (default every "
                   "frame: all, or a Blender capture's train, val and test in turn)")
    p.add_argument("--out", type=Path, help="output JSON (default: print it)")
    add_other_capture_arg(p)
    p.set_defaults(func=run)


def scene_sources(args: argparse.Namespace, renderer: Any = None) -> tuple[list[Camera] | None, Any]:
    """(training cameras, SfM points) from --cameras, --data, or the model."""
    from phd_core.data import load_cameras, load_dataset

    if getattr(args, "cameras", None) is not None:
        return load_cameras(args.cameras), None
    if getattr(args, "data", None) is not None:
        dataset = load_dataset(args.data, "train", with_images=False)
        return dataset.cameras, dataset.points
    return None, None


def make(spec: str, renderer: Any = None, cameras: list[Camera] | None = None, points: Any = None) -> list[Camera]:
    name, count, options = parse_spec(spec)
    check_option_names(name, options)
    return candidate_cameras(name, count, cameras=cameras, points=points, renderer=renderer, **options)


def frames_json(cameras: list[Camera], spec: str) -> dict[str, Any]:
    return {"generator": spec, "frames": [c.to_frame() for c in cameras]}


def capture_frames(args: argparse.Namespace) -> list[Camera]:
    """`frames[:COUNT]`: the cameras of --split of --data, or of the capture --model was trained
    on; without --split every frame: its "all" split, or each split in turn for a capture
    without one (Blender). COUNT: that many of them, evenly spaced."""
    from phd_core.data import load_dataset, locate, select_views

    count = args.spec.partition(":")[2]
    if count and not count.isdigit():
        raise InputError("spec", f"expected {FRAMES} or {FRAMES}:COUNT, got {args.spec!r}")
    if args.model is not None:
        from .models import capture_of, model_views, open_model

        model = open_model(args.model)
        capture = capture_of(model, args.data)

        def load(split: str) -> list[Camera]:
            return model_views(model, args.data, split, with_images=False, other_capture=args.other_capture).cameras
    elif args.data is not None:
        capture = args.data

        def load(split: str) -> list[Camera]:
            return load_dataset(capture, split, with_images=False).cameras
    else:
        raise InputError("data", f"give --data (a capture) or --model (the capture it was trained on): {FRAMES} "
                                 "writes that capture's frames")

    def has(split: str) -> bool:
        try:
            return bool(locate(capture, split))
        except InputError:
            return False

    if args.split is not None:
        splits = [args.split]
    elif has("all"):
        splits = ["all"]
    else:                                       # one file per split (Blender)
        splits = [split for split in BLENDER_SPLITS if has(split)] or ["all"]
    cameras = [camera for split in splits for camera in load(split)]
    return [cameras[i] for i in select_views(len(cameras), int(count) if count else None)]


def run(args: argparse.Namespace) -> int:
    if args.spec.split(":")[0] == FRAMES:
        poses = capture_frames(args)
    else:
        if args.split is not None:
            raise InputError("split", f"--split chooses the frames of `{FRAMES}`; a generator places its poses "
                                      "around the training cameras")
        poses = generated(args)
    if args.out is None:
        print(json.dumps(frames_json(poses, args.spec), indent=1))
    else:
        from phd_core.io import write_json_atomic

        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(args.out, frames_json(poses, args.spec))
        print(f"{len(poses)} {args.spec.split(':')[0]} poses at {poses[0].width}x{poses[0].height} -> {args.out}")
    return 0


def generated(args: argparse.Namespace) -> list[Camera]:
    """The poses of a generator spec, placed around --cameras, --data's train split or --model."""
    renderer = None
    cameras, points = scene_sources(args)
    if args.model is not None:
        from .models import open_model

        renderer = open_model(args.model).renderer
    if renderer is None and cameras is None:
        raise InputError("model", "give --model, --data or --cameras: the poses are placed around that scene")
    return make(args.spec, renderer, cameras, points)
