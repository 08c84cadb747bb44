"""What the routes ask the worker pool to do: request checks, then calls into `phd_core`.

Each `*_job` function validates a request on the event loop (cheap: parsing cameras,
checking caps, finding the dropout ratio) and returns the `Work` that a worker thread runs
later (expensive: loading the model, rendering). The work calls the engine
(`phd_core.uq`) exactly as a Python user would, so the service's numbers are the
library's numbers.
"""

from __future__ import annotations

import base64
import io
import tempfile
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from phd_core import uq
from phd_core.data import POSES, candidate_name, export_cameras, source_pose
from phd_core.data.inria import cameras_from_entries, is_inria_cameras
from phd_core.errors import InputError, check_int
from phd_core.executors import LOCAL, Executor
from phd_core.io import colorize, png_bytes
from phd_core.renderers import (
    DEFAULT_SIGNAL,
    FAMILIES,
    Renderer,
    RenderMemory,
    accepts_background,
    load_model_bytes,
    memory_probe_bytes,
    set_background,
    signal_channels,
)
from phd_core.renderers.visibility import (
    COVERAGE_CAPTURE_BYTES,
    PASS_UNIT_BYTES,
    SEEN_LOADED_BYTES,
    seen_bytes,
    visibility_bytes,
)
from phd_core.scene import Camera, cameras_from_json, capture_up
from phd_core.uq import Progress
from phd_core.uq.candidates import candidate_cameras, check_option_names
from phd_core.uq.rank import check_target_strategy
from phd_core.uq.sampling import VIEW_CACHE_BYTES
from phd_core.uq.select import level_views
from phd_core.uq.strategies import CHEAPER_STRATEGY, get_strategy
from phd_core.uq.strategies.captured import CapturedStore, camera_key
from phd_core.uq.strategies.targets import density_bytes

from .budget import (
    DEFAULT_MASK_PIXEL_BYTES,
    PNG_PIXEL_BYTES,
    MemoryLedger,
    MemoryPlan,
    ModelSize,
    OverBudget,
    model_bytes,
    plan_work,
)
from .errors import ServiceError, busy, invalid, not_found
from .jobs import Work
from .schemas import (
    CalibrateRequest,
    Calibration,
    PosesRequest,
    RankedCandidate,
    RankRequest,
    RankResult,
    RenderSize,
    SelectedView,
    SelectRequest,
    SelectResult,
)
from .settings import Settings
from .store import ModelRecord, ModelStore, utc_now

# ----------------------------------------------------------------------------- loaded models

def model_loader(store: ModelStore) -> Callable[[str], Renderer]:
    """How the memory ledger loads a stored model by id (404 if it was deleted meanwhile): the
    file alone, as stored; its training cameras are the record's, and what loading noted was
    noted at its upload (no warning is issued: a warning's write to a full disk must not fail
    the request, and "no training cameras" was wrong for a model whose cameras the record holds)."""
    def load(model_id: str) -> Renderer:
        record = store.get(model_id)
        if record is None or not store.path(record).is_file():
            raise not_found("model", model_id)
        renderer = load_model_bytes(store.path(record).read_bytes(), record.name)
        if accepts_background(renderer) and record.describe.get("background") is not None:
            set_background(renderer, record.describe["background"])
        return renderer
    return load


# ----------------------------------------------------------------------------- request checks

FRAME_KEYS = {"fx": "fl_x", "fy": "fl_y", "width": "w", "height": "h"}  # Camera attribute -> frame key


def _camera_field(prefix: str, library_field: str) -> str:
    """'frames[3].fx' from the library -> 'cameras[3].fl_x', the key the user wrote."""
    if library_field.startswith("frames"):
        path, _, key = library_field[len("frames"):].rpartition(".")
        return f"{prefix}{path}.{FRAME_KEYS.get(key, key)}" if path else prefix + key
    return f"{prefix}.{library_field}"


