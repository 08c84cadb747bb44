"""The one way every command opens a model and the views it works on.

A model is a file of any registered family (a PLY with its `phd train` sidecar, a NeRF
checkpoint) or a trainer's output folder as the trainer left it (`phd_core.renderers.outputs`:
the reference 3DGS trainer's, splatfacto's, gsplat's). A folder brings its own cameras and,
when the capture it was trained on is found, that capture and the run's own train/test split:
`phd render --model <run>` renders the frames the run held out, with no --data or --split.

A capture given with --data must be in the model's frame (`check_frame`): a capture holding
images of the run's own capture at other poses is refused with what to give instead. A
splatfacto run, for example, holds its poses in the frame of the transforms.json it read, not
in that of the COLMAP folder ns-process-data started from.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

from phd_core.data import Dataset, load_dataset, locate, select_views
from phd_core.errors import InputError, ModelNote
from phd_core.renderers import Renderer, load_model
from phd_core.renderers.outputs import TrainerOutput, read_output
from phd_core.scene import Camera

from .options import apply_background

SAME_POSE = 1e-3         # centres this close (x the cameras' spread) and directions this close (radians) coincide


@dataclass
class OpenedModel:
    path: Path
    renderer: Renderer
    output: TrainerOutput | None = None         # a trainer's folder: what it holds (capture, split)
    checked: set[Path] = field(default_factory=set)     # captures found in its frame (check_frame)

    @property
    def label(self) -> str:
        return str(self.path)


def open_model(path: Path, background: list[str] | None = None) -> OpenedModel:
    """A model file or a trainer's output folder, rendered over --background when given."""
    path = Path(path)
    if path.is_dir():
        output = read_output(path)
        opened = OpenedModel(path, output.renderer(), output)
    else:
        opened = OpenedModel(path, load_model(path))
    apply_background(opened.renderer, background)
    return opened


def model_views(model: OpenedModel, data: Path | None, split: str, *, views: int | list[int] | None = None,
                downscale: float = 1.0, background: tuple[float, float, float] = (1.0, 1.0, 1.0),
                with_images: bool = True) -> Dataset:
    """The frames of `split` of `data`, or, for a trainer's folder, of the capture its run read
    and by the run's own split when `data` is left out or names that capture. `views`: a count
    of evenly spaced frames of the split, or indices into it."""
    output = model.output
    if output is not None and output.capture is not None and (data is None or same_capture(data, output.capture)):
        options = dict(downscale=downscale, background=background, with_images=with_images)
        if split == "all" or not output.splits:
            return load_dataset(output.capture, split, views=views, **options)
        frames = output.splits.get(split)
        if frames is None:
            raise InputError("split", f"{model.label} was trained with the splits {', '.join(output.splits)} "
                                      f"(and all), not {split!r}")
        if not frames:
            raise InputError("split", f"the run {model.label} held no frame of its capture in its {split} split: "
                                      "give --split train or all")
        chosen = [frames[i] for i in select_views(len(frames), views)]
        dataset = load_dataset(output.capture, "all", views=chosen, **options)
        dataset.split = split
        return dataset
    if data is None:
        where = ("its run's capture was not found" if output is not None else
                 "a model file names no capture (the one it was trained on: the --data given to phd train)")
        raise InputError("data", f"give --data: {where}")
    check_frame(model, Path(data))
    return load_dataset(data, split, views=views, downscale=downscale, background=background,
                        with_images=with_images)


def same_capture(data: Path, capture: Path) -> bool:
    """Whether `data` names `capture`: read as the same format, the same file or a folder holding it
    (a COLMAP scene folder holds its sparse/0 model)."""
    try:
        (data_format, located), (capture_format, target) = locate(data, "all"), locate(capture, "all")
    except InputError:
        return False
    return data_format is capture_format and target.resolve().is_relative_to(located.resolve())


def check_frame(model: OpenedModel, data: Path) -> None:
    """Refuse a capture that is not in the model's frame. It is when one of the model's training
    cameras appears among its cameras (same centre and viewing direction); it is not when it
    holds images of the run's own capture (same names) at other poses. Otherwise (a capture of
    other views, a model without training cameras) it cannot be told, and a note says so."""
    training = list(model.renderer.training_cameras or [])
    if not training or Path(data).resolve() in model.checked:
        return
    model.checked.add(Path(data).resolve())
    capture = _capture(data)
    if appearing(training, capture.cameras):
        return
    own = model.output.capture if model.output is not None else None
    names = {Path(name).stem for name in _capture(own).names or []} if own is not None else set()
    shared = sorted({Path(name).stem for name in capture.names or []} & names)
    if shared:
        raise InputError("data", f"{data} is not in the frame of {model.label}: it holds {len(shared)} images of the "
                                 f"run's capture ({', '.join(shared[:3])}{', ...' if len(shared) > 3 else ''}) at "
                                 f"other poses, so renders would show the model from wrong poses (a splatfacto "
                                 f"run's poses are those of the transforms.json it read, not of the COLMAP model it "
                                 f"came from); give {own}, or leave --data out")
    warnings.warn(f"none of the {len(training)} training cameras of {model.label} is among the {len(capture.cameras)} "
                  f"of {data}: that they share a frame could not be checked", ModelNote, stacklevel=2)


def _capture(data: Path) -> Dataset:
    """Every camera of a capture, with its image names: its "all" split, else its "train" split
    (Blender has no "all")."""
    try:
        return load_dataset(data, "all", with_images=False)
    except InputError:
        return load_dataset(data, "train", with_images=False)


def appearing(cameras: list[Camera], capture: list[Camera]) -> int:
    """How many of `cameras` have a camera of `capture` at the same centre (within SAME_POSE
    times their spread) looking the same way (within SAME_POSE radians)."""
    centres = torch.stack([c.center for c in cameras])                                 # [N, 3]
    spread = float((centres - centres.median(dim=0).values).norm(dim=-1).median()) or 1.0
    forward = torch.stack([-c.c2w[:3, 2] for c in cameras])                            # [N, 3]
    other_centres = torch.stack([c.center for c in capture])                           # [M, 3]
    other_forward = torch.stack([-c.c2w[:3, 2] for c in capture])                      # [M, 3]
    close = torch.cdist(centres, other_centres) <= SAME_POSE * spread                  # [N, M]
    aligned = (forward @ other_forward.T).clamp(-1, 1).acos() <= SAME_POSE             # [N, M]
    return int((close & aligned).any(dim=1).sum())
