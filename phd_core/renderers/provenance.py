"""What a model records of the capture it was trained on, and how well a capture's photos fit
the model: how photos other than its capture's are caught.

A trainer records a `TrainedOn` (the `phd train` sidecar's keys, a checkpoint's metadata): the
capture's path (a hint: captures move), its format, its fingerprint (`phd_core.data.identity`:
the image names and camera centres of its train split) and the model's fit on it: the PSNR
of FIT_VIEWS of its training views rendered at FIT_SIZE pixels against their photos
(`measure_fit`). A capture given later with the same fingerprint has the model's views
wherever it lies; its photos, and those of any other capture, are measured the same way, on its
frames at the model's training poses when it has them (else on evenly spaced frames of its
train split), and are not the model's capture's when their fit falls more than FIT_MARGIN dB
below the recorded one (`falls_short`; the measurements that chose the margin are in
docs/formats.md, "The wrong capture caught").

Without photos, cameras tell only their frame: `phd_core.renderers.unseen_views` finds those
that see almost none of a model.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any, Sequence

from pydantic import BaseModel, ConfigDict, Field

from ..data import Dataset, load_dataset, locate, select_views
from ..data.identity import fingerprint
from ..io.configs import MAX_PATH_BYTES, parse_config
from ..scene import DEFAULT_MAX_SIZE, Camera, pose_matches
from .protocol import Renderer

FIT_VIEWS = 4            # views a fit is measured on
FIT_SIZE = 64            # pixels on their longer side: a few renders of this size cost well under a second
FIT_MARGIN = 3.0         # dB: photos whose fit falls further below the model's own are not its capture's
                         # (measured: its own photos rewritten lose at most 0.3 dB, another scene's 4.2 or more)


@dataclass(frozen=True)
class Fit:
    """How well a model renders a capture's photos: the PSNR of the views' pooled squared error."""

    psnr: float
    frames: list[int]        # the frames of the capture's train split it was measured on
    width: int               # the size they were rendered at (the first, when sizes differ)
    height: int


@dataclass(frozen=True)
class TrainedOn:
    """What a model records of the capture it was trained on."""

    path: str | None                    # where the capture lay at training: a hint, since captures move
    format: str | None                  # its format (phd_core.data.FORMATS)
    fingerprint: str | None = None      # its train split's identity (phd_core.data.identity)
    fit: Fit | None = None              # what the model reached on its training views (`measure_fit`)

    def fields(self) -> dict[str, Any]:
        """As a sidecar and a checkpoint store it (sidecars before the fingerprint hold the first two)."""
        return {"dataset": self.path, "dataset_format": self.format, "dataset_fingerprint": self.fingerprint,
                "training_fit": None if self.fit is None else asdict(self.fit)}

    @classmethod
    def from_fields(cls, fields: Any) -> "TrainedOn | None":
        """What `fields` wrote, read back (checked as `_Record`: a model file is a user's file);
        None when no capture is named."""
        record = parse_config(_Record, fields, "trained_on")
        if record.dataset is None:
            return None
        fit = record.training_fit
        return cls(record.dataset, record.dataset_format, record.dataset_fingerprint,
                   None if fit is None else Fit(fit.psnr, fit.frames, fit.width, fit.height))


class _FitRecord(BaseModel):
    psnr: Annotated[float, Field(allow_inf_nan=False)]
    frames: Annotated[list[Annotated[int, Field(ge=0)]], Field(max_length=FIT_VIEWS)]
    width: Annotated[int, Field(ge=1, le=DEFAULT_MAX_SIZE)]
    height: Annotated[int, Field(ge=1, le=DEFAULT_MAX_SIZE)]


class _Record(BaseModel):
    """`TrainedOn.fields()` as a sidecar or checkpoint holds it, bounded: its text reaches the
    model's facts and messages. Sidecars written before the fingerprint hold the first two."""

    model_config = ConfigDict(extra="ignore")
    dataset: Annotated[str, Field(max_length=MAX_PATH_BYTES)] | None = None
    dataset_format: Annotated[str, Field(max_length=64)] | None = None
    dataset_fingerprint: Annotated[str, Field(max_length=128)] | None = None
    training_fit: _FitRecord | None = None


def record_training(renderer: Renderer, capture: str | Path) -> TrainedOn:
    """What a trainer records of `capture` after training `renderer` on its train split."""
    data_format, _ = locate(capture, "train")
    split = load_dataset(capture, "train", with_images=False)
    return TrainedOn(str(Path(capture).resolve()), data_format.name, fingerprint(split),
                     measure_fit(renderer, capture, split))


def measure_fit(renderer: Renderer, capture: str | Path, split: Dataset | None = None, name: str = "train") -> Fit:
    """`renderer`'s fit on FIT_VIEWS frames of the split `name` of `capture` (`split`: that split
    loaded without images, if at hand), rendered at FIT_SIZE pixels against their photos
    composited on the model's background: the frames at the model's training poses when the
    split has them, else evenly spaced ones."""
    split = split if split is not None else load_dataset(capture, name, with_images=False)
    frames = fit_frames(split.cameras, renderer.training_cameras or [])
    first = split.cameras[frames[0]]
    background = tuple(renderer.describe().get("background") or (1.0, 1.0, 1.0))
    photos = load_dataset(capture, name, views=frames, downscale=max(1.0, max(first.width, first.height) / FIT_SIZE),
                          background=background)
    assert photos.images is not None                    # loaded with its images (the default)
    squared = [float(((renderer.render(camera)[0].double() - photo.double()) ** 2).mean())
               for camera, photo in zip(photos.cameras, photos.images)]
    mse = max(sum(squared) / len(squared), 1e-10)       # identical images: 100 dB, not infinity
    return Fit(round(10 * math.log10(1 / mse), 2), frames, photos.cameras[0].width, photos.cameras[0].height)


def fit_frames(cameras: Sequence[Camera], training: Sequence[Camera]) -> list[int]:
    """FIT_VIEWS evenly spaced frames of `cameras` among those at a pose of `training` (the
    model's training views), or among all of them when none is."""
    shared = sorted({i for i in pose_matches(training, cameras) if i is not None}) if training else []
    pool = shared or list(range(len(cameras)))
    return [pool[i] for i in select_views(len(pool), min(FIT_VIEWS, len(pool)))]


def falls_short(given: Fit, reference: Fit) -> bool:
    """Whether a capture's fit is so far below the model's own that it is another capture."""
    return given.psnr < reference.psnr - FIT_MARGIN
