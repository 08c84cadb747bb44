"""`run_capture`: photos or a video in, a capture folder out, in the layout the project's
COLMAP reader reads and the reference 3DGS trainer's convert.py writes:

    DIR/input/                 the photos structure-from-motion saw (photos.py), or the video's
                               frames (video.py)
    DIR/distorted/database.db  COLMAP's features and matches
    DIR/distorted/sparse/0/    the reconstruction with its lens model (SIMPLE_RADIAL by default)
    DIR/images/                the registered photos, undistorted
    DIR/sparse/0/              their PINHOLE cameras, poses and SfM points (.bin)
    DIR/phd_capture.json       this run's CaptureReport

Matching (`matcher="auto"`): a video's frames, and numbered photos, are in capture order, so
each is matched with its neighbours (sequential); an unordered set of at most EXHAUSTIVE_MAX
photos has every pair matched (exhaustive, n(n-1)/2 pairs); a larger unordered set is refused
rather than left to run for hours.

Registration: at least max(MIN_IMAGES, MIN_SHARE of the inputs) photos must register, unless
`min_registered` says otherwise. MIN_IMAGES = 8 leaves the test split (every 8th image) one
view and training seven; half the inputs, because a capture that registers fewer shows a part
of what the photos show (the rest failed, or formed models of their own), which the user
should hear now rather than find in a trained model.

Adding photos (`add_photos`, `phd capture NEW --add-to DIR`) extends a capture without
recomputing it: the new photos' features are extracted into a copy of its database, matched
with every photo of the capture (new x all pairs), and registered by the incremental mapper
started from the capture's reconstruction with its frames and cameras fixed, so every earlier
pose, intrinsic and the capture's frame stay as they were (a model trained on it stays in
place). A new photo of the capture's size shares its camera; another size gets a camera of its
own, refined. The registered photos are undistorted again (all of them, which is simpler than
merging two undistorted models and took 0.3 s for 23 photos at 300 px: the earlier ones come
out byte for byte the same, tested), and the copy replaces the capture. A photo that shares too
little with the capture (a photo of something else) does not register; when none does, nothing
is written.

Every size is bounded before work: the number of photos (`max_images`; a video is sampled to
at most that many frames), the pixels of each (`max_size` on the longer side; larger photos
are downscaled first), and an output folder that exists and is not empty is refused unless
`overwrite` and it holds an earlier phd_capture.json (nothing else is ever deleted). The folder
is built beside DIR, loaded back with `phd_core.data.load_dataset` (every image read at its
camera's size), and only then renamed into place: DIR holds a whole capture or none.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator, Sequence

from ..data import load_dataset
from ..errors import InputError, check_float, check_int
from ..io import write_json_atomic
from .photos import PHOTO_SUFFIXES, VIDEO_SUFFIXES, capture_order, input_names, is_video, list_photos, write_photo

if TYPE_CHECKING:
    from .sfm import Progress

MATCHERS = ("auto", "sequential", "exhaustive")
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE", "SIMPLE_PINHOLE", "PINHOLE")
STAGES = ("input", "features", "matching", "mapping", "undistortion", "check")
EXHAUSTIVE_MAX = 100           # photos; 4,950 pairs
MIN_IMAGES = 8
MIN_SHARE = 0.5
DEFAULT_MAX_SIZE = 1600        # px, longer side
DEFAULT_MAX_IMAGES = 300
DEFAULT_FPS = 2.0
REPORT = "phd_capture.json"

StageProgress = Callable[[str, float], None]      # (stage, fraction of it done)


@dataclass
class CaptureReport:
    """What `run_capture` did: counts, the choices it made and why, seconds per stage."""

    out: str
    source: str                   # "photos" or "video"
    inputs: int                   # photos given, or frames sampled from the video
    registered: list[str]         # names in images/, sorted
    matcher: str                  # "sequential" or "exhaustive"
    matcher_reason: str
    pairs: int                    # image pairs matched
    camera_model: str             # of the distorted model
    cameras: int                  # 1 shared by every photo, or one per photo
    points: int                   # SfM points
    reprojection_error: float     # mean, px
    origins: dict[str, str]       # input/ name -> the photo, or the video and time, it came from
    notes: list[str]              # what was done to the inputs, in a sentence each
    seconds: dict[str, float] = field(default_factory=dict)   # per stage (STAGES)
    pycolmap: str = ""                                          # its version
    added: list[str] = field(default_factory=list)             # add_photos: the photos it registered
    not_registered: list[str] = field(default_factory=list)    # add_photos: those it could not

    @property
    def share(self) -> float:
        """The share of the inputs that registered."""
        return len(self.registered) / self.inputs


def registration_threshold(inputs: int) -> int:
    """How many of `inputs` images must register, by default (the module docstring)."""
    return max(MIN_IMAGES, math.ceil(MIN_SHARE * inputs))


def run_capture(inputs: str | Path | Sequence[str | Path], out: str | Path, *, matcher: str = "auto",
                max_size: int = DEFAULT_MAX_SIZE, max_images: int = DEFAULT_MAX_IMAGES, fps: float = DEFAULT_FPS,
                camera_model: str = "SIMPLE_RADIAL", min_registered: int | None = None, overwrite: bool = False,
                seed: int = 0, progress: StageProgress | None = None) -> CaptureReport:
    """Structure-from-motion on `inputs` (a folder of photos, photo files, or one video),
    written as a capture folder at `out` (the module docstring)."""
    paths = [Path(inputs)] if isinstance(inputs, (str, Path)) else [Path(p) for p in inputs]
    if not paths:
        raise InputError("inputs", "give a folder of photos, photo files or a video")
    if matcher not in MATCHERS:
        raise InputError("matcher", f"must be one of {', '.join(MATCHERS)}, got {matcher!r}")
    if camera_model not in CAMERA_MODELS:
        raise InputError("camera_model", f"must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    check_int(max_size, "max_size", minimum=64)
    check_int(max_images, "max_images", minimum=2)
    check_float(fps, "fps", minimum=0, open_min=True)
    if min_registered is not None:
        check_int(min_registered, "min_registered", minimum=2, maximum=max_images)
    out = Path(out)
    _check_out(out, paths, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    with _building(out) as work:
        report = _reconstruct(paths, work, matcher=matcher, max_size=max_size, max_images=max_images, fps=fps,
                              camera_model=camera_model, min_registered=min_registered, seed=seed,
                              progress=_stage_progress(progress))
        report.out = str(out)
        _publish(work, out, report)
    return report


@contextmanager
def _building(out: Path) -> Iterator[Path]:
    """A folder beside `out` to build a capture in, removed when the build fails (nothing is
    written at `out` until `_publish`)."""
    work = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.partial-"))
    os.chmod(work, 0o755)
    try:
        yield work
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


def _publish(work: Path, out: Path, report: CaptureReport) -> None:
    """The capture built in `work` checked to load, its report written, and put at `out`."""
    with _timed(report.seconds, "check"):
        _check_loads(work, len(report.registered))
    write_json_atomic(work / REPORT, asdict(report))
    _replace(out, work)


def _stage_progress(progress: StageProgress | None) -> Callable[[str], Progress]:
    """Each stage's progress callback: progress(stage, fraction), or nothing."""
    if progress is None:
        return lambda stage: (lambda fraction: None)
    return lambda stage: (lambda fraction: progress(stage, fraction))


