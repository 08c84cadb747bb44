"""Request and response bodies of the REST API, shared by the service and the Python client.

Pure pydantic: importing this module imports neither FastAPI nor torch, so the client
(`client.PHDClient`) parses the server's answers into exactly these types.

Cameras travel as JSON frames in the Blender / nerfstudio style that
`phd_core.scene.camera_from_frame` reads: `transform_matrix` (4x4 camera-to-world,
OpenGL), intrinsics (`fl_x`/`fl_y`/`cx`/`cy` or `camera_angle_x`) and the image size
`w`/`h`. A camera list is either a list of frames or a transforms.json object
(`{"camera_angle_x": ..., "frames": [...]}`) whose top-level keys are defaults for
every frame.
"""

from __future__ import annotations

from typing import Any, Callable, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, field_validator, model_validator

from phd_core.data import POSES
from phd_core.registry import Registry
from phd_core.renderers import DEFAULT_FAMILY, DEFAULT_SIGNAL, FAMILIES, SIGNALS, Family, signals_help
from phd_core.uq import DEFAULT_SELECTION_RULE, SELECTION_RULES, rules_help
from phd_core.uq.candidates import GENERATORS
from phd_core.uq.strategies import DEFAULT_STRATEGY, STRATEGIES

API_VERSION = "v1"

CameraList = Union[list[dict[str, Any]], dict[str, Any]]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JobKind = Literal["calibrate", "rank", "select", "explain", "capture", "add_photos", "train", "next"]
HeatmapMode = Literal["none", "base64", "files"]

def _by_family(fact: Callable[[Family], str]) -> str:
    """'splats (3dgs, 2dgs) or first-layer hidden units (nerf)': a fact of each registered
    family, the families that share it together (those without it left out)."""
    kinds: dict[str, list[str]] = {}
    for family in FAMILIES.values():
        if fact(family):
            kinds.setdefault(fact(family), []).append(family.name)
    return " or ".join(f"{value} ({', '.join(names)})" for value, names in kinds.items())


def _registered(registry: Registry, name: str) -> str:
    """`name` when the registry has it; else a validation error that lists the known names."""
    if name not in registry:
        raise ValueError(registry.unknown(name))
    return name


_SIGNAL_DOC = ("What zeta and the calibration error are measured on, one of the registry's signals: "
               + signals_help() + ".")


def _known_signal(name: str | None) -> str | None:
    return None if name is None else _registered(SIGNALS, name)


_CAMERAS_DOC = ("A list of Blender/nerfstudio frames, or a transforms.json object with a 'frames' "
                "list (its other keys are defaults for every frame). Each frame needs "
                "transform_matrix, a focal length (fl_x or camera_angle_x) and w/h (or give "
                "width/height in the request).")


NOT_RECORDED = "not recorded"      # what a stored answer of an earlier release lacks

