"""The capture loop's work: photos in, structure-from-motion, a model trained, the next views out,
round after round (`/v1/captures`, issue 49).

Each `*_job` function checks a request and returns the `Work` a worker thread runs, as
`service.work` does for models:

    reconstruct_job   the first photos (or a video) -> the capture folder (`phd_core.process.run_capture`)
    add_photos_job    new photos registered into it, the others' poses fixed (`phd_core.process.add_photos`)
    train_job         a model trained on the capture's photos less its test photos, from the latest
                      model of the family when `warm_start` (the trainer's `init`), stored as a model
                      linked to the capture, calibrated (Algorithm 1), and measured on the test photos
                      (PSNR, sigma-max-bar)
    next_job          the latest model's rank job (`service.work.rank_job`) over candidates around the
                      capture, told the capture's own path as targets when asked; the poses come back in
                      the capture's frame, and the round keeps them

Structure-from-motion runs in the worker (pycolmap on the service's cores); training runs on the
configured executor (`phd_core.executors`): in the worker for `local`, with progress and
cancellation at every step; on a Ray cluster as one task that gets the capture's images and
cameras as bytes (no shared file system needed) and returns the model file.
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import tempfile
import time
import zipfile
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

from phd_core import uq
from phd_core.data import load_dataset
from phd_core.errors import InputError
from phd_core.eval import psnr
from phd_core.executors import LOCAL, Executor
from phd_core.executors.local import LocalExecutor
from phd_core.io import fsync_path
from phd_core.process import capture as sfm
from phd_core.process.capture import STAGES, CaptureReport
from phd_core.renderers import FAMILIES, Renderer
from phd_core.scene import Camera
from phd_core.train.config import StepCallback
from phd_core.uq import Progress

from .budget import MemoryLedger, OverBudget
from .captures import CaptureRecord, CaptureStore
from .errors import ServiceError, from_exception, insufficient_storage, invalid, not_found
from .jobs import JobProgress, Work
from .photos import PhotoUpload
from .plans import Bounded, Renders, span
from .requests import render_size, stored_cameras
from .schemas import (
    Calibration,
    CandidateSpec,
    CaptureInfo,
    CaptureRound,
    NextRequest,
    RankRequest,
    RankResult,
    RenderSize,
    TrainRequest,
    TrainResult,
    TrainSummary,
)
from .settings import Settings
from .store import ModelRecord, ModelStore, utc_now, writing
from .upload import Upload
from .work import rank_job

# What a job reserves of the memory budget (service.budget), estimated:
SFM_FIXED_BYTES = 512 << 20       # COLMAP's database, matcher and mapper for a few hundred photos
SFM_PIXEL_BYTES = 48              # per pixel of the largest photo, per core: SIFT's scale space (float32 octaves)
TRAIN_SPLAT_BYTES = 2048          # per splat of the budget: parameters, gradients and Adam's two moments, twice
TRAIN_PIXEL_BYTES = 2048          # per pixel of the largest view: the rasteriser's lists and their gradients
IMAGE_PIXEL_BYTES = 16            # per pixel of every view: the training images (float32 RGBA)
# What structure-from-motion writes, checked against the disk's room before it starts: the photos
# as COLMAP sees them and undistorted (each at most the size sent, downscaled ones smaller), the
# database's features, and the reconstruction.
SFM_DISK_PER_BYTE = 3
SFM_DISK_FIXED = 32 << 20
DEFAULT_CANDIDATES = CandidateSpec(generator="orbit", count=64)   # next views' candidates when none are given


def capture_info(record: CaptureRecord, job: str | None = None) -> CaptureInfo:
    report = record.report or {}
    return CaptureInfo(id=record.id, name=record.name, state=record.state,  # type: ignore[arg-type]
                       created_at=record.created_at, updated_at=record.updated_at,
                       num_photos=len(report.get("registered", [])), test_photos=record.test_photos,
                       model_id=record.model_id, rounds=[CaptureRound(**r) for r in record.rounds],
                       report={k: v for k, v in report.items() if k not in ("registered", "origins")} or None,
                       error=record.error, job=job)


def _stages(progress: Progress) -> Callable[[str, float], None]:
    """A structure-from-motion stage's progress as the job's: each stage an equal share."""
    return lambda stage, fraction: progress((STAGES.index(stage) + fraction) / len(STAGES))


def sfm_bytes(settings: Settings) -> int:
    """What structure-from-motion may hold: the fixed part and the scale space of the largest
    photo (at most `capture_max_size` on its longer side) on every core."""
    side = settings.capture_max_size
    return SFM_FIXED_BYTES + SFM_PIXEL_BYTES * side * side * (os.cpu_count() or 1)


def check_room(store: ModelStore, upload: PhotoUpload, settings: Settings) -> None:
    """507 naming `photos` when what structure-from-motion writes would not fit on the data
    directory's disk outside the space kept free (checked before it starts)."""
    need = SFM_DISK_PER_BYTE * upload.size + SFM_DISK_FIXED
    room = store.free_bytes() - settings.keep_free_bytes
    if need > room:
        raise insufficient_storage(f"the reconstruction of {upload.count} photos (about {need} bytes)", "photos",
                                   f"the service's disk has {max(room, 0)} bytes free outside the space kept free")