def read_report(capture: Path) -> CaptureReport:
    """The CaptureReport `run_capture` (or `add_photos`) wrote in a capture folder."""
    path = Path(capture) / REPORT
    if not path.is_file():
        raise InputError("capture", f"{capture} holds no {REPORT}: photos are added to a folder phd capture wrote")
    try:
        return CaptureReport(**json.loads(path.read_text()))
    except (ValueError, TypeError) as exc:
        raise InputError("capture", f"{path} cannot be read: {exc}") from None


def add_photos(capture: str | Path, inputs: str | Path | Sequence[str | Path], *, max_size: int = DEFAULT_MAX_SIZE,
               max_images: int = DEFAULT_MAX_IMAGES, seed: int = 0,
               progress: StageProgress | None = None) -> CaptureReport:
    """New photos (a folder of them, or photo files) registered into the capture at `capture`
    (the module docstring); the capture's report after it, whose `added` and `not_registered`
    name this call's photos."""
    from . import sfm

    capture = Path(capture)
    before = read_report(capture)
    paths = [Path(inputs)] if isinstance(inputs, (str, Path)) else [Path(p) for p in inputs]
    check_int(max_size, "max_size", minimum=64)
    check_int(max_images, "max_images", minimum=2)
    photos, skipped = list_photos(paths)
    if not photos:
        raise InputError("photos", f"no photos to add ({', '.join(PHOTO_SUFFIXES)})")
    known = set(before.origins)
    total = len(known) + len(photos)
    if total > max_images:
        raise InputError("photos", f"the capture would hold {total} photos, more than max_images ({max_images})")
    names = input_names(photos, False)
    taken = [name for name in names if name in known]
    if taken:
        raise InputError("photos", f"the capture holds a photo named {taken[0]!r} already: rename the new one")
    stage = _stage_progress(progress)
    seconds: dict[str, float] = {}
    with _building(capture) as work:
        with _timed(seconds, "input"):
            for folder in ("input", "distorted"):
                shutil.copytree(capture / folder, work / folder)
            for i, (photo, name) in enumerate(zip(photos, names)):
                write_photo(photo, work / "input" / name, max_size)
                stage("input")((i + 1) / len(photos))
        database, existing = work / "distorted" / "database.db", work / "distorted" / "sparse" / "0"
        sfm.seed(seed)
        with sfm.quiet_colmap():
            with _timed(seconds, "features"):
                sfm.add_features(database, work / "input", names, camera_model=before.camera_model,
                                 progress=stage("features"))
            with _timed(seconds, "matching"):
                old = sorted(known)
                pairs = [(new, other) for i, new in enumerate(names) for other in old + names[i + 1:]]
                sfm.match_pairs(database, pairs, seed=seed, progress=stage("matching"))
            with _timed(seconds, "mapping"):
                model = sfm.map_images(database, work / "input", work / "distorted" / "extended" / "0", seed=seed,
                                       progress=stage("mapping"), existing=existing)
            registered = sorted(image.name for image in model.images.values() if image.has_pose)
            added = [name for name in names if name in set(registered)]
            missing = sorted(set(before.registered) - set(registered))
            if missing:          # the fixed frames register by construction: anything else is a fault of ours
                raise RuntimeError(f"extending the reconstruction lost {len(missing)} of its photos: {_some(missing)}")
            if not added:
                raise InputError("photos", f"none of the {len(names)} new photos registered ({_some(names)}): each "
                                 "shares too few matched features with the capture (a photo of something else, or "
                                 "too little overlap with the photos taken); nothing was changed")
            shutil.rmtree(existing.parent)
            (work / "distorted" / "extended").rename(existing.parent)
            with _timed(seconds, "undistortion"):
                sfm.undistort(existing, work / "input", work, registered, progress=stage("undistortion"))
        not_registered = [name for name in names if name not in set(added)]
        notes = [f"skipped {len(skipped)} files that are not photos: {_some(skipped)}"] if skipped else []
        if not_registered:
            notes.append(f"{len(not_registered)} of the {len(names)} photos added did not register: "
                         f"{_some(not_registered)}")
        report = replace(before, inputs=before.inputs + len(names), registered=registered,
                         pairs=before.pairs + len(pairs), cameras=model.num_cameras(), points=model.num_points3D(),
                         reprojection_error=round(model.compute_mean_reprojection_error(), 3),
                         origins={**before.origins, **{name: str(photo) for photo, name in zip(photos, names)}},
                         notes=notes, seconds=seconds, pycolmap=sfm.VERSION, added=added,
                         not_registered=not_registered)
        _publish(work, capture, report)
    return report


