"""`phd candidates`: candidate poses made for the user, as transforms-style JSON that
`phd rank --candidates` (and the service) read.

    phd candidates orbit:64 --model runs/cup/ --out candidates.json
    phd candidates spiral:30 --data ../shared/data/cup_colmap

The scene (centre, radius, up, intrinsics) comes from the training cameras: those stored
with --model, or the train split of --data, or --cameras; with none of them, from the
model's splats.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from phd_core.errors import InputError
from phd_core.scene import Camera
from phd_core.uq.candidates import GENERATORS, candidate_cameras, check_option_names, parse_spec

from .options import model_help


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "candidates", help="make candidate poses for `phd rank` (orbit, sphere, spiral, jitter, ...)",
        description="Write candidate camera poses as transforms-style JSON. SPEC is NAME[:COUNT][,key=value...]; "
                    "generators: " + "; ".join(f"{name}: {g.summary}" for name, g in GENERATORS.items()))
    p.add_argument("spec", help="e.g. orbit:64, orbit:48,rings=3, spiral:30, jitter:20,angle=10")
    p.add_argument("--model", type=Path, help="its training cameras, else its splats, place the poses: "
                   + model_help())
    p.add_argument("--data", type=Path, help="a capture (any format): its train split places the poses")
    p.add_argument("--cameras", type=Path, help="training cameras: transforms JSON or a reference cameras.json")
    p.add_argument("--out", type=Path, help="output JSON (default: print it)")
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


def run(args: argparse.Namespace) -> int:
    renderer = None
    cameras, points = scene_sources(args)
    if args.model is not None:
        from .models import open_model

        renderer = open_model(args.model).renderer
    if renderer is None and cameras is None:
        raise InputError("model", "give --model, --data or --cameras: the poses are placed around that scene")
    poses = make(args.spec, renderer, cameras, points)
    if args.out is None:
        print(json.dumps(frames_json(poses, args.spec), indent=1))
    else:
        from phd_core.io import write_json_atomic

        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(args.out, frames_json(poses, args.spec))
        print(f"{len(poses)} {args.spec.split(':')[0]} poses at {poses[0].width}x{poses[0].height} -> {args.out}")
    return 0