def _frames(folder: Path, names: list[str]) -> list[dict[str, Any]]:
    """The cameras of the photos `names` of a capture as transforms frames, by name."""
    data = load_dataset(folder, "all", with_images=False)
    assert data.names is not None             # a COLMAP capture names its images
    wanted = set(names)
    return [camera.to_frame() for camera, name in zip(data.cameras, data.names) if name in wanted]


def _round(number: int, report: CaptureReport, sent: list[str], folder: Path) -> dict[str, Any]:
    registered = sorted(name for name in sent if name in set(report.registered))     # the order of `captured`
    return CaptureRound(round=number, photos=sent, registered=registered,
                        not_registered=[name for name in sent if name not in set(report.registered)],
                        sfm_seconds=round(sum(report.seconds.values()), 2),
                        captured=_frames(folder, registered)).model_dump()


def _test_names(report: CaptureReport, asked: list[str], sent: list[str]) -> list[str]:
    """The capture's names of the photos the request held out (asked by the names it sent them under)."""
    by_origin = {Path(origin).name: name for name, origin in report.origins.items()}
    named = [by_origin.get(name, name) for name in asked]
    return [name for name in named if name in set(sent)]


def users_terms(exc: BaseException, upload: PhotoUpload) -> BaseException:
    """A library error that names the server's folder of the photos in the words of the request
    (the photos sent); any other exception as it is."""
    if isinstance(exc, InputError):
        reason = exc.reason
        for path, shown in ((upload.folder, "the photos sent"), (upload.video, "the video sent")):
            if path is not None:
                reason = reason.replace(str(path), shown)
        if reason != exc.reason:
            return InputError(exc.field, reason)
    return exc


def check_test(upload: PhotoUpload) -> list[str]:
    """The `test` names, each one of the photos sent (422 naming `test` otherwise)."""
    asked = upload.test_photos()
    sent = {p.name for p in upload.folder.iterdir()} if upload.video is None else set()
    unknown = [name for name in asked if name not in sent]
    if unknown:
        raise invalid("test", f"{unknown[0]!r} is not one of the photos sent" + (
            " (a video's frames cannot be held out)" if upload.video is not None else ""))
    return asked


# ----------------------------------------------------------------------------- structure-from-motion

def reconstruct_job(record: CaptureRecord, upload: PhotoUpload, captures: CaptureStore, settings: Settings,
                    ledger: MemoryLedger, asked_test: list[str]) -> Work:
    """The first photos -> the capture folder; the capture `ready` with round 0, or `failed`."""
    def work(progress: Progress) -> tuple[CaptureInfo, dict[str, bytes]]:
        try:
            check_room(captures.store, upload, settings)
            with ledger.reserve(sfm_bytes(settings)), writing("the capture's reconstruction", "photos"):
                report = sfm.run_capture(upload.inputs(), captures.folder(record.id),
                                         max_size=settings.capture_max_size, max_images=settings.max_capture_photos,
                                         progress=_stages(progress), **record.settings)
        except BaseException as raised:
            exc = users_terms(raised, upload)
            known = from_exception(exc)
            detail = (known or ServiceError(500, "internal_error", f"structure-from-motion failed "
                                            f"({type(exc).__name__}); see the server log")).detail()
            captures.update(record.id, state="failed", error=detail.model_dump())
            if exc is raised:
                raise
            raise exc from None
        finally:
            shutil.rmtree(upload.folder, ignore_errors=True)
            if upload.video is not None:
                upload.video.unlink(missing_ok=True)
        sent = list(report.origins)
        done = captures.update(record.id, state="ready", report=asdict(report),
                               test_photos=_test_names(report, asked_test, sent),
                               rounds=[_round(0, report, sent, captures.folder(record.id))])
        if done is None:
            raise not_found("capture", record.id)
        return capture_info(done), {}
    return work