@dataclass
class _Inputs:
    """What the input stage wrote into input/ and decided from it."""

    source: str                 # "photos" or "video"
    names: list[str]            # in input/, in capture order
    origins: dict[str, str]     # name -> the photo, or the video and time, it came from
    single_camera: bool         # one size, so one camera
    matcher: str
    matcher_reason: str
    threshold: int              # images that must register
    notes: list[str]


def _reconstruct(paths: list[Path], work: Path, *, matcher: str, max_size: int, max_images: int, fps: float,
                 camera_model: str, min_registered: int | None, seed: int,
                 progress: Callable[[str], Progress]) -> CaptureReport:
    """Every stage, in `work`; the report of what they did (its `out` still unset)."""
    from . import sfm  # pycolmap loads for a capture, not with every `phd` command

    seconds: dict[str, float] = {}
    source, distorted = work / "input", work / "distorted"
    with _timed(seconds, "input"):
        inputs = _take_inputs(paths, source, matcher=matcher, max_size=max_size, max_images=max_images, fps=fps,
                              min_registered=min_registered, progress=progress("input"))
    database, model_dir = distorted / "database.db", distorted / "sparse" / "0"
    distorted.mkdir()
    sfm.seed(seed)
    with sfm.quiet_colmap():
        with _timed(seconds, "features"):
            sfm.extract_features(database, source, inputs.names, camera_model=camera_model,
                                 single_camera=inputs.single_camera, progress=progress("features"))
        with _timed(seconds, "matching"):
            pairs = sfm.match_features(database, sequential=inputs.matcher == "sequential", seed=seed,
                                       progress=progress("matching"))
        with _timed(seconds, "mapping"):
            model = sfm.map_images(database, source, model_dir, seed=seed, progress=progress("mapping"))
        registered = sorted(image.name for image in model.images.values() if image.has_pose)
        if len(registered) < inputs.threshold:
            raise InputError("registered", f"structure-from-motion registered {len(registered)} of "
                             f"{len(inputs.names)} images, and at least {inputs.threshold} must "
                             f"({_threshold_reason(min_registered)}); nothing was written. More overlap between "
                             "neighbouring photos, more texture, or larger photos (max_size) help")
        with _timed(seconds, "undistortion"):
            sfm.undistort(model_dir, source, work, registered, progress=progress("undistortion"))
    missing = [name for name in inputs.names if name not in set(registered)]
    if missing:
        inputs.notes.append(f"{len(missing)} of {len(inputs.names)} images did not register: {_some(missing)}")
    return CaptureReport(out="", source=inputs.source, inputs=len(inputs.names), registered=registered,
                         matcher=inputs.matcher, matcher_reason=inputs.matcher_reason, pairs=pairs,
                         camera_model=camera_model, cameras=model.num_cameras(), points=model.num_points3D(),
                         reprojection_error=round(model.compute_mean_reprojection_error(), 3),
                         origins=inputs.origins, notes=inputs.notes, seconds=seconds, pycolmap=sfm.VERSION)