def read_cameras(source: Any, size: RenderSize, settings: Settings, *, field: str, cap: int) -> list[Camera]:
    """Validated cameras at their own size (frames without w/h take the request's width x
    height), or a 422 naming the frame and key."""
    frames = source.get("frames") if isinstance(source, dict) else source
    if isinstance(frames, list) and len(frames) > cap:
        raise invalid(field, f"{len(frames)} cameras exceed the cap of {cap} per request")
    if (size.width is None) != (size.height is None):
        raise invalid("width" if size.width is None else "height", "give width and height together")
    try:
        if is_inria_cameras(source):     # the reference 3DGS trainer's cameras.json, as is
            return cameras_from_entries(source, settings.max_frame_size, file="frames")
        return cameras_from_json(source, width=size.width, height=size.height, max_size=settings.max_frame_size)
    except InputError as exc:
        raise invalid(_camera_field(field, exc.field), exc.reason) from None


def render_size(cameras: list[Camera], size: RenderSize, settings: Settings, *, field: str) -> list[Camera]:
    """The cameras at the requested render size (width x height, else 1/downscale), each
    within the render cap, or a 422 naming the field to change."""
    try:
        if size.width is not None:
            # A width without a height reaches resized, whose check answers 422 naming height.
            cameras = [c.resized(size.width, size.height) for c in cameras]  # type: ignore[arg-type]
        elif size.downscale is not None:
            cameras = [c.scaled(size.downscale) for c in cameras]
    except InputError as exc:
        raise invalid(exc.field if exc.field in ("downscale", "width", "height") else field, exc.reason) from None
    for i, camera in enumerate(cameras):
        if max(camera.width, camera.height) > settings.max_image_size:
            raise invalid(f"{field}[{i}]", f"renders at {camera.width}x{camera.height}, above the cap of "
                          f"{settings.max_image_size} pixels per side (lower the resolution with downscale "
                          "or width/height)")
    return cameras


def parse_cameras(source: Any, size: RenderSize, settings: Settings, *, field: str, cap: int) -> list[Camera]:
    """Validated cameras at the requested render size, or a 422 naming the frame and key."""
    return render_size(read_cameras(source, size, settings, field=field, cap=cap), size, settings, field=field)


def stored_cameras(record: ModelRecord) -> list[Camera]:
    """The training cameras stored with a model (validated at upload), [] when there are none."""
    return cameras_from_json(record.training_frames) if record.training_frames else []


def stored_up(record: ModelRecord) -> tuple[list[float], str]:
    """The model's up and how it was found: as found at upload (`capture_up` on its training
    cameras and opaque splats); for a model stored before that, from its cameras alone."""
    up, rule = record.describe.get("up"), record.describe.get("up_rule")
    if isinstance(up, list) and isinstance(rule, str):
        return up, rule
    found = capture_up(stored_cameras(record))
    return found.vector.tolist(), found.rule


def check_samples(samples: int | None, settings: Settings, default: int) -> int:
    samples = default if samples is None else samples
    if samples > settings.max_samples:
        raise invalid("samples", f"{samples} samples exceed the cap of {settings.max_samples}")
    return samples


def stored_ratio(record: ModelRecord, field: str, given: float | None) -> tuple[float, str]:
    """The dropout ratio to use: the request's, else the stored calibration's, else 409."""
    if given is not None:
        return given, "request"
    if record.calibration is None:
        raise ServiceError(409, "not_calibrated", f"model '{record.id}' has no calibration: calibrate it "
                           f"(POST /v1/models/{record.id}/calibrate) or give {field}", field)
    return float(record.calibration["r_drop"]), "calibration"


def job_signal(given: str | None, ratios: list[tuple[ModelRecord, str]]) -> str:
    """What a job measures zeta on: the request's signal, else that of the stored calibrations
    whose r_drop it uses (ratios: (record, ratio source) per model), else the default. An r_drop
    calibrated on another signal than the request's is a 409 naming `signal`."""
    used = {record.id: record.calibration.get("signal", DEFAULT_SIGNAL) for record, source in ratios
            if source == "calibration" and record.calibration is not None}
    signal = given if given is not None else next(iter(used.values()), DEFAULT_SIGNAL)
    for model_id, calibrated in used.items():
        if calibrated != signal:
            raise ServiceError(409, "signal_mismatch", f"model '{model_id}' was calibrated on the {calibrated} "
                               f"signal, not {signal}: calibrate it with signal '{signal}', give the dropout "
                               "ratio, or use its signal", "signal")
    return signal


def pixels(cameras: list[Camera]) -> int:
    return sum(c.width * c.height for c in cameras)