class _Request(BaseModel):
    """Request bodies reject unknown fields, so a misspelt option is a 422, not ignored."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class _Response(BaseModel):
    model_config = ConfigDict(extra="ignore")


# ----------------------------------------------------------------------------- errors

class ErrorDetail(_Response):
    code: str = Field(description="Stable machine-readable error code, e.g. 'model_not_found'.")
    message: str = Field(description="What went wrong, for a person.")
    field: str | None = Field(None, description="The offending request field, when one is to blame.")


class ErrorResponse(_Response):
    """The body of every error answer."""

    error: ErrorDetail


# ----------------------------------------------------------------------------- health and models

class Health(_Response):
    status: Literal["ok"] = "ok"
    version: str
    api_version: str = API_VERSION
    key_required: bool = Field(False, description="Whether the other routes need an API key (the web page asks for "
                               "one before it calls them).")


class Calibration(_Response):
    """A stored PH-Dropout calibration (Algorithm 1): r_drop and its error curve."""

    r_drop: float
    ratios: list[float] = Field(description="Tested dropout ratios, ascending.")
    errors: list[float] = Field(description="Mean error on the training views at each tested ratio.")
    epsilon: float
    step: float
    samples: int
    seed: int
    method: str
    capped: bool
    warnings: list[str] = []
    signal: str = Field(DEFAULT_SIGNAL, description="What the error was measured on (request field signal); rank "
                        "and select measure zeta on it when they use this r_drop.")
    num_cameras: int = Field(description="How many training cameras the calibration rendered.")
    created_at: str


class ModelInfo(_Response):
    id: str
    name: str
    kind: str = Field(description="Model family, one of the registry's kinds (phd_core.renderers.FAMILIES).")
    num_units: int = Field(description=f"Dropout units: {_by_family(lambda f: f.units)}.")
    sh_degree: int | None = Field(None, description="Spherical-harmonic degree (models with SH colour).")
    network: dict[str, Any] | None = Field(None, description="Network size facts: "
                                           f"{_by_family(lambda f: ', '.join(f.network))}.")
    bounds: dict[str, list[float]] | None = Field(None, description="Scene bounds {'min': [x,y,z], 'max': [x,y,z]}.")
    size_bytes: int
    sha256: str
    created_at: str
    has_training_cameras: bool
    num_training_cameras: int
    has_calibration: bool
    calibration: Calibration | None = None
    camera_format: str | None = Field(None, description="The format of the capture the training cameras came from "
                                      "(phd_core.data.FORMATS, the name `phd rank` reports); ranked poses come back in "
                                      "it too where it has a pose convention (phd_core.data.POSES).")
    note: str | None = Field(None, description="Set only in an upload's answer (status 200, not 201) when the same "
                             "bytes with the same training cameras, background and capture format are stored already "
                             "under this key: the answer is that model, and no entry was added.")

    @field_validator("kind")
    @classmethod
    def _known_family(cls, kind: str) -> str:
        return _registered(FAMILIES, kind)
    details: dict[str, Any] = Field(default_factory=dict, description="Everything the renderer reports (describe()).")


class ModelList(_Response):
    models: list[ModelInfo]


class TrainingCameras(_Response):
    """A model's stored training cameras as transforms-style frames (empty when it has none)."""

    frames: list[dict[str, Any]]
    up: list[float] = Field(description="The capture's up direction, unit, world coordinates "
                            "(phd_core.scene.capture_up, found at upload: orthogonal to the cameras' horizontal "
                            "image axes, or the normal of the floor the model's splats show near that; +z "
                            "without cameras): the generated poses stand on it and the page's 3D view "
                            "starts upright on it.")
    up_rule: str = Field(description="How the up was found: 'support plane' (the floor or table the splats "
                         "show), 'horizontal axes' (the cameras' own), or the fallback when they cannot tell: "
                         "'mean up', 'mean view' or 'default'.")


# ----------------------------------------------------------------------------- work requests

class RenderSize(_Request):
    """Render resolution: the frames' own size, scaled by 1/downscale, or width x height."""

    downscale: FiniteFloat | None = Field(None, gt=0, le=64, description="Render at 1/downscale of each frame's size.")
    width: int | None = Field(None, ge=1, description="Render width in pixels (with height; overrides downscale).")
    height: int | None = Field(None, ge=1, description="Render height in pixels (with width).")


class CalibrateRequest(RenderSize):
    epsilon: FiniteFloat | None = Field(None, gt=0, le=1, description="Error threshold; default the engine's.")
    step: FiniteFloat | None = Field(None, ge=1e-4, lt=1, description="Dropout-ratio grid step.")
    samples: int | None = Field(None, ge=1, description="Masks per tested ratio.")
    method: Literal["linear", "bisection"] = "linear"
    seed: int = Field(0, ge=0, le=2**63 - 1)
    training_cameras: CameraList | None = Field(None, description="Training cameras; default the stored ones. "
                                                + _CAMERAS_DOC)
    signal: str = Field(DEFAULT_SIGNAL, description=_SIGNAL_DOC, examples=list(SIGNALS))
    run_async: bool = Field(False, alias="async", description="Answer 202 with a job at once.")

    _signal = field_validator("signal")(_known_signal)


class CandidateSpec(_Request):
    """Candidate poses made by the service: a generator placed around the model's training
    cameras (else its splats), with their intrinsics."""

    generator: str = Field(description="One of the registry's generators: " + ", ".join(
        f"{name} ({g.summary})" for name, g in GENERATORS.items()) + ".")
    count: int = Field(64, ge=1, description="How many poses (at most the server's candidate cap).")
    options: dict[str, Union[int, FiniteFloat, list[FiniteFloat]]] = Field(
        default_factory=dict, description="The generator's options, e.g. {'rings': 3, 'elevation': 0.4} for orbit.")

    @field_validator("generator")
    @classmethod
    def _known_generator(cls, name: str) -> str:
        return _registered(GENERATORS, name)