def _take_inputs(paths: list[Path], source: Path, *, matcher: str, max_size: int, max_images: int, fps: float,
                 min_registered: int | None, progress: Progress) -> _Inputs:
    """The photos, or the video's frames, written into `source`; every bound and the matcher
    rule applied before a photo is written."""
    source.mkdir()
    if len(paths) == 1 and is_video(paths[0]):
        from .video import sample_video  # PyAV, as pycolmap: loaded when needed

        sampled = sample_video(paths[0], source, fps=fps, max_frames=max_images, max_size=max_size,
                               progress=progress)
        names = sampled.names
        threshold = _check_count(len(names), min_registered)
        chosen, reason = choose_matcher(matcher, video=True, ordered=True, count=len(names))
        origins = {name: f"{paths[0]} at {i * sampled.step:.2f} s" for i, name in enumerate(names)}
        return _Inputs("video", names, origins, True, chosen, reason, threshold,
                       [f"video of {sampled.seconds:.1f} s at {sampled.size[0]}x{sampled.size[1]}: a frame every "
                        f"{sampled.step:.2f} s, {len(names)} frames"])
    photos, skipped = list_photos(paths)
    if not photos:
        held = f"; it holds {_some(skipped)}" if skipped else ""
        raise InputError("inputs", f"{paths[0]} holds no photos ({', '.join(PHOTO_SUFFIXES)}; a video is one of "
                         f"{', '.join(VIDEO_SUFFIXES)}){held}")
    if len(photos) > max_images:
        raise InputError("inputs", f"{len(photos)} photos, more than max_images ({max_images}): choose fewer, "
                         "or raise the bound (structure-from-motion's time grows faster than the photo count)")
    threshold = _check_count(len(photos), min_registered)
    photos, ordered = capture_order(photos)
    chosen, reason = choose_matcher(matcher, video=False, ordered=ordered, count=len(photos))
    names = input_names(photos, ordered)
    notes = [f"skipped {len(skipped)} files that are not photos: {_some(skipped)}"] if skipped else []
    sizes, downscaled = set(), 0
    for i, (photo, name) in enumerate(zip(photos, names)):
        size, scaled = write_photo(photo, source / name, max_size)
        sizes.add(size)
        downscaled += scaled
        progress((i + 1) / len(photos))
    renamed = [f"{photo.name} -> {name}" for photo, name in zip(photos, names) if photo.name != name]
    if downscaled:
        notes.append(f"downscaled {downscaled} photos to {max_size} px on the longer side (max_size)")
    if renamed:
        notes.append(f"renamed {len(renamed)} photos for COLMAP (numbers zero-padded to sort in capture order, "
                     f"spaces made '_'): {_some(renamed, 3)}")
    if len(sizes) > 1:
        notes.append(f"the photos have {len(sizes)} sizes: one camera per photo")
    return _Inputs("photos", names, {name: str(photo) for photo, name in zip(photos, names)}, len(sizes) == 1,
                   chosen, reason, threshold, notes)