@dataclass
class Renders:
    """What a job renders, for its memory plan: each model (with the request field naming it)
    and every camera rendered with it; what the job keeps across views."""

    models: list[tuple[ModelRecord, str, list[Camera]]]
    samples: int
    kept_bytes: int = 0
    kept_field: str = "cameras"
    keeps_views: bool = False       # calibration keeps prepared views for re-use (up to VIEW_CACHE_BYTES)
    visibility: bool = False        # a visibility pass follows each render (rank strategies that use it)
    signal: str = DEFAULT_SIGNAL    # what the renders return (its channels size the engine's images)
    cheaper: Renders | None = None  # the same job under CHEAPER_STRATEGY (a strategy that uses visibility)
    sizes: dict[str, int] = field(init=False)    # file bytes by model id

    def __post_init__(self) -> None:
        self.sizes = {record.id: record.size_bytes for record, _, _ in self.models}

    def plan(self, settings: Settings, bounds: RenderMemory | None = None, kept_views: int = 0,
             renderers: dict[str, Renderer] | None = None) -> MemoryPlan:
        """The memory plan (service.budget), or a 413 naming the field to lower. Without the
        renders' bounds (before the models are loaded), a lower bound. When the strategy's own
        memory is what does not fit (the `cheaper` job would), the 413 names `strategy`."""
        pixels = max(c.width * c.height for _, _, cameras in self.models for c in cameras)
        try:
            return plan_work([ModelSize(r.id, r.num_units, r.size_bytes, name) for r, name, _ in self.models], pixels,
                             self.samples, self.kept_bytes + kept_views, settings.memory_budget_bytes, renders=bounds,
                             size_field="downscale", kept_field=self.kept_field,
                             channels=signal_channels(self.signal))
        except OverBudget as refused:
            if self.cheaper is None:
                raise
            try:
                self.cheaper.plan(settings, None if renderers is None else
                                  self.cheaper.bounds(renderers, lambda fraction: None)[0])
            except OverBudget:
                raise refused from None
            raise OverBudget("strategy", refused.need, refused.budget,
                              f"strategy '{CHEAPER_STRATEGY}', which fits (the strategy's view of what each camera "
                              "sees does not), or a lower resolution (downscale, or width/height)") from None

    def bounds(self, renderers: dict[str, Renderer], progress: Progress) -> tuple[RenderMemory, int]:
        """The largest bounds of the renders, and what calibration's prepared views keep."""
        found, kept = [], 0
        for record, _, cameras in self.models:
            renderer = renderers[record.id]
            memory = FAMILIES[renderer.kind].memory
            for camera in cameras:
                progress(0.0)                     # a cancelled job stops here too
                bound = (RenderMemory(0, 0, DEFAULT_MASK_PIXEL_BYTES * camera.width * camera.height)
                         if memory is None else memory(renderer, camera))
                if self.visibility:
                    bound = replace(bound, fixed=bound.fixed + PASS_UNIT_BYTES * record.num_units + bound.seen)
                found.append(bound)
                kept += bound.kept
        return RenderMemory.largest(found), min(kept, VIEW_CACHE_BYTES) if self.keeps_views else 0


@dataclass
class Bounded:
    """A job's work, run with its models in memory and its memory reserved, together. Once its
    models are loaded the plan is made again with the bounds of its renders (each model
    projected into each camera), and the renders are batched to fit it."""

    renders: Renders
    settings: Settings
    ledger: MemoryLedger
    work: Callable[[dict[str, Renderer], Progress], tuple[Any, dict[str, bytes]]]

    def plan(self, renderers: dict[str, Renderer], progress: Progress) -> MemoryPlan:
        """The plan with the bounds of the renders, or a 413 naming the field to lower."""
        return self.renders.plan(self.settings, *self.renders.bounds(renderers, progress), renderers=renderers)

    def __call__(self, progress: Progress) -> tuple[Any, dict[str, bytes]]:
        probe = max(memory_probe_bytes(record.num_units) for record, _, _ in self.renders.models)
        with self.ledger.models(self.renders.sizes, probe) as renderers:
            plan = self.plan(renderers, progress)
        with self.ledger.models(self.renders.sizes, plan.bytes) as renderers, uq.limit_mask_batch(plan.mask_batch):
            return self.work(renderers, progress)


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _span(progress: Progress, start: float, end: float) -> Progress:
    """Progress of one phase mapped onto [start, end] of the job."""
    return lambda fraction: progress(start + (end - start) * fraction)


