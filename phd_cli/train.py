"""`phd train`: fit a model of any family with a trainer (`phd_core.renderers.FAMILIES`) to a
capture. The flags every trainer takes are below; each family's own come from its
`train_options` dataclass, one flag per field."""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, fields
from pathlib import Path
from typing import get_type_hints

from phd_core.data import load_dataset
from phd_core.renderers import DEFAULT_FAMILY, FAMILIES, Family
from phd_core.scene import Camera

from .options import add_background_arg, parse_background
from .report import add_progress_args, bars_on, say

# Every trainer's default step count (phd_core.train.splats.TrainConfig.iterations and
# phd_core.train.nerf.DEFAULT_ITERATIONS; tests/cli/test_cli_report.py holds them equal) and what
# the default run costs: `/usr/bin/time -v phd train --data ../shared/data/lego_200 --out m.ply`
# (user + system time 246 s, wall 830 s with the load average at 11 on 2 cores; 26,336 splats).
DEFAULT_ITERATIONS = 2000
TIME_HINT = (f"{DEFAULT_FAMILY} (the default family) at the defaults, 16 views of lego_200 at 100x100: 4.1 "
             "minutes of CPU time (measured: 14 minutes of wall clock on 2 cores busy with other work)")
# That run's CPU time per step and pixel (246 s / (2000 steps x 100 x 100 pixels)): a step renders
# one training view, so a capture's own hint is steps x pixels of a view x this.
SECONDS_PER_PIXEL_STEP = 246 / (DEFAULT_ITERATIONS * 100 * 100)


def trainable() -> list[Family]:
    """The registered families with a trainer, by kind."""
    return sorted((family for family in FAMILIES.values() if family.trainer), key=lambda family: family.name)


def register(subparsers: argparse._SubParsersAction) -> None:
    families = trainable()
    kinds = ", ".join(family.name for family in families)
    p = subparsers.add_parser("train", help=f"train a model ({kinds}) on a capture",
                              description="Train on a split of a capture (default its train split); saves the model "
                              "with its training cameras.")
    p.add_argument("--model", choices=[family.name for family in families], default=DEFAULT_FAMILY,
                   help=f"model family (default {DEFAULT_FAMILY})")
    p.add_argument("--data", required=True, type=Path, help="capture: Blender/nerfstudio transforms, a COLMAP "
                   "scene (images/ + sparse/0), or LLFF poses_bounds.npy (its train split)")
    p.add_argument("--split", default="train",
                   help="the frames --views counts or indexes: the capture's train split (default), its test split "
                   "(val for Blender), or all its frames (COLMAP, LLFF, nerfstudio: e.g. a capture less its held-out "
                   "photos, given as --views indices)")
    p.add_argument("--views", default="16",
                   help="number of evenly spaced training views, or a comma-separated index list (default 16)")
    p.add_argument("--downscale", type=float, default=2.0, help="image downscale factor (default 2)")
    p.add_argument("--iterations", type=int, default=None, help=f"optimisation steps (default {DEFAULT_ITERATIONS}, "
                   f"every trainer's; {TIME_HINT}; the time grows about linearly with the steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--init", type=Path, default=None, metavar="MODEL",
                   help="continue from this model of the same family (a warm start: its splats, with "
                   "densification resumed and no opacity reset; e.g. the model of the capture before its latest "
                   "photos came). Short runs gain most: on cup_colmap, 8 then 12 views, +4.7 dB of test PSNR over "
                   "a cold start of the same steps at 100 steps, +2.1 at 200, even at 600 (-0.2 and +1.0 dB by seed). "
                   "Splat families only")
    p.add_argument("--out", required=True, type=Path, help="output file, named for its family (" + ", ".join(
        f"{family.extension} for {family.name}" for family in families) + "; a PLY gets a sidecar <stem>.json "
        "with its training cameras)")
    for family in families:
        add_option_flags(p, family)
    own = ", ".join(family.name for family in families if family.set_background is None)
    add_background_arg(p, "the colour to train over (images with alpha are composited on it; the model is "
                       "rendered over it). Default: white for captures with alpha masks; for real captures the "
                       f"images' mean colour, or white for models that keep their own background ({own})")
    add_progress_args(p)
    p.set_defaults(func=run)


def add_option_flags(parser: argparse.ArgumentParser, family: Family) -> None:
    """One flag per field of the family's training options (`--depth-distortion`), with its
    type, default, choices and help; a bool is a switch."""
    if family.train_options is None:
        return
    types = get_type_hints(family.train_options)
    for field in fields(family.train_options):
        flag, text = "--" + field.name.replace("_", "-"), f"{family.name}: {field.metadata['help']}"
        if types[field.name] is bool:
            parser.add_argument(flag, action="store_true", help=text)
        else:
            parser.add_argument(flag, type=types[field.name], default=field.default,
                                choices=field.metadata["choices"], help=text)


def parse_views(text: str) -> int | list[int]:
    from phd_core.errors import InputError
    try:
        return [int(v) for v in text.split(",")] if "," in text else int(text)
    except ValueError:
        raise InputError("views", f"expected a count or comma-separated indices, got {text!r}") from None


def check_out(out: Path, family: Family) -> None:
    """--out must carry the family's extension: a file named for another family is refused."""
    from phd_core.errors import InputError

    if out.suffix.lower() != family.extension:
        raise InputError("out", f"a {family.name} model is written as a {family.extension} file, got {out.name!r} "
                                f"(e.g. --out {out.with_suffix(family.extension)}, or choose the family with --model)")


def sizes(cameras: list[Camera]) -> str:
    """The views' count and size as a person reads them: "16 views at 100x100" (sizes listed when they differ)."""
    shown = sorted({f"{c.width}x{c.height}" for c in cameras})
    return f"{len(cameras)} view{'s' if len(cameras) != 1 else ''} at {', '.join(shown)}"


def time_hint(cameras: list[Camera], iterations: int) -> str:
    """What this capture's training should cost, from its own size: steps x pixels of a view
    at the CPU time per pixel-step the lego run above measured (more splats cost more)."""
    pixels = sum(c.width * c.height for c in cameras) / len(cameras)
    minutes = iterations * pixels * SECONDS_PER_PIXEL_STEP / 60
    rate = SECONDS_PER_PIXEL_STEP * 1e6
    return (f"training {sizes(cameras)} for {iterations} steps: about {minutes:.1f} minutes of CPU time ("
            f"{iterations} steps x {pixels:,.0f} pixels a view at the {rate:.1f} us a pixel-step {DEFAULT_FAMILY} "
            "took on lego_200; a capture that grows more splats takes longer, other families differ)")


def run(args: argparse.Namespace) -> int:
    views = parse_views(args.views)
    started = time.perf_counter()
    family = FAMILIES[args.model]
    check_out(args.out, family)
    cameras = load_dataset(args.data, args.split, views=views, downscale=args.downscale, with_images=False).cameras
    say(args, time_hint(cameras, args.iterations or DEFAULT_ITERATIONS))
    options = {} if family.train_options is None else asdict(family.train_options(
        **{field.name: getattr(args, field.name) for field in fields(family.train_options)}))
    background = parse_background(args.background)
    if background is not None:
        options["background"] = list(background)
    if args.init is not None:
        options["init"] = args.init
    renderer = family.train(args.data, views=views, downscale=args.downscale, iterations=args.iterations,
                            seed=args.seed, out=args.out, progress=bars_on(args), split=args.split, **options)
    print(f"trained {renderer.kind} with {renderer.num_units} dropout units on {sizes(cameras)} in "
          f"{time.perf_counter() - started:.1f} s -> {args.out}")
    return 0
