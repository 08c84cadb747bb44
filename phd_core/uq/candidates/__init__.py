"""Candidate-pose generators: where a next-best view may be taken from.

`GENERATORS` maps a name to a `Generator`; adding one is one module plus one
`GENERATORS.register` call. Built in: `orbit` (rings), `hemisphere` and `sphere` (look-at poses spread evenly),
`spiral` (forward-facing, for LLFF-like captures) and `jitter` (moved copies of the training
poses).

`candidate_cameras` is what users call: it places the poses around the scene
(`frame.scene_frame`: from the training cameras, else the splats) and gives them the
training cameras' intrinsics, so `candidate_cameras("orbit", 64, cameras=training)` needs
nothing else. A spec string "orbit:64,rings=3,elevation=0.4" names the same call
(`parse_spec`), for the CLI and the service.
"""

from __future__ import annotations

import inspect
import math
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import torch

from ...errors import InputError, check_int
from ...registry import Registry
from ...scene import Camera
from .frame import SceneFrame, scene_frame, scene_points
from .hemisphere import hemisphere_cameras, sphere_cameras
from .jitter import jitter_cameras
from .orbit import orbit_cameras
from .spiral import spiral_cameras


@dataclass(frozen=True)
class Generator:
    name: str
    summary: str                                  # one line for --help, the API schema and the docs
    generate: Callable[..., list[Camera]]         # (count, **options) -> count candidate poses


GENERATORS: Registry[Generator] = Registry("candidate generator")
GENERATORS.register(Generator("orbit", "look-at rings around the scene (rings, elevation, spread)", orbit_cameras))
GENERATORS.register(Generator("hemisphere", "look-at poses spread evenly (Fibonacci spiral) over a band of "
                              "the upper hemisphere", hemisphere_cameras))
GENERATORS.register(Generator("sphere", "look-at poses spread evenly over the whole sphere around the scene",
                              sphere_cameras))
GENERATORS.register(Generator("spiral", "a forward-facing spiral in front of the training cameras (LLFF-like "
                              "captures)", spiral_cameras))
GENERATORS.register(Generator("jitter", "copies of the training poses moved and turned a little (position, angle, "
                              "seed)", jitter_cameras))


def get_generator(name: str) -> Generator:
    """The registered generator called `name`, or an InputError listing the known names."""
    return GENERATORS.lookup(name, "generator")


# What the scene frame fills in when the caller leaves it out (only for generators that take it).
_LOOK_AT_INTRINSICS = ("width", "height", "fov_x")


def _derived(frame: SceneFrame, points: torch.Tensor | None) -> dict[str, Any]:
    values: dict[str, Any] = {"center": frame.center.tolist(), "radius": frame.radius, "up": frame.up.tolist(),
                              "elevation": frame.elevation, "cameras": frame.cameras, "points": points}
    if frame.template is not None:
        t = frame.template
        values.update(width=t.width, height=t.height, fov_x=2 * math.atan(t.width / (2 * t.fx)))
    return values


OWN_PARAMETERS = ("count", "cameras", "points", "renderer")   # candidate_cameras' own, never a generator option


def check_option_names(generator: str, options: Mapping[str, Any]) -> None:
    """Refuse an option named like one of `candidate_cameras`' own parameters: passed as
    **options it would bind to that parameter (or collide with it) instead of reaching the
    generator. Callers that forward a user's options check them with this first."""
    for key in options:
        if key in OWN_PARAMETERS:
            raise InputError(f"options.{key}", f"{key!r} is not an option of generator {generator!r}: the "
                                               "caller sets it (the pose count, or the scene the poses are placed "
                                               "around)")