# ----------------------------------------------------------------------------- calibrate

def calibrate_job(record: ModelRecord, body: CalibrateRequest, settings: Settings, store: ModelStore,
                  ledger: MemoryLedger, executor: Executor = LOCAL) -> tuple[Work, float]:
    if body.training_cameras is not None:
        source, field = body.training_cameras, "training_cameras"
    elif record.training_frames:
        source, field = record.training_frames, "training_cameras"
    else:
        raise ServiceError(409, "no_training_cameras", f"model '{record.id}' has no stored training cameras: "
                           "give training_cameras (or upload the model with its cameras)", "training_cameras")
    cameras = parse_cameras(source, body, settings, field=field, cap=settings.max_training_cameras)
    samples = check_samples(body.samples, settings, uq.DEFAULT_CALIBRATION_SAMPLES)
    given = {"epsilon": body.epsilon, "step": body.step}
    options: dict[str, float] = {k: v for k, v in given.items() if v is not None}
    step = body.step or uq.DEFAULT_STEP
    estimate = pixels(cameras) * (1 + samples * int(1 / step))
    # One pass renders LOOKAHEAD ratios of `samples` masks per view; it keeps float32 references.
    channels = signal_channels(body.signal)
    renders = Renders([(record, "model_id", cameras)], samples * uq.LOOKAHEAD,
                      kept_bytes=4 * channels * pixels(cameras), kept_field="training_cameras", keeps_views=True,
                      signal=body.signal)
    renders.plan(settings)

    def work(renderers: dict[str, Renderer], progress: Progress) -> tuple[Calibration, dict[str, bytes]]:
        result = uq.calibrate(renderers[record.id], cameras, samples=samples, method=body.method, seed=body.seed,
                              progress=progress, executor=executor, signal=body.signal, **options)
        calibration = Calibration(**result.to_dict(), num_cameras=len(cameras), created_at=utc_now())
        if not store.set_calibration(record.id, calibration.model_dump()):
            raise not_found("model", record.id)
        return calibration, {}

    return Bounded(renders, settings, ledger, work), float(estimate)


# ----------------------------------------------------------------------------- rank

def generated_candidates(record: ModelRecord, body: RankRequest, settings: Settings,
                         ledger: MemoryLedger) -> list[Camera]:
    """The poses of a rank request's generator spec, placed around the model's training cameras
    (else its splats: the model is loaded, waiting for memory at most `upload_wait`), checked
    like explicit cameras, at their own size."""
    spec = body.candidates
    assert spec is not None  # rank_job calls this only for a request that gives candidates
    if spec.count > settings.max_candidates:
        raise invalid("candidates.count", f"{spec.count} poses exceed the cap of {settings.max_candidates} per request")
    training = stored_cameras(record)
    # The ignores below: the options' values are the schema's numbers, which mypy cannot match
    # with candidate_cameras' typed parameters; their names are checked first.
    try:
        check_option_names(spec.generator, spec.options)
        if training:
            options = {"up": stored_up(record)[0], **spec.options}      # the stored up, unless given
            poses = candidate_cameras(spec.generator, spec.count, cameras=training,
                                      **options)  # type: ignore[arg-type]
        else:
            # The points taken from the splats are a fraction of the model's own bytes.
            with ledger.models({record.id: record.size_bytes}, model_bytes(record.size_bytes),
                               timeout=settings.upload_wait) as renderers:
                poses = candidate_cameras(spec.generator, spec.count, renderer=renderers[record.id],
                                          **spec.options)  # type: ignore[arg-type]
    except InputError as exc:
        raise invalid(f"candidates.{exc.field}", exc.reason) from None
    except TimeoutError:
        raise busy("candidates", settings.retry_after) from None
    return read_cameras([c.to_frame() for c in poses], body, settings, field="candidates",
                        cap=settings.max_candidates)


