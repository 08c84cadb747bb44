"""What every trainer-output reader returns, the registry they join, and the warning when a
folder's cameras do not see its splats (`scene.unseen_cameras`)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from ...errors import InputError, ModelNote, ModelWarning, bounded_notes
from ...registry import Registry
from ...scene import UNSEEN_SHARE, Camera, Similarity, unseen_cameras
from ..gs3d import GaussianModel, GaussianRenderer

DISTANCE_CHUNK = 1 << 20     # point-to-target distances computed at once (8 MB of float64)


@dataclass
class TrainerOutput:
    """A trainer's output folder resolved, everything in the user's frame."""

    model: GaussianModel                   # the splats, moved into the user's frame
    cameras: list[Camera]                  # training cameras ([] when the folder does not say)
    background: tuple[float, float, float]
    source: Path                           # the file the splats were read from
    ply: Path | None = None                # that file, when it holds exactly `model` (uploadable as is)
    frame: Similarity | None = None        # user frame -> the trainer's frame (None: the same frame)
    camera_format: str | None = None       # the pose convention of the user's capture (phd_core.data.POSES)
    name: str = ""                         # what to call the model: the run, "<experiment>/<method>" (read_output
                                           # falls back to the folder's name)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    capture: Path | None = None            # the capture the run read, as `phd_core.data.load_dataset` opens it
    # The run's own split: "train" and "test" frames as indices into the capture's "all" split
    # ({}: the capture's own splits are the run's).
    splits: dict[str, list[int]] = field(default_factory=dict)

    def renderer(self) -> GaussianRenderer:
        """The splats with their training cameras, background and what loading noted (its facts' notes)."""
        return GaussianRenderer(self.model, self.background, self.cameras or None, camera_format=self.camera_format,
                                notes=self.notes + self.warnings)


@dataclass(frozen=True)
class OutputFormat:
    name: str
    title: str                                   # for messages: "a nerfstudio splatfacto output folder"
    detect: Callable[[Path], bool]               # True when a folder is this trainer's output
    read: Callable[[Path, Path | None], TrainerOutput]   # (folder, read nothing outside this folder unless None)
    order: int = 100                             # detection order, lowest first (`read_output`)


OUTPUTS: Registry[OutputFormat] = Registry("trainer output folder")


def read_output(path: str | Path, within: str | Path | None = None, *, warn: bool = True) -> TrainerOutput:
    """The first trainer output, by `order`, that recognises the folder, read; its notes and
    warnings (at most MAX_NOTES each, cut to NOTE_CHARS: they quote the folder's files) are
    also issued as Python warnings (ModelNote, ModelWarning) unless `warn` is False (the
    service keeps them with the model instead). The built-in ones look for different files
    (cameras.json + point_cloud/, config.yml, ckpts/); the order decides for a folder holding
    more than one. `within`: the capture a run names is only looked for inside that folder (the
    service passes the upload's own folder)."""
    path = Path(path)
    for output_format in OUTPUTS.in_order():
        if output_format.detect(path):
            output = output_format.read(path, None if within is None else Path(within))
            output.name = output.name or path.resolve().name
            empty = unseen_cameras(output.model.means.detach(), output.cameras)
            if empty:
                output.warnings.append(
                    f"{len(empty)} of the model's {len(output.cameras)} training cameras see almost none of its "
                    f"splats (fewer than {UNSEEN_SHARE:.0%} of the centres in view): the cameras and the splats "
                    "are probably in different frames, so renders will be empty and rankings meaningless")
            output.notes, output.warnings = bounded_notes(output.notes), bounded_notes(output.warnings)
            for note in output.notes if warn else ():
                warnings.warn(note, ModelNote, stacklevel=2)
            for warning in output.warnings if warn else ():
                warnings.warn(warning, ModelWarning, stacklevel=2)
            return output
    known = "; ".join(f.title for f in OUTPUTS.in_order())
    raise InputError("model", f"{path} is a folder but no trainer output this project reads ({known})")


def load_output(path: str | Path) -> GaussianRenderer:
    """A trainer's output folder as a renderer with its training cameras and background."""
    return read_output(path).renderer()


def sh_from_parts(dc: torch.Tensor, rest: torch.Tensor, field: str) -> torch.Tensor:
    """SH coefficients [G, K, 3] from the DC term [G, 3] (or [G, 1, 3]) and the rest [G, K-1, 3],
    as trainers store them apart; an InputError naming `field` when the shapes disagree."""
    dc = dc[:, None, :] if dc.dim() == 2 else dc
    if dc.dim() != 3 or rest.dim() != 3 or dc.shape[1:] != (1, 3) or rest.shape[0] != dc.shape[0] \
            or rest.shape[2] != 3:
        raise InputError(field, f"the DC colour must be [G, 3] or [G, 1, 3] and the higher SH terms [G, K-1, 3], got "
                                f"{list(dc.shape)} and {list(rest.shape)}")
    return torch.cat([dc, rest], dim=1)


def data_candidates(folder: Path, data: Path, within: Path | None = None) -> list[Path]:
    """Where the data path a trainer recorded may be now: itself when absolute, else relative
    to the working directory, the output folder or any folder above it (trainers record the
    path as they were given it, relative to where they ran). `within`: only places inside that
    folder (a folder uploaded to the service must not make it read the server's own files)."""
    places = [data] if data.is_absolute() else [base / data for base in (Path.cwd(), folder, *folder.resolve().parents)]
    return places if within is None else [p for p in places if p.resolve().is_relative_to(within.resolve())]


def nearest_distances(points: torch.Tensor, targets: torch.Tensor, k: int = 1) -> torch.Tensor:
    """For each of points [P, 3], the distance to the k-th nearest of targets [T, 3]: [P] float64
    (k = 2 skips the point itself when the points are among the targets), DISTANCE_CHUNK
    distances at a time (a capture's SfM points may be millions)."""
    out = torch.empty(points.shape[0], dtype=torch.float64)
    chunk = max(1, DISTANCE_CHUNK // max(1, targets.shape[0]))
    for start in range(0, points.shape[0], chunk):
        distances = torch.cdist(points[start:start + chunk].double(), targets.double())
        out[start:start + chunk] = distances.topk(k, dim=1, largest=False).values[:, -1]
    return out