def _check_count(count: int, min_registered: int | None) -> int:
    """The registration threshold for `count` images; fewer images than it are refused now."""
    threshold = min_registered or registration_threshold(count)
    if count < threshold:
        raise InputError("inputs", f"{count} images, and at least {threshold} must register "
                         f"({_threshold_reason(min_registered)})")
    return threshold


@contextmanager
def _timed(seconds: dict[str, float], stage: str) -> Iterator[None]:
    """seconds[stage] = the wall seconds the block took."""
    started = time.perf_counter()
    yield
    seconds[stage] = round(time.perf_counter() - started, 2)


def choose_matcher(requested: str, *, video: bool, ordered: bool, count: int) -> tuple[str, str]:
    """(matcher, why) by the module docstring's rule; `requested` other than "auto" wins."""
    if requested != "auto":
        return requested, "as asked"
    if video:
        return "sequential", "a video's frames are in time order: each is matched with its neighbours"
    if ordered:
        return "sequential", "the photos are numbered: their numbers give the capture order"
    if count <= EXHAUSTIVE_MAX:
        return "exhaustive", f"{count} photos in no known order (at most {EXHAUSTIVE_MAX}): every pair is matched"
    raise InputError("matcher", f"{count} photos in no known order (their names differ in more than numbers): "
                     f"matching every pair of more than {EXHAUSTIVE_MAX} photos takes hours on a CPU. Name them in "
                     "capture order (IMG_0001.jpg, ...) for sequential matching, or ask for exhaustive matching")


def _threshold_reason(min_registered: int | None) -> str:
    if min_registered is not None:
        return "min_registered"
    return (f"the larger of {MIN_IMAGES}, so that the test split (every 8th image) keeps one view and training "
            f"seven, and half the inputs, so that the capture shows what the photos show")


def _some(names: Sequence[str], shown: int = 5) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def _check_out(out: Path, inputs: list[Path], overwrite: bool) -> None:
    """Refuse an output that is a file, an input inside it, and a folder that holds files,
    unless `overwrite` and it is an earlier capture (it holds REPORT)."""
    if out.exists() and not out.is_dir():
        raise InputError("out", f"{out} is a file: give a folder for the capture")
    for path in inputs:
        if path.resolve().is_relative_to(out.resolve()):
            raise InputError("out", f"the input {path} lies inside {out}: write the capture elsewhere")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError("out", f"{out} exists and is not empty: choose a new folder, or overwrite an earlier "
                             "capture")
        if not (out / REPORT).is_file():
            raise InputError("out", f"{out} holds files that phd capture did not write (no {REPORT}): only an earlier "
                             "capture is overwritten")


def _replace(out: Path, work: Path) -> None:
    """Put the finished folder `work` at `out` (an earlier capture there is removed after)."""
    if out.is_dir() and any(out.iterdir()):
        old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
        out.rename(old / out.name)
        work.rename(out)
        shutil.rmtree(old)
    else:
        work.rename(out)         # over an empty folder, in one step


def _check_loads(folder: Path, registered: int) -> None:
    """Load the capture back with the project's reader, every image read at its camera's size
    (and kept at 64 px, so memory stays small)."""
    try:
        full = load_dataset(folder, "all", with_images=False).cameras
        dataset = load_dataset(folder, "all", downscale=max(full[0].width, full[0].height) / 64)
    except InputError as exc:
        raise InputError("out", f"the capture does not load: {exc}; nothing was written") from None
    assert len(dataset.cameras) == registered, f"the capture loads {len(dataset.cameras)} images of {registered}"