def candidate_cameras(generator: str, count: int, *, cameras: Sequence[Camera] | None = None,
                      points: torch.Tensor | None = None, renderer: object | None = None,
                      **options: Any) -> list[Camera]:
    """`count` candidate poses from the generator called `generator`, placed around the scene.

    The scene comes from `cameras` (the training cameras; default the renderer's), else from
    `points` (default the renderer's opaque splats); with neither, the generator's own
    defaults hold (a Blender-like scene at the origin). Options the caller gives win over the
    derived ones; an option the generator does not take is an error naming it. Look-at poses
    get the training cameras' intrinsics (fx, fy, cx, cy, size) unless width, height or
    fov_x are given.
    """
    entry = get_generator(generator)
    count = check_int(count, "count", 1)
    if cameras is None and renderer is not None:
        cameras = getattr(renderer, "training_cameras", None)
    if points is None and renderer is not None:
        points = scene_points(renderer)
    accepted = inspect.signature(entry.generate).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in accepted.values())
    for key in options:
        if key not in accepted and not takes_any:        # OWN_PARAMETERS never get here: they bind above
            takes = sorted(k for k in accepted if k not in OWN_PARAMETERS)
            raise InputError(f"options.{key}", f"generator {generator!r} takes {', '.join(takes) or 'no options'}")
    frame = scene_frame(cameras, points, options.get("up")) if cameras or points is not None else None
    kwargs = dict(options)
    if frame is not None:
        for key, value in _derived(frame, points).items():
            if key in accepted and key not in kwargs:
                kwargs[key] = value
    for name, parameter in accepted.items():
        if name != "count" and parameter.default is inspect.Parameter.empty and name not in kwargs \
                and parameter.kind is not inspect.Parameter.VAR_KEYWORD:
            what = "the training cameras" if name == "cameras" else name
            raise InputError(name, f"generator {generator!r} needs {what}")
    try:
        poses = entry.generate(count, **kwargs)
    except (TypeError, ValueError, RuntimeError) as exc:
        if isinstance(exc, InputError):
            raise InputError(exc.field if exc.field.startswith(("count", "cameras")) else f"options.{exc.field}",
                             exc.reason) from None
        raise InputError("options", f"generator {generator!r} rejected the options: {exc}") from None
    template = frame.template if frame is not None else None
    if template is not None and "fov_x" in accepted and not set(_LOOK_AT_INTRINSICS) & set(options):
        poses = [Camera(p.c2w, template.fx, template.fy, template.cx, template.cy, template.width, template.height,
                        template.max_size) for p in poses]
    return poses


_SPEC = re.compile(r"([A-Za-z_][\w-]*)(?::(\d+))?((?:,[A-Za-z_]\w*=[^,]+)*)")


def parse_spec(text: str, default_count: int = 64) -> tuple[str, int, dict[str, Any]]:
    """"orbit:64,rings=3,up=0;0;1" -> ("orbit", 64, {"rings": 3, "up": [0, 0, 1]}).

    Values are numbers; a list of numbers is written with ';'. The generator name is
    checked against the registry."""
    match = _SPEC.fullmatch(text.strip()) if isinstance(text, str) else None
    if match is None:
        raise InputError("candidates", f"expected NAME[:COUNT][,key=value...] (e.g. orbit:64,rings=2), got {text!r}")
    name, count, rest = match.group(1), int(match.group(2) or default_count), match.group(3)
    get_generator(name)
    options: dict[str, Any] = {}
    for pair in filter(None, rest.split(",")):
        key, value = pair.split("=", 1)
        try:
            numbers = [float(v) for v in value.split(";")]
        except ValueError:
            raise InputError(f"options.{key}", f"must be a number (or numbers joined by ';'), got {value!r}") from None
        numbers = [int(v) if v.is_integer() and "." not in value and "e" not in value.lower() else v for v in numbers]
        options[key] = numbers if ";" in value else numbers[0]
    return name, count, options


__all__ = ["GENERATORS", "Generator", "SceneFrame", "candidate_cameras", "get_generator", "hemisphere_cameras",
           "jitter_cameras", "orbit_cameras", "parse_spec", "scene_frame", "scene_points",
           "sphere_cameras", "spiral_cameras"]