def rank_job(record: ModelRecord, body: RankRequest, settings: Settings, job_url: Callable[[str], str],
             ledger: MemoryLedger, executor: Executor = LOCAL, store: ModelStore | None = None) -> tuple[Work, float]:
    """store: where the model's captured coverage is kept (None: the captured poses are rendered at every rank)."""
    if body.candidates is not None:
        poses = generated_candidates(record, body, settings, ledger)
        cameras = render_size(poses, body, settings, field="candidates")
    else:
        poses = read_cameras(body.cameras, body, settings, field="cameras", cap=settings.max_candidates)
        cameras = render_size(poses, body, settings, field="cameras")
    convention = record.describe.get("camera_format")        # poses go back in the source's terms too
    samples = check_samples(body.samples, settings, uq.DEFAULT_SAMPLES)
    ratio, source = stored_ratio(record, "dropout_ratio", body.dropout_ratio)
    signal = job_signal(body.signal, [(record, source)])
    captured = (stored_cameras(record) if body.captured is None else
                parse_cameras(body.captured, body, settings, field="captured", cap=settings.max_training_cameras))
    visibility = get_strategy(body.strategy).uses_visibility
    targets = None
    if body.targets is not None:
        try:
            check_target_strategy(body.strategy)
        except InputError as exc:
            raise invalid(exc.field, exc.reason) from None
        # At the candidates' render size, whatever their own (`targets_at_size`, as `phd rank` does).
        targets = uq.targets_at_size(read_cameras(body.targets, body, settings, field="targets",
                                                  cap=settings.max_candidates), cameras)
    heatmaps = body.heatmaps != "none"
    returned = len(cameras) if body.top_k is None else min(body.top_k, len(cameras))
    rendered = pixels(cameras[:returned]) if heatmaps else 0   # one plain render per returned view
    estimate = pixels(cameras) * samples + rendered
    split = 1.0 - rendered / estimate if estimate else 1.0
    # With heat maps, every candidate's zeta channel max ([H, W] float32) is kept until the order is
    # known, then each returned view's two PNGs (at most PNG_PIXEL_BYTES a pixel each).
    kept = 4 * pixels(cameras) + 2 * PNG_PIXEL_BYTES * returned * max(c.width * c.height for c in cameras)
    kept = kept if heatmaps else 0
    # A strategy that uses visibility keeps what every candidate and target view sees
    # (`visibility_bytes`, the candidates' measured with their dropout renders, the targets'
    # rendered once each). What the captured poses saw is read from the model's stored coverage
    # where it holds them (a stored view stays stored, so the job finds what this plan counts);
    # the rest are rendered, one visibility pass each, kept in compact form and stored
    # (`captured_seen`; a rank that renders none writes nothing). Told targets, the default also
    # holds their distances to the poses (`density_bytes`: whether they are the capture's own path).
    coverage = (CapturedStore(store.cache(record), default=stored_cameras(record))
                if visibility and store is not None else None)
    stored = coverage.index() if coverage is not None else {}
    keys = [camera_key(c) for c in captured] if visibility else []
    fresh = [c for c, key in zip(captured, keys) if key not in stored]
    aimed = targets or []              # given only to a strategy that uses visibility (check_target_strategy)
    read = SEEN_LOADED_BYTES * sum(stored[key] for key in dict.fromkeys(keys) if key in stored)
    seen = (sum(visibility_bytes(record.num_units, c) for c in cameras + aimed) + read
            + seen_bytes(record.num_units, fresh) + COVERAGE_CAPTURE_BYTES
            + density_bytes(len(aimed), len(cameras), len(captured))) if visibility else 0
    renders = Renders([(record, "model_id", cameras + fresh + aimed)], samples, kept_bytes=kept + seen,
                      kept_field="heatmaps" if kept >= seen else "downscale", visibility=visibility, signal=signal)
    if visibility and not aimed:   # over the budget for the strategy's own memory: say which strategy fits
        renders.cheaper = Renders([(record, "model_id", cameras)], samples, kept_bytes=kept,
                                  kept_field="heatmaps", signal=signal)
    renders.plan(settings)

    def work(renderers: dict[str, Renderer], progress: Progress) -> tuple[RankResult, dict[str, bytes]]:
        renderer = renderers[record.id]
        ranked = uq.rank_views(renderer, cameras, ratio=ratio, samples=samples, seed=body.seed, top_k=body.top_k,
                               strategy=body.strategy, captured=captured, keep_peak=heatmaps,
                               progress=_span(progress, 0.0, split), executor=executor, coarse=body.coarse,
                               refine=body.refine, signal=signal, captured_store=coverage, targets=targets)
        views = [RankedCandidate(index=r.index, rank=r.rank, sigma_max=r.sigma_max, sigma_mean=r.sigma_mean,
                                 score=r.score, refined=r.refined, camera=poses[r.index].to_frame(),
                                 source_pose=source_pose(poses[r.index], convention)) for r in ranked]
        artifacts: dict[str, bytes] = {}
        vmax = None
        if heatmaps:
            # One colour scale for all maps (the largest sigma_max), so they compare by eye. The
            # maps are the ranking's own zeta (kept as its channel max): nothing is rendered twice.
            vmax = max(v.sigma_max for v in views)
            done = _span(progress, split, 1.0)
            for k, (view, r) in enumerate(zip(views, ranked)):
                assert r.peak is not None  # ranked with keep_peak=heatmaps
                png = png_bytes(colorize(r.peak, vmax if vmax > 0 else None)[0])
                view.heatmap_png, view.heatmap_url = deliver(png, body.heatmaps, f"heatmap_{view.index:04d}.png",
                                                             artifacts, job_url)
                # Beside the map, the model's own render of the view (one render, no dropout).
                image = renderer.render(cameras[view.index])[0]
                view.render_png, view.render_url = deliver(png_bytes(image), body.heatmaps,
                                                           f"render_{view.index:04d}.png", artifacts, job_url)
                done((k + 1) / len(views))
        result = RankResult(model_id=record.id, dropout_ratio=ratio, ratio_source=source, strategy=body.strategy,
                            rule=ranked.rule, signal=signal, samples=samples,
                            seed=body.seed, width=cameras[0].width, height=cameras[0].height,
                            num_candidates=len(cameras), num_targets=len(targets or []), heatmap_vmax=vmax,
                            camera_format=convention, views=views,
                            notes=list(record.describe.get("notes", [])))
        return result, artifacts

    return Bounded(renders, settings, ledger, work), float(estimate)