class RankRequest(RenderSize):
    cameras: CameraList | None = Field(None, description="Candidate poses (or give candidates). " + _CAMERAS_DOC)
    candidates: CandidateSpec | None = Field(None, description="Instead of cameras: poses made by a generator.")
    samples: int | None = Field(None, ge=2, description="Dropout samples N per view; default the engine's.")
    seed: int = Field(0, ge=0, le=2**63 - 1)
    dropout_ratio: FiniteFloat | None = Field(None, ge=0, lt=1, description="Default: the stored calibration's r_drop.")
    top_k: int | None = Field(None, ge=1, description="Return only the first k candidates: a batch meant to be "
                              "captured together (diverse for the default strategy).")
    strategy: str = Field(DEFAULT_STRATEGY, description="Next-best-view strategy, one of the names in the "
                          "registry: " + ", ".join(f"{name} ({s.summary})" for name, s in STRATEGIES.items())
                          + ". The default won the active-learning benchmark (docs/nbv.md).",
                          examples=list(STRATEGIES))   # the web page offers these names
    captured: CameraList | None = Field(None, description="Poses already captured; default the model's stored "
                                        "training cameras. " + _CAMERAS_DOC)
    targets: CameraList | None = Field(None, description="The views the model will be looked at from (a walkthrough "
                                       "path, a turntable ring), rendered at the candidates' size: the coverage "
                                       "strategies (visibility, visibility_sigma, visibility_sigma_fvs) value a "
                                       "candidate by what it fixes in these views: the parts they show that the "
                                       "captured views missed from their direction. Default: every view alike. "
                                       + _CAMERAS_DOC)
    heatmaps: HeatmapMode = Field("none", description="zeta heat maps of the returned views: inline base64 PNG, "
                                  "or PNG files to download from the job's artefacts.")
    coarse: FiniteFloat | None = Field(None, gt=0, lt=1, description="Coarse to fine: rank every candidate at this "
                                       "scale of its size first, then re-rank the best `refine` at full size "
                                       "(faster for many candidates; agreement and price in docs/performance.md).")
    refine: int | None = Field(None, ge=1, description="With coarse: how many candidates are re-ranked at full "
                               "size (default 20 % of them, at least top_k).")
    signal: str | None = Field(None, description=_SIGNAL_DOC + " Default: the stored calibration's when its r_drop "
                               "is used, else " + DEFAULT_SIGNAL + ".", examples=list(SIGNALS))
    run_async: bool = Field(False, alias="async", description="Answer 202 with a job at once.")

    _signal = field_validator("signal")(_known_signal)

    @field_validator("strategy")
    @classmethod
    def _known_strategy(cls, name: str) -> str:
        return _registered(STRATEGIES, name)

    @model_validator(mode="after")
    def _one_candidate_source(self) -> "RankRequest":
        if (self.cameras is None) == (self.candidates is None):
            raise ValueError("give either cameras (explicit candidate poses) or candidates (a generator spec)")
        return self


class SelectRequest(RenderSize):
    model_a: str
    model_b: str
    cameras: CameraList = Field(description="Views to choose a model for. " + _CAMERAS_DOC)
    samples: int | None = Field(None, ge=2)
    seed: int = Field(0, ge=0, le=2**63 - 1)
    ratio_a: FiniteFloat | None = Field(None, ge=0, lt=1, description="Default: model a's calibration.")
    ratio_b: FiniteFloat | None = Field(None, ge=0, lt=1, description="Default: model b's calibration.")
    rule: Literal[tuple(SELECTION_RULES)] = Field(  # type: ignore[valid-type]
        DEFAULT_SELECTION_RULE, description=rules_help() + ".")
    images: HeatmapMode = Field("none", description="The selected model's render per view: inline base64 PNG "
                                "or downloadable files.")
    both_images: bool = Field(False, description="With images: also the other model's render per view "
                              "(other_image_png / other_image_url), to compare the two.")
    signal: str | None = Field(None, description=_SIGNAL_DOC + " Default: the stored calibrations' when their r_drop "
                               "is used, else " + DEFAULT_SIGNAL + ".", examples=list(SIGNALS))
    run_async: bool = Field(False, alias="async", description="Answer 202 with a job at once.")

    _signal = field_validator("signal")(_known_signal)


