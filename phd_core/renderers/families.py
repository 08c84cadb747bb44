"""Model families and loading: any supported model is recognised by its content, never by
its file name.

`FAMILIES` maps a kind (the renderer's `kind`) to a `Family`: how its files are recognised (a
3DGS PLY starts with `ply`; a NeRF checkpoint is a safetensors file marked as ours), how
they are loaded, which file extension the service stores them under, which trainer
`phd train` calls (named, so loading a model never imports a trainer) with which options,
how much memory a render of one camera takes (`RenderMemory`, which the service budgets
with), whether it renders over a background given, where its content lies, and what the API
shows of it. The CLI and the service know a family only through this entry. Anything no family
recognises (a pickle, an archive, random bytes) is refused before it is parsed, so no file
can execute code on load. A new family is one module defining its `Family` plus one
`FAMILIES.register` call (`phd_core/renderers/__init__.py` registers the built-in ones); the
CLI and the service take their names from here. Trainers' output folders are read by
`phd_core.renderers.outputs` (one module per trainer); this module never imports a family.
"""

from __future__ import annotations

import importlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from ..errors import InputError, ModelWarning, check_color
from ..registry import Registry
from ..scene import Camera, unseen_cameras
from .protocol import Renderer, RenderMemory

SNIFF_BYTES = 4096


def option(default: Any, help: str, choices: Sequence[str] | None = None) -> Any:
    """A field of a family's training options: its default, the help of its `phd train` flag
    and, for a string, the values allowed."""
    return field(default=default, metadata={"help": help, "choices": choices})


@dataclass(frozen=True)
class Family:
    """One model family: how its files are recognised, loaded, stored, shown and trained."""

    name: str                                               # the kind: the renderer's `kind`
    title: str                                              # for messages: "a 3DGS PLY"
    extension: str                                          # file extension the service stores it under
    sniff: Callable[[bytes], bool]                          # True for the first SNIFF_BYTES of its files
    load: Callable[[bytes, str, list[Camera] | None], Renderer]   # (content, name, training cameras or None)
    # The callables below are given only renderers this family loaded, so each takes its own
    # renderer class: the parameter is Any (a Renderer would refuse them as too narrow).
    beside: Callable[[Path, Any], Renderer] | None = None   # extras stored next to a model file
    trainer: str | None = None                              # "module:function" that `phd train` calls
    # The trainer's own options: a dataclass whose fields (made with `option`) are `phd train`
    # flags and are checked when it is built; None: the trainer takes only the common ones.
    train_options: type | None = None
    memory: Callable[[Any, Camera], RenderMemory] | None = None   # bounds of one camera's render
                                                            # (None: unknown; the service assumes its worst case)
    # Renders over the colour given (a checked [r, g, b]); None: the model carries its own.
    set_background: Callable[[Any, tuple[float, float, float]], None] | None = None
    units: str = "dropout units"                            # what its dropout units are: "splats"
    # Where its content lies: points [P, 3] (splat centres, a NeRF's occupied cells), which
    # `unseen_views` projects to tell cameras that see none of it; None: unknown.
    content_points: Callable[[Any], Any] | None = None
    network: tuple[str, ...] = ()                           # describe() keys the API shows as its network's size

    def train(self, data: str | Path, **kwargs: Any) -> Renderer:
        """Run the family's trainer on a capture (imported only now: loading never needs it)."""
        if self.trainer is None:
            raise InputError("model", f"{self.name} models cannot be trained here")
        module, function = self.trainer.split(":")
        return getattr(importlib.import_module(module), function)(data, **kwargs)


FAMILIES: Registry[Family] = Registry("model family")


class UnknownModelError(InputError):
    """No registered family recognises the content."""

    def __init__(self, name: str):
        super().__init__("model", f"{name} is neither {family_titles('nor')} (the kind is detected from the content, "
                                  "not the file name)")


def accepts_background(renderer: Renderer) -> bool:
    """Whether `renderer`'s family renders over a colour given (else its model carries its own)."""
    family = FAMILIES.get(renderer.kind)
    return family is not None and family.set_background is not None


def set_background(renderer: Renderer, color: Sequence[float] | str) -> None:
    """Render `renderer` over `color` (a name or [r, g, b] in [0, 1]): the colour it was trained
    over. A model that carries its own background (a NeRF checkpoint) refuses, naming the field."""
    if not accepts_background(renderer):
        raise InputError("background", f"a {renderer.kind} model carries its own background (set at training)")
    setter = FAMILIES[renderer.kind].set_background
    assert setter is not None                  # accepts_background checked it
    setter(renderer, check_color(color, "background"))


def unseen_views(renderer: Renderer, cameras: Sequence[Camera]) -> list[int]:
    """The cameras that see almost none of the model (`scene.unseen_cameras` of its family's
    `content_points`) when they are most of `cameras`, as another capture's cameras are; [] for a
    family that does not say where its content lies."""
    family = FAMILIES.get(renderer.kind)
    if family is None or family.content_points is None:
        return []
    return unseen_cameras(family.content_points(renderer), cameras)


def family_titles(conjunction: str) -> str:
    """The registered families' titles joined by `conjunction` ("or", "nor"), for messages and help."""
    return f" {conjunction} ".join(family.title for family in FAMILIES.values())


def family_of(head: bytes) -> Family | None:
    """The family whose files start like `head` (the first SNIFF_BYTES of a file), or None."""
    return next((f for f in FAMILIES.values() if f.sniff(head)), None)


def model_kind(head: bytes) -> str | None:
    """The kind of a file from its first bytes, or None."""
    family = family_of(head)
    return None if family is None else family.name


def load_model_bytes(data: bytes, name: str = "model",
                     training_cameras: list[Camera] | None = None) -> Renderer:
    """Parse a model held in memory. `training_cameras` overrides any stored in the file."""
    family = family_of(data[:SNIFF_BYTES])
    if family is None:
        raise UnknownModelError(name)
    return family.load(data, name, training_cameras)


def load_model(path: str | Path) -> Renderer:
    """Load a model file, with what its family keeps next to it (a PLY's sidecar `<stem>.json`
    from `phd train`: training cameras and background), or a trainer's output folder as is
    (`phd_core.renderers.outputs`: the reference 3DGS trainer, nerfstudio's splatfacto, gsplat).
    What the model's facts note (`describe()["notes"]`: a PLY in nerfstudio's internal frame, no
    training cameras) is also issued as a ModelWarning."""
    path = Path(path)
    if path.is_dir():
        from .outputs import load_output

        return load_output(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError("model", f"cannot read {path}: {exc.strerror or exc}") from None
    family = family_of(data[:SNIFF_BYTES])
    if family is None:
        raise UnknownModelError(path.name)
    renderer = family.load(data, path.name, None)
    renderer = renderer if family.beside is None else family.beside(path, renderer)
    for note in renderer.describe().get("notes", []):       # printed by the CLI, kept in the model's facts
        warnings.warn(note, ModelWarning, stacklevel=2)
    return renderer