def deliver(png: bytes, mode: str, name: str, artifacts: dict[str, bytes],
            job_url: Callable[[str], str]) -> tuple[str | None, str | None]:
    """A PNG inline (mode "base64") or as a downloadable job artefact: (base64, url)."""
    if mode == "base64":
        return b64(png), None
    artifacts[name] = png
    return None, job_url(name)


# ----------------------------------------------------------------------------- select

def select_job(record_a: ModelRecord, record_b: ModelRecord, body: SelectRequest, settings: Settings,
               job_url: Callable[[str], str], ledger: MemoryLedger, executor: Executor = LOCAL) -> tuple[Work, float]:
    cameras = parse_cameras(body.cameras, body, settings, field="cameras", cap=settings.max_candidates)
    samples = check_samples(body.samples, settings, uq.DEFAULT_SAMPLES)
    ratio_a, source_a = stored_ratio(record_a, "ratio_a", body.ratio_a)
    ratio_b, source_b = stored_ratio(record_b, "ratio_b", body.ratio_b)
    signal = job_signal(body.signal, [(record_a, source_a), (record_b, source_b)])
    images = body.images != "none"
    estimate = pixels(cameras) * (2 * samples + 2 * images)
    levels: dict[str, list[Camera]] = {"model_a": [], "model_b": []}      # rendered at their own size
    kept = 0
    rule = uq.SELECTION_RULES[body.rule]     # the schema admits registered names only
    if rule.relative:
        records = {"model_a": record_a, "model_b": record_b}
        training: dict[str, list[Camera]] = {}
        for name, record in records.items():
            if not record.training_frames:
                raise invalid(name, f"the model has no training cameras, which rule '{body.rule}' needs: upload "
                              "it with its cameras, or use rule 'sigma_mean'")
            training[name] = stored_cameras(record)
        own = {name: level_views(cams) for name, cams in training.items()}
        for name, other in (("model_a", "model_b"), ("model_b", "model_a")):
            # Its own level views; with coverage every training view (what each view sees is kept);
            # checked: also the other's level views, where both full renders are kept.
            levels[name] = (training[name] if rule.coverage else own[name]) + (own[other] if rule.checked else [])
            if rule.coverage:
                kept += sum(visibility_bytes(records[name].num_units, c) for c in cameras + levels[name])
            if rule.checked:
                kept += 2 * 12 * pixels(own[other])
        levels_rendered = 2 if rule.checked else 1       # its own, and the other's
        estimate += 2 * levels_rendered * uq.SELECTION_TRAINING_VIEWS * pixels(cameras[:1]) * samples
    # With images, both models' full render of every view ([H, W, 3] float32) is kept until the
    # choice, then the PNGs of the chosen one (and of the other with both_images).
    kept += (2 * 12 + (1 + body.both_images) * PNG_PIXEL_BYTES) * pixels(cameras) if images else 0
    renders = Renders([(record_a, "model_a", cameras + levels["model_a"]),
                       (record_b, "model_b", cameras + levels["model_b"])], samples, kept_bytes=kept,
                      kept_field="images", visibility=rule.coverage, signal=signal)
    renders.plan(settings)

    def work(renderers: dict[str, Renderer], progress: Progress) -> tuple[SelectResult, dict[str, bytes]]:
        renderer_a, renderer_b = renderers[record_a.id], renderers[record_b.id]
        result = uq.select_models(renderer_a, renderer_b, cameras, ratio_a=ratio_a, ratio_b=ratio_b,
                                  samples=samples, seed=body.seed, rule=body.rule,
                                  training_a=stored_cameras(record_a), training_b=stored_cameras(record_b),
                                  keep_images=("both" if body.both_images else True) if images else False,
                                  progress=progress, executor=executor, signal=signal)
        views: list[SelectedView] = []
        artifacts: dict[str, bytes] = {}
        for v in result.views:
            view = SelectedView(index=v.index, choice=v.choice, score_a=v.score_a, score_b=v.score_b,
                                model_id=record_a.id if v.choice == "a" else record_b.id)
            if v.image is not None:
                view.image_png, view.image_url = deliver(png_bytes(v.image), body.images,
                                                         f"selected_{v.index:04d}.png", artifacts, job_url)
            if v.other_image is not None:
                view.other_image_png, view.other_image_url = deliver(
                    png_bytes(v.other_image), body.images, f"other_{v.index:04d}.png", artifacts, job_url)
            views.append(view)
        counts = {"a": sum(v.choice == "a" for v in views), "b": sum(v.choice == "b" for v in views)}
        return SelectResult(model_a=record_a.id, model_b=record_b.id, ratio_a=ratio_a, ratio_b=ratio_b,
                            rule=body.rule, signal=signal, samples=samples, seed=body.seed, counts=counts,
                            views=views), artifacts

    return Bounded(renders, settings, ledger, work), float(estimate)


