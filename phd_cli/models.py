"""The one way every command opens a model and the views it works on.

A model is a file of any registered family (a PLY with its `phd train` sidecar, a NeRF
checkpoint) or a trainer's output folder as the trainer left it (`phd_core.renderers.outputs`:
the reference 3DGS trainer's, splatfacto's, gsplat's). A folder brings its own cameras and,
when the capture it was trained on is found, that capture and the run's own train/test split:
`phd render --model <run>` renders the frames the run held out, with no --data or --split. A
model file trained by `phd train` names its capture too: without --data, commands use it.

A capture given with --data must be the one the model was trained on (`check_capture`).
Refused are: a capture holding images of the run's own capture at other poses (`check_frame`;
a splatfacto run, for example, holds its poses in the frame of the transforms.json it read, not
in that of the COLMAP folder ns-process-data started from); one whose cameras see almost none
of the model; one other than the recorded capture (known by its fingerprint wherever it lies,
else by its path) that holds none of the model's training views; and one whose photos fit the
model far worse than its training views did (`phd_core.renderers.provenance`), as photos of
another scene at the model's very poses do. --other-capture makes the last three a note.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

from phd_core.data import Dataset, load_dataset, locate, select_views
from phd_core.data.identity import fingerprint
from phd_core.errors import InputError, ModelNote
from phd_core.renderers import Renderer, load_model, unseen_views
from phd_core.renderers.outputs import TrainerOutput, read_output
from phd_core.renderers.provenance import FIT_MARGIN, Fit, TrainedOn, falls_short, measure_fit
from phd_core.scene import UNSEEN_SHARE, Camera, pose_matches

from .options import apply_background


@dataclass
class OpenedModel:
    path: Path
    renderer: Renderer
    output: TrainerOutput | None = None         # a trainer's folder: what it holds (capture, split)
    checked: set[Path] = field(default_factory=set)     # captures already checked (check_capture)

    @property
    def label(self) -> str:
        return str(self.path)

    @property
    def trained_on(self) -> TrainedOn | None:
        """The capture the model was trained on: what its sidecar or checkpoint records, or the
        capture a trainer's folder names (by path alone); None when nothing names one."""
        if self.output is not None:
            return None if self.output.capture is None else TrainedOn(str(self.output.capture), None)
        return TrainedOn.from_fields(self.renderer.describe().get("trained_on") or {})


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
                with_images: bool = True, other_capture: bool = False) -> Dataset:
    """The frames of `split` of `data` (default: the capture the model was trained on), or, for
    a trainer's folder, of the capture its run read and by the run's own split when `data` is
    left out or names that capture. `views`: a count of evenly spaced frames of the split, or
    indices into it. `data` is checked to be the model's capture (`check_capture`)."""
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
    data = capture_of(model, data)
    check_capture(model, data, other_capture)
    return load_dataset(data, split, views=views, downscale=downscale, background=background,
                        with_images=with_images)


def capture_of(model: OpenedModel, data: Path | None) -> Path:
    """`data`, else the capture the model names (a trainer's folder: its run's); an error saying
    what to give when it names none or the capture is no longer where it was."""
    if data is not None:
        return Path(data)
    recorded = model.trained_on
    if model.output is not None:
        if model.output.capture is not None:
            return model.output.capture
        raise InputError("data", "give --data: its run's capture was not found")
    if recorded is None or recorded.path is None:
        raise InputError("data", "give --data: the model names no capture (a model file trained by phd train names "
                                 "the one it was trained on in its sidecar or checkpoint)")
    if not Path(recorded.path).exists():
        raise InputError("data", f"give --data: {model.label} was trained on {recorded.path}, which is no longer "
                                 "there (a capture moved elsewhere is known by its fingerprint)")
    return Path(recorded.path)


def same_capture(data: Path, capture: Path) -> bool:
    """Whether `data` names `capture`: read as the same format, the same file or a folder holding it
    (a COLMAP scene folder holds its sparse/0 model). Located by their train split, which every
    format has (a Blender capture has no "all")."""
    try:
        (data_format, located), (capture_format, target) = locate(data, "train"), locate(capture, "train")
    except InputError:
        return False
    return data_format is capture_format and target.resolve().is_relative_to(located.resolve())


def check_capture(model: OpenedModel, data: Path, other_capture: bool = False) -> None:
    """Refuse a capture that is not the one the model was trained on: one in another frame
    (`check_frame`, whatever `other_capture` says), or one `capture_problem` finds; with
    `other_capture` the latter is a note. Each capture is checked once per model."""
    if Path(data).resolve() in model.checked:
        return
    check_frame(model, data)
    refuse("data", capture_problem(model, data), other_capture, "give the capture it was trained on")
    model.checked.add(Path(data).resolve())


def check_cameras_see(model: OpenedModel, cameras: list[Camera], other_capture: bool = False) -> None:
    """Refuse cameras most of which see almost none of the model (another capture's, or in
    another frame): renders from them are empty, and a calibration on them meaningless."""
    problem = unseen_problem(model, cameras)
    refuse("cameras", None if problem is None else f"{problem}: they are not the cameras of its capture",
           other_capture, "give the cameras it was trained on")