class PosesRequest(_Request):
    """Ranked poses to download as the files a capture tool reads (`phd rank --export` writes the same)."""

    cameras: list[dict[str, Any]] = Field(description="The poses in capture order, as transforms frames at their "
                                          "own size: a rank result's views[].camera.", min_length=1)
    indices: list[int] | None = Field(None, description="Each pose's candidate index (views[].index): the images "
                                      "to capture are named rank<k>_candidate<index>.png. Default 0, 1, 2, ...")
    format: str | None = Field(None, description="One of the pose conventions: " + ", ".join(
        f"{name} ({c.writes})" for name, c in POSES.items()) + ". Default: the model's camera_format, else "
        "nerfstudio. A COLMAP text model comes as a zip of its three files.", examples=list(POSES))

    @field_validator("format")
    @classmethod
    def _known_format(cls, name: str | None) -> str | None:
        return None if name is None else _registered(POSES, name)

    @model_validator(mode="after")
    def _one_index_per_pose(self) -> "PosesRequest":
        if self.indices is not None and len(self.indices) != len(self.cameras):
            raise ValueError(f"give one index per camera: {len(self.indices)} indices for {len(self.cameras)} cameras")
        return self


class ExplainRequest(RenderSize):
    """Per-splat explanation of a model for the 3D view: coverage by the captured views,
    PH-Dropout fragility at the model's r_drop, and what a picked pose would newly see."""

    samples: int | None = Field(None, ge=2, description="Dropout samples N per view; default the engine's.")
    seed: int = Field(0, ge=0, le=2**63 - 1)
    dropout_ratio: FiniteFloat | None = Field(None, ge=0, lt=1, description="Default: the stored calibration's r_drop.")
    pick: dict[str, Any] | None = Field(None, description="A pose whose newly seen splats to show (e.g. the ranking's "
                                        "first), as a transforms frame; without it no novelty.")
    captured: CameraList | None = Field(None, description="Poses already captured; default the model's stored "
                                        "training cameras. " + _CAMERAS_DOC)
    cap: int = Field(200_000, ge=1, le=2_000_000, description="Splats to send values for: the same draw as the "
                     "scene's points at this cap (GET /v1/models/{id}/scene).")
    signal: str | None = Field(None, description=_SIGNAL_DOC + " Default: the stored calibration's when its r_drop "
                               "is used, else " + DEFAULT_SIGNAL + ".", examples=list(SIGNALS))
    run_async: bool = Field(False, alias="async", description="Answer 202 with a job at once.")

    _signal = field_validator("signal")(_known_signal)

# ----------------------------------------------------------------------------- work results

class RankedCandidate(_Response):
    index: int = Field(description="Position of the candidate in the request's camera list.")
    rank: int = Field(description="1 = capture first; ranks 1..top_k form one batch (the CLI's, the page's and the "
                      "demo's numbers).")
    sigma_max: float
    sigma_mean: float
    score: float = Field(description="The strategy's score of this candidate when it was ranked.")
    refined: bool = Field(True, description="False: ranked at the coarse size only (request field coarse); its "
                          "statistics and heat map are the coarse render's.")
    heatmap_png: str | None = Field(None, description="base64 PNG of zeta (heatmaps='base64').")
    heatmap_url: str | None = Field(None, description="Path of the PNG artefact (heatmaps='files').")
    render_png: str | None = Field(None, description="base64 PNG of the model's render of the view (no dropout), "
                                   "to show beside the heat map (heatmaps='base64').")
    render_url: str | None = Field(None, description="Path of the render's PNG artefact (heatmaps='files').")
    camera: dict[str, Any] | None = Field(None, description="The candidate's camera as a transforms frame, as "
                                          "given or generated (its own size, before downscale): transform_matrix "
                                          "(4x4 camera-to-world, OpenGL), fl_x, fl_y, cx, cy, w, h.")
    source_pose: dict[str, Any] | None = Field(
        None, description="The same pose in the convention of the source the model's cameras came from (the "
        "result's camera_format), with its name in 'format': colmap {qvec [w,x,y,z], tvec (world-to-camera, "
        "OpenCV), camera {model, width, height, params}}, 3dgs-output {position, rotation (camera-to-world, OpenCV), "
        "fx, fy, width, height} (a cameras.json entry), nerfstudio/blender (a transforms frame). Null when the "
        "source is unknown.")

    @property
    def c2w(self) -> list[list[float]] | None:
        """The 4x4 camera-to-world matrix (OpenGL, as phd_core's Camera), None without a camera."""
        return None if self.camera is None else self.camera["transform_matrix"]