# ----------------------------------------------------------------------------- poses to capture

@dataclass(frozen=True)
class PoseFile:
    """Ranked poses written as a capture tool's file: its bytes, media type and file name."""

    content: bytes
    media_type: str
    filename: str


def export_poses(record: ModelRecord, body: PosesRequest, settings: Settings) -> PoseFile:
    """The poses in `body` written by `phd_core.data.export_cameras`, the function `phd rank --export`
    calls, with the same image names: in the convention asked for, else the model's own. A
    folder (a COLMAP text model) comes back as a zip of its files."""
    cameras = read_cameras(body.cameras, RenderSize(), settings, field="cameras", cap=settings.max_candidates)
    # A candidate's index names its image file: one of a rank request's at most max_candidates.
    indices = list(range(len(cameras))) if body.indices is None else [
        check_int(index, f"indices[{k}]", 0, settings.max_candidates - 1) for k, index in enumerate(body.indices)]
    own = record.describe.get("camera_format")                 # a capture format; LLFF has no pose convention
    convention = POSES[body.format or (own if isinstance(own, str) and own in POSES else "nerfstudio")]
    folder = convention.suffix == ""
    target = "colmap" if folder else convention.file_name or "transforms.json"
    with tempfile.TemporaryDirectory(prefix="phd-poses-") as tmp:
        path = Path(tmp) / target
        export_cameras(path, cameras, [candidate_name(rank, index) for rank, index in enumerate(indices, 1)],
                       convention.name)
        if not folder:
            return PoseFile(path.read_bytes(), "application/json", target)
        archive = io.BytesIO()
        with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zipped:
            for file in sorted(path.iterdir()):
                zipped.write(file, f"{target}/{file.name}")
        return PoseFile(archive.getvalue(), "application/zip", f"{target}.zip")