def refuse(field: str, problem: str | None, other_capture: bool, instead: str) -> None:
    """An InputError naming `field` for `problem`, or with `other_capture` a note; nothing without one."""
    if problem is None:
        return
    if not other_capture:
        raise InputError(field, f"{problem}; {instead} (or --other-capture to go on all the same)")
    warnings.warn(f"{problem} (--other-capture: going on)", ModelNote, stacklevel=3)


def unseen_problem(model: OpenedModel, cameras: list[Camera]) -> str | None:
    """That most of `cameras` see almost none of the model (`phd_core.renderers.unseen_views`), or None."""
    unseen = unseen_views(model.renderer, cameras)
    if not unseen:
        return None
    return (f"{len(unseen)} of the {len(cameras)} cameras see almost none of {model.label} (fewer than "
            f"{UNSEEN_SHARE:.0%} of it in view)")


def capture_problem(model: OpenedModel, data: Path) -> str | None:
    """Why `data` is not the capture the model was trained on, or None when it is or nothing tells.

    It is not when most of its cameras see almost none of the model; when, other than the
    recorded capture (by its fingerprint; for sidecars written before fingerprints and for
    trainer folders, by its path), it holds none of the model's training views; or when its
    photos fit the model more than FIT_MARGIN dB worse than the model's training views did
    (`provenance`: the fit recorded at training, else measured now on the recorded capture), as
    photos of another scene at the model's very poses do. Without photos or a fit to compare
    with, the recorded capture passes silently and any other with a note."""
    recorded, split = model.trained_on, load_dataset(data, "train", with_images=False)
    identified = recorded is not None and (recorded.fingerprint == fingerprint(split) if recorded.fingerprint else
                                           same_capture(data, Path(recorded.path or "")))
    if identified and recorded is not None:
        named = (f"{data} has the image names and poses of {recorded.path}, the capture {model.label} was trained "
                 "on, but other photos")
    else:
        named = f"{data} is not the capture {model.label} was trained on" + (
            "" if recorded is None else f" ({recorded.path})")
    unseen = unseen_problem(model, split.cameras)
    if unseen is not None:
        return f"{named}: {unseen}"
    reference, unread = training_fit(model, recorded), None
    try:
        given = measure_fit(model.renderer, data, split)
    except InputError as exc:                     # its photos are not there, or not readable
        given, unread = None, exc
    fit = ("" if reference is None or given is None else
           f"{len(given.frames)} of its views render at {given.psnr:.1f} dB PSNR against its photos, "
           f"{reference.psnr - given.psnr:.1f} dB below the {reference.psnr:.1f} dB the model reached on "
           f"{len(reference.frames)} of its training views")
    training = model.renderer.training_cameras or []
    if not identified and recorded is not None and training and \
            all(i is None for i in pose_matches(training, split.cameras)):
        return f"{named}: it holds none of the model's {len(training)} training views" + (
            f", and {fit}" if fit else "")
    if reference is not None and given is not None:
        return f"{named}: {fit} (more than {FIT_MARGIN:g} dB below)" if falls_short(given, reference) else None
    if not identified:
        why = (f"the photos of {data} could not be read ({unread})" if unread is not None else
               f"{model.label} names no capture it was trained on" if recorded is None else
               f"{model.label} records no fit on {recorded.path}, which is not at hand")
        warnings.warn(f"{why}: that {data} is its capture was checked by its cameras alone", ModelNote, stacklevel=3)
    return None


def training_fit(model: OpenedModel, recorded: TrainedOn | None) -> Fit | None:
    """The fit the model reached on its training views: recorded at training, else measured now
    on the capture it names when that is at hand."""
    if recorded is None or recorded.fit is not None:
        return None if recorded is None else recorded.fit
    if recorded.path is None or not Path(recorded.path).exists():
        return None
    try:
        return measure_fit(model.renderer, recorded.path)
    except InputError:
        return None


def check_frame(model: OpenedModel, data: Path) -> None:
    """Refuse a capture that holds images of the run's own capture (same names) at other poses
    than the model's training cameras: the model's views in another frame."""
    training = list(model.renderer.training_cameras or [])
    own = model.output.capture if model.output is not None else None
    if not training or own is None:
        return
    capture = _capture(data)
    if any(match is not None for match in pose_matches(training, capture.cameras)):
        return
    names = {Path(name).stem for name in _capture(own).names or []}
    shared = sorted({Path(name).stem for name in capture.names or []} & names)
    if shared:
        raise InputError("data", f"{data} is not in the frame of {model.label}: it holds {len(shared)} images of the "
                                 f"run's capture ({', '.join(shared[:3])}{', ...' if len(shared) > 3 else ''}) at "
                                 f"other poses, so renders would show the model from wrong poses (a splatfacto "
                                 f"run's poses are those of the transforms.json it read, not of the COLMAP model it "
                                 f"came from); give {own}, or leave --data out")


def _capture(data: Path) -> Dataset:
    """Every camera of a capture, with its image names: its "all" split, else its "train" split
    (Blender has no "all")."""
    try:
        return load_dataset(data, "all", with_images=False)
    except InputError:
        return load_dataset(data, "train", with_images=False)