class RankResult(_Response):
    model_id: str
    dropout_ratio: float
    ratio_source: Literal["request", "calibration"]
    strategy: str
    rule: str = Field(NOT_RECORDED, description="The rule that ordered the views, in words: the default follows "
                      "target views that are the capture's own path and spreads from the captured views otherwise "
                      f"({NOT_RECORDED!r} in a job stored by an earlier release).")
    signal: str = Field(DEFAULT_SIGNAL, description="What zeta was measured on.")
    samples: int
    seed: int
    width: int = Field(description="Render width of the first candidate.")
    height: int
    num_candidates: int
    num_targets: int = Field(0, description="The target views the order was made for (0: for every view alike), so "
                             "a client reading the job later knows which question it answers.")
    heatmap_vmax: float | None = Field(None, description="zeta value drawn as the top colour of every heat map.")
    camera_format: str | None = Field(None, description="The format of the model's camera source (colmap, "
                                      "3dgs-output, nerfstudio, blender, llff), in which source_pose is given (null "
                                      "for a format without a pose convention: llff).")
    views: list[RankedCandidate] = Field(description="In the order the strategy would capture them.")
    notes: list[str] = Field(default_factory=list, description="What loading the model noted that bears on these "
                             "poses (e.g. a model with no training cameras: its poses are in the frame its file "
                             "holds the model in).")


class SelectedView(_Response):
    index: int
    choice: Literal["a", "b"]
    model_id: str
    score_a: float = Field(description="Model a's score of this view under the rule (lower = more trusted).")
    score_b: float
    image_png: str | None = None
    image_url: str | None = None
    other_image_png: str | None = Field(None, description="The model not chosen: its render (both_images).")
    other_image_url: str | None = None


class SelectResult(_Response):
    model_a: str
    model_b: str
    ratio_a: float
    ratio_b: float
    rule: str
    signal: str = Field(DEFAULT_SIGNAL, description="What zeta was measured on.")
    samples: int
    seed: int
    counts: dict[str, int] = Field(description="How many views chose a and b.")
    views: list[SelectedView]


class ExplainResult(_Response):
    model_id: str
    dropout_ratio: float
    ratio_source: Literal["request", "calibration"]
    signal: str
    samples: int
    seed: int
    width: int = Field(description="Render width of the first captured view.")
    height: int
    num_views: int = Field(description="Captured views measured (the pick apart).")
    total: int = Field(description="Splats in the model.")
    count: int = Field(description="Splats the values are for: the scene's points at `cap`, in their order.")
    cap: int
    scales: dict[str, float] = Field(description="Per quantity, the value its byte 254 stands for (bytes 0-254 "
                                     "are linear from 0; coverage: 3 views' worth, fragility: its 99th "
                                     "percentile, novelty: the 99th percentile of its non-zero values, 0 "
                                     "when the pick shows nothing no captured view did).")
    values: dict[str, str] = Field(description="Per quantity (coverage, fragility, novelty with a pick), base64 "
                                   "of one byte per point; 255: no value (a splat no view shows).")
    unseen_share: float = Field(description="Share of the model's splats no captured view saw unhidden.")

# ----------------------------------------------------------------------------- captures (the capture loop)

class TrainSummary(_Response):
    """What training a round's model measured (service.loop)."""

    model_id: str
    family: str
    iterations: int | None = Field(description="Optimisation steps (None: the trainer's default).")
    train_views: int
    warm_from: str | None = Field(None, description="The model training continued from (warm start), else None.")
    seconds: float = Field(description="Wall seconds of training alone.")
    num_units: int
    r_drop: float | None = Field(None, description="The calibration's dropout ratio (None: calibration failed, "
                                 "`calibration_error` says why).")
    calibration_error: str | None = None
    test_views: int = Field(0, description="Held-out photos the model was measured on (the capture's test_photos).")
    test_psnr: float | None = Field(None, description="Mean PSNR (dB) of the model's renders of the held-out "
                                    "photos; None without any.")
    sigma_max_bar: float | None = Field(None, description="Mean over the held-out views of sigma_max, the largest "
                                        "per-pixel std over dropout renders (the paper's Appendix A.1).")