def add_photos_job(record: CaptureRecord, upload: PhotoUpload, captures: CaptureStore, settings: Settings,
                   ledger: MemoryLedger, asked_test: list[str]) -> Work:
    """New photos registered into the capture; a new round. The capture is `ready` again after,
    whatever happened (add_photos leaves the folder as it was on failure)."""
    folder = captures.folder(record.id)

    def work(progress: Progress) -> tuple[CaptureInfo, dict[str, bytes]]:
        try:
            check_room(captures.store, upload, settings)
            with ledger.reserve(sfm_bytes(settings)), writing("the photos' registration", "photos"):
                report = sfm.add_photos(folder, upload.folder, max_size=settings.capture_max_size,
                                    max_images=settings.max_capture_photos, progress=_stages(progress))
        except BaseException as raised:
            captures.update(record.id, state="ready")
            exc = users_terms(raised, upload)
            if exc is raised:
                raise
            raise exc from None
        finally:
            shutil.rmtree(upload.folder, ignore_errors=True)
        sent = sorted(report.added + report.not_registered)
        current = captures.get(record.id)
        if current is None:
            raise not_found("capture", record.id)
        done = captures.update(record.id, state="ready", report=asdict(report),
                               test_photos=current.test_photos + _test_names(report, asked_test, sent),
                               rounds=current.rounds + [_round(len(current.rounds), report, sent, folder)])
        assert done is not None
        return capture_info(done), {}
    return work


# ----------------------------------------------------------------------------- training

@dataclass(frozen=True)
class TrainSpec:
    """One training run, as the executor ships it: what `Family.train` is called with."""

    family: str
    views: list[int]                # indices of the capture's photos (split "all") trained on
    downscale: float
    iterations: int | None
    seed: int
    options: dict[str, Any]


def train_in(folder: Path, spec: TrainSpec, init: Path | None, out: Path,
             on_step: StepCallback | None) -> None:
    """Train `spec` on the capture in `folder`, writing the model to `out` (its sidecar beside)."""
    FAMILIES[spec.family].train(folder, split="all", views=spec.views, downscale=spec.downscale,
                                iterations=spec.iterations, seed=spec.seed, out=out, progress=False,
                                init=init, on_step=on_step, **spec.options)


def train_shipped(chunk: list[TrainSpec], files: bytes, init: bytes | None) -> tuple[bytes, bytes | None]:
    """Executor task: the capture's images and cameras (a zip's bytes) unpacked into a temporary
    folder, trained there; the model file's bytes back, and its sidecar's (training cameras,
    background) when the family writes one."""
    with tempfile.TemporaryDirectory(prefix="phd-train-") as tmp:
        root = Path(tmp)
        with zipfile.ZipFile(io.BytesIO(files)) as zipped:
            zipped.extractall(root / "capture")
        start = None
        if init is not None:
            start = root / f"init{FAMILIES[chunk[0].family].extension}"
            start.write_bytes(init)
        out = root / f"model{FAMILIES[chunk[0].family].extension}"
        train_in(root / "capture", chunk[0], start, out, None)
        sidecar = out.with_suffix(".json")
        return out.read_bytes(), sidecar.read_bytes() if sidecar.is_file() else None


