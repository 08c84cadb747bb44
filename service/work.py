"""What the routes ask the worker pool to do: request checks (`service.requests`), then calls into `phd_core`.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from phd_core import uq
from phd_core.data import POSES, candidate_name, export_cameras, source_pose
from phd_core.errors import InputError, check_int
from phd_core.executors import LOCAL, Executor
from phd_core.io import colorize, png_bytes
from phd_core.renderers import (
    Renderer,
    accepts_background,
    load_model_bytes,
    set_background,
    signal_channels,
)
from phd_core.renderers.visibility import (
    COVERAGE_CAPTURE_BYTES,
    SEEN_LOADED_BYTES,
    seen_bytes,
    visibility_bytes,
)
from phd_core.scene import Camera
from phd_core.uq import Progress
from phd_core.uq.candidates import candidate_cameras, check_option_names
from phd_core.uq.rank import check_target_strategy
from phd_core.uq.select import level_views
from phd_core.uq.strategies import get_strategy
from phd_core.uq.strategies.captured import CapturedStore, camera_key
from phd_core.uq.strategies.targets import density_bytes

from .budget import (
    PNG_PIXEL_BYTES,
    MemoryLedger,
    model_bytes,
)
from .errors import ServiceError, busy, invalid, not_found
from .jobs import Work
from .plans import Bounded, Renders, span
from .requests import (
    check_samples,
    job_signal,
    parse_cameras,
    pixels,
    read_cameras,
    render_size,
    stored_cameras,
    stored_ratio,
    stored_up,
)
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
                               progress=span(progress, 0.0, split), executor=executor, coarse=body.coarse,
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
            done = span(progress, split, 1.0)
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


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


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