class CaptureRound(_Response):
    round: int = Field(description="0: the photos the capture was created with; then one per addition.")
    photos: list[str] = Field(description="The photos sent this round, as named in the capture.")
    registered: list[str] = Field(description="Of them, those structure-from-motion registered, by name (the "
                                  "order of `captured`).")
    not_registered: list[str] = Field(default_factory=list)
    sfm_seconds: float | None = None
    captured: list[dict[str, Any]] = Field(default_factory=list, description="The registered photos' cameras "
                                           "(transforms frames, the capture's frame; PINHOLE, undistorted).")
    train: TrainSummary | None = None
    next: list[dict[str, Any]] | None = Field(None, description="The poses the round's next views asked for, in "
                                              "order (transforms frames).")


class CaptureInfo(_Response):
    id: str
    name: str
    state: Literal["reconstructing", "registering", "ready", "failed"]
    created_at: str
    updated_at: str
    num_photos: int = Field(description="Photos registered in the reconstruction.")
    test_photos: list[str] = Field(description="Photos held out of training: each round's test PSNR.")
    model_id: str | None = Field(None, description="The latest model trained on the capture.")
    rounds: list[CaptureRound]
    report: dict[str, Any] | None = Field(None, description="The latest structure-from-motion report (matcher, "
                                          "points, reprojection error, seconds per stage, notes).")
    error: ErrorDetail | None = Field(None, description="Why the first reconstruction failed (state failed).")
    job: str | None = Field(None, description="Set in the answer that started work on it: the job's id "
                            "(GET /v1/jobs/{id}).")


class CaptureList(_Response):
    captures: list[CaptureInfo]


class TrainRequest(_Request):
    model: str = Field(DEFAULT_FAMILY, description="Model family: " + ", ".join(
        f"`{f.name}`" for f in FAMILIES.values() if f.trainer))
    iterations: int | None = Field(None, ge=1, le=100_000, description="Optimisation steps; default the family's "
                                   "trainer's (as `phd train`).")
    downscale: FiniteFloat = Field(1.0, ge=1, le=64, description="Train on the photos at 1/downscale of their size "
                                   "(they are at most the capture's max_size already).")
    seed: int = Field(0, ge=0, le=2**31 - 1)
    warm_start: bool = Field(True, description="Continue from the capture's latest model of this family (its "
                             "splats, densification resumed) instead of from scratch (docs/service.md, 'The capture "
                             "loop': measured against a cold start).")
    options: dict[str, Any] = Field(default_factory=dict, description="The family's own training options, as "
                                    "`phd train` takes them as flags, underscored (`phd train --help`).")
    samples: int | None = Field(None, ge=2, description="Dropout samples N of the calibration and of sigma_max_bar.")
    run_async: bool = Field(True, alias="async", description="Answer 202 with a job at once (the default: training "
                            "takes minutes).")


class TrainResult(_Response):
    capture_id: str
    round: int
    summary: TrainSummary


class NextRequest(RankRequest):
    """A rank request of the capture's latest model; `targets` may be "capture": the capture's own
    registered views (its path) as the views the model will be looked at from."""

    targets: Union[CameraList, Literal["capture"], None] = Field(  # type: ignore[assignment]
        None, description="The views the model will be looked at from: 'capture' for the capture's own registered "
        "views (its path), or cameras. " + _CAMERAS_DOC)
    top_k: int | None = Field(2, ge=1, description="How many views to capture next (the batch).")
    candidates: CandidateSpec | None = Field(None, description="Poses made by a generator around the capture; "
                                             "default 64 orbit poses (or give cameras).")

    @model_validator(mode="after")
    def _one_candidate_source(self) -> "NextRequest":      # replaces RankRequest's: neither is the default
        if self.cameras is not None and self.candidates is not None:
            raise ValueError("give either cameras (explicit candidate poses) or candidates (a generator spec)")
        return self


class Job(_Response):
    id: str
    kind: JobKind
    state: JobState
    progress: float = Field(description="Fraction done in [0, 1].")
    eta_seconds: float | None = Field(None, description="Seconds left of the work the job is doing now, at its "
                                      "recent pace (training jobs while they train); null when not known.")
    eta_max_seconds: float | None = Field(None, description="A bound on eta_seconds' work: each step left priced at "
                                          "the largest size the model can have by then (at most doubling at each "
                                          "densification, within its splat budget); equal to eta_seconds once the "
                                          "model cannot grow.")
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    estimated_pixels: float = Field(description="The work estimate: rendered views x samples x pixels.")
    result: Union[RankResult, SelectResult, Calibration, ExplainResult, CaptureInfo, TrainResult, None] = None
    error: ErrorDetail | None = None
    artifacts: list[str] = Field(default_factory=list, description="Names of downloadable PNG artefacts.")