def capture_files(folder: Path) -> bytes:
    """What training reads of a capture (images/ and sparse/0/) as a zip's bytes (stored, not deflated: JPEGs)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as zipped:
        for sub in ("images", "sparse"):
            for path in sorted((folder / sub).rglob("*")):
                if path.is_file():
                    zipped.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


def train_bytes(cameras: list[Camera], splats_per_pixel: float = 4.0) -> int:
    """What a splat training run holds at most: its splat budget (splats_per_pixel x the largest
    view's pixels, phd_core.train.splats) with their optimiser state, the rasteriser's work on
    the largest view and every training image."""
    largest = max(c.width * c.height for c in cameras)
    return int(TRAIN_SPLAT_BYTES * splats_per_pixel * largest + TRAIN_PIXEL_BYTES * largest
               + IMAGE_PIXEL_BYTES * sum(c.width * c.height for c in cameras))


def previous_model(record: CaptureRecord, family: str, store: ModelStore) -> ModelRecord | None:
    """The capture's latest model of `family` that is still stored (the warm start's init)."""
    for entry in reversed(record.rounds):
        train = entry.get("train") or {}
        if train.get("family") == family:
            found = store.get(train["model_id"])
            if found is not None and store.path(found).is_file():
                return found
    return None


def train_job(record: CaptureRecord, body: TrainRequest, captures: CaptureStore, store: ModelStore,
              settings: Settings, ledger: MemoryLedger, ingest: Callable[[Upload, str], ModelRecord],
              executor: Executor = LOCAL) -> tuple[Work, float]:
    """A model trained on the capture (module docstring). `ingest` stores a trained file as the
    upload path stores one (service.state.ServiceState.ingest)."""
    family = FAMILIES.get(body.model)
    if family is None or family.trainer is None:
        raise invalid("model", f"must be one of {', '.join(f.name for f in FAMILIES.values() if f.trainer)}, got "
                      f"{body.model!r}")
    if record.state != "ready":
        raise ServiceError(409, "capture_busy", f"capture '{record.id}' is {record.state}: train it once it is ready",
                           "capture_id")
    folder = captures.folder(record.id)
    data = load_dataset(folder, "all", downscale=body.downscale, with_images=False)
    assert data.names is not None
    test = set(record.test_photos)
    views = [i for i, name in enumerate(data.names) if name not in test]
    held = [i for i, name in enumerate(data.names) if name in test]
    if len(views) < 2:
        raise invalid("test", f"{len(views)} photos are left to train on once the test photos are held out")
    options = dict(body.options)
    if family.train_options is None and options:
        raise invalid("options", f"{family.name} takes no training options of its own (`phd train --help`), got "
                      f"{', '.join(sorted(options))[:200]}")
    if family.train_options is not None:
        try:
            family.train_options(**options)
        except (TypeError, InputError) as exc:
            raise invalid("options", str(exc)) from None
    cameras = [data.cameras[i] for i in views]
    try:
        size = render_size([data.cameras[i] for i in held] + cameras, RenderSize(), settings, field="downscale")
    except ServiceError as exc:
        raise invalid("downscale", exc.message) from None
    reserve = train_bytes(cameras)
    if reserve > settings.memory_budget_bytes:
        raise OverBudget("downscale", reserve, settings.memory_budget_bytes, "a larger downscale")
    init = previous_model(record, body.model, store) if body.warm_start else None
    if init is not None and isinstance(init.describe.get("background"), list):
        options.setdefault("background", init.describe["background"])   # every warm round over one colour
    spec = TrainSpec(body.model, views, body.downscale, body.iterations, body.seed, options)
    samples = body.samples or uq.DEFAULT_CALIBRATION_SAMPLES
    estimate = float(sum(c.width * c.height for c in size) * samples * 10)

    def work(progress: JobProgress) -> tuple[TrainResult, dict[str, bytes]]:
        out = store.new_temp_path().with_suffix(family.extension)
        try:
            started = time.perf_counter()
            with ledger.reserve(reserve):
                if isinstance(executor, LocalExecutor):
                    train_in(folder, spec, None if init is None else store.path(init), out,
                             lambda at: progress(0.8 * at.step / at.total, (at.seconds_left, at.seconds_left_max)))
                else:
                    shipped = executor.share(capture_files(folder))
                    init_bytes = None if init is None else store.path(init).read_bytes()
                    trained, sidecar = executor.map(partial(train_shipped, init=init_bytes), [[spec]], shipped)[0]
                    out.write_bytes(trained)
                    if sidecar is not None:
                        out.with_suffix(".json").write_bytes(sidecar)
            seconds = time.perf_counter() - started
            model = ingest(trained_upload(out, record, len(record.rounds) - 1), body.model)
        finally:
            out.unlink(missing_ok=True)
            out.with_suffix(".json").unlink(missing_ok=True)
        summary = measure(model, store, folder, held, body, samples, settings, ledger, executor,
                          lambda fraction: progress(0.8 + 0.2 * fraction))
        summary = summary.model_copy(update={"family": body.model, "iterations": body.iterations,
                                             "train_views": len(views), "seconds": round(seconds, 2),
                                             "warm_from": None if init is None else init.id})
        current = captures.get(record.id)
        if current is None:
            raise not_found("capture", record.id)
        rounds = current.rounds[:-1] + [{**current.rounds[-1], "train": summary.model_dump()}]
        captures.update(record.id, rounds=rounds)
        return TrainResult(capture_id=record.id, round=len(rounds) - 1, summary=summary), {}

    return work, estimate


def trained_upload(path: Path, record: CaptureRecord, round_: int) -> Upload:
    """A trained model file as an upload (its sidecar gives cameras, background and capture format)."""
    fsync_path(path)
    sidecar = path.with_suffix(".json")
    data = path.read_bytes()
    return Upload(path=path, filename=path.name, name=f"{record.name} round {round_}", size=len(data),
                  head=data[:4096], sha256=hashlib.sha256(data).hexdigest(), has_file=True,
                  cameras=sidecar.read_bytes() if sidecar.is_file() else None,
                  facts={"capture_id": record.id, "round": round_})


def measure(model: ModelRecord, store: ModelStore, folder: Path, held: list[int], body: TrainRequest,
            samples: int, settings: Settings, ledger: MemoryLedger, executor: Executor,
            progress: Progress) -> TrainSummary:
    """The stored model calibrated on its training cameras (Algorithm 1; stored with it), and
    measured on the held-out photos: the PSNR of its renders, and sigma-max-bar at r_drop. Run
    within the memory plan of those renders (service.plans), as a calibrate job is."""
    training = render_size(stored_cameras(model), RenderSize(), settings, field="downscale")
    test = load_dataset(folder, "all", views=held, downscale=body.downscale) if held else None
    tested = [] if test is None else test.cameras
    renders = Renders([(model, "downscale", training + tested)], samples * uq.LOOKAHEAD,
                      kept_bytes=4 * 3 * sum(c.width * c.height for c in training), kept_field="downscale",
                      keeps_views=True)
    renders.plan(settings)

    def work(renderers: dict[str, Renderer], progress: Progress) -> tuple[TrainSummary, dict[str, bytes]]:
        renderer = renderers[model.id]
        summary = TrainSummary(model_id=model.id, family=model.kind, iterations=body.iterations, train_views=0,
                               seconds=0.0, num_units=model.num_units, test_views=len(held))
        try:
            found = uq.calibrate(renderer, training, samples=samples, seed=body.seed, executor=executor,
                                 progress=span(progress, 0.0, 0.5))
        except InputError as exc:              # r_drop = 0: a model not properly trained (the round says so)
            summary.calibration_error = exc.reason
        else:
            summary.r_drop = found.r_drop
            store.set_calibration(model.id, Calibration(**found.to_dict(), num_cameras=len(training),
                                                        created_at=utc_now()).model_dump())
        if test is None:
            return summary, {}
        assert test.images is not None
        scores = [psnr(renderer.render(camera)[0].clamp(0, 1), image) for camera, image in zip(tested, test.images)]
        summary.test_psnr = round(sum(scores) / len(scores), 3)
        if summary.r_drop is not None:
            views = uq.uncertainty(renderer, tested, ratio=summary.r_drop, samples=samples, seed=body.seed,
                                   executor=executor, progress=span(progress, 0.5, 1.0))
            summary.sigma_max_bar = uq.sigma_max_bar(views)
        return summary, {}

    return Bounded(renders, settings, ledger, work)(progress)[0]


# ----------------------------------------------------------------------------- next views

def next_job(record: CaptureRecord, body: NextRequest, captures: CaptureStore, store: ModelStore,
             settings: Settings, job_url: Callable[[str], str], ledger: MemoryLedger,
             executor: Executor = LOCAL) -> tuple[Work, float]:
    """The latest model's rank job (service.work.rank_job); the round keeps the poses it chose."""
    model = store.get(record.model_id) if record.model_id else None
    if model is None:
        raise ServiceError(409, "not_trained", f"capture '{record.id}' has no model yet: train it first "
                           f"(POST /v1/captures/{record.id}/train)", "capture_id")
    fields = body.model_dump(by_alias=True, exclude_unset=True, exclude={"targets", "top_k"})
    if body.cameras is None and body.candidates is None:
        fields["candidates"] = DEFAULT_CANDIDATES.model_dump()
    fields["top_k"] = body.top_k
    if body.targets == "capture":
        fields["targets"] = [c.to_frame() for c in stored_cameras(model)]
    elif body.targets is not None:
        fields["targets"] = body.targets
    work, estimate = rank_job(model, RankRequest(**fields), settings, job_url, ledger, executor, store)

    def ranked(progress: JobProgress) -> tuple[RankResult, dict[str, bytes]]:
        result, artifacts = work(progress)
        current = captures.get(record.id)
        if current is not None and current.rounds:
            poses = [view.camera for view in result.views if view.camera is not None]
            captures.update(record.id, rounds=current.rounds[:-1] + [{**current.rounds[-1], "next": poses}])
        return result, artifacts

    return ranked, estimate
