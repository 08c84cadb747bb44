"""`phd train`: fit a model of any family with a trainer (`phd_core.renderers.FAMILIES`) to a
capture. The flags every trainer takes are below; each family's own come from its
`train_options` dataclass, one flag per field."""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, fields
from pathlib import Path
from typing import get_type_hints

from phd_core.renderers import DEFAULT_FAMILY, FAMILIES, Family

from .options import add_background_arg, parse_background


def trainable() -> list[Family]:
    """The registered families with a trainer, by kind."""
    return sorted((family for family in FAMILIES.values() if family.trainer), key=lambda family: family.name)


def register(subparsers: argparse._SubParsersAction) -> None:
    families = trainable()
    kinds = ", ".join(family.name for family in families)
    p = subparsers.add_parser("train", help=f"train a model ({kinds}) on a capture",
                              description="Train on the train split; saves the model with its training cameras.")
    p.add_argument("--model", choices=[family.name for family in families], default=DEFAULT_FAMILY,
                   help=f"model family (default {DEFAULT_FAMILY})")
    p.add_argument("--data", required=True, type=Path, help="capture: Blender/nerfstudio transforms, a COLMAP "
                   "scene (images/ + sparse/0), or LLFF poses_bounds.npy (its train split)")
    p.add_argument("--views", default="16",
                   help="number of evenly spaced training views, or a comma-separated index list (default 16)")
    p.add_argument("--downscale", type=float, default=2.0, help="image downscale factor (default 2)")
    p.add_argument("--iterations", type=int, default=None, help="optimisation steps (default: the trainer's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, type=Path, help="output file (" + ", ".join(
        f"{family.extension} for {family.name}" for family in families) + ")")
    for family in families:
        add_option_flags(p, family)
    own = ", ".join(family.name for family in families if family.set_background is None)
    add_background_arg(p, "the colour to train over (images with alpha are composited on it; the model is "
                       "rendered over it). Default: white for captures with alpha masks; for real captures the "
                       f"images' mean colour, or white for models that keep their own background ({own})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
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


def run(args: argparse.Namespace) -> int:
    views = parse_views(args.views)
    started = time.perf_counter()
    family = FAMILIES[args.model]
    options = {} if family.train_options is None else asdict(family.train_options(
        **{field.name: getattr(args, field.name) for field in fields(family.train_options)}))
    background = parse_background(args.background)
    if background is not None:
        options["background"] = list(background)
    renderer = family.train(args.data, views=views, downscale=args.downscale, iterations=args.iterations,
                            seed=args.seed, out=args.out, progress=not args.quiet, **options)
    print(f"trained {renderer.kind} with {renderer.num_units} dropout units in "
          f"{time.perf_counter() - started:.1f} s -> {args.out}")
    return 0
