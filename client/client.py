"""`PHDClient`: the PH-Dropout service from Python, one method per route.

    from client import PHDClient

    with PHDClient("http://127.0.0.1:8000", api_key=None) as phd:
        model = phd.upload_model("model.ply", cameras="data/transforms_train.json")
        phd.calibrate(model.id)
        ranking = phd.rank(model.id, candidates, downscale=4, top_k=5)
        print([(v.index, v.sigma_max, v.c2w) for v in ranking.views])   # c2w: the pose to capture

Results are the service's own pydantic types (`service.schemas`). Every error answer
raises a `PHDError` subclass carrying the server's status, code, message and field. Work
that the server turns into a job (asked with `run_async=True`, or too big to answer at
once) is waited for when `wait=True` (the default), with an optional progress callback.

Cameras may be given as `phd_core.scene.Camera` objects, as frame dicts, as a
transforms.json object, as the path of a transforms.json file, or as a trainer's sidecar
JSON (`training_cameras`). Frames without an image size get it from their image file when
that is a PNG next to the JSON.
"""

from __future__ import annotations

import json
import struct
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence, Union, cast

import httpx
from pydantic import BaseModel

from service.schemas import (
    Calibration,
    CaptureInfo,
    CaptureList,
    ExplainResult,
    Health,
    Job,
    ModelInfo,
    ModelList,
    RankResult,
    SelectResult,
    TrainingCameras,
    TrainResult,
)

ProgressCallback = Callable[[float], None]
Cameras = Union[str, Path, dict, Iterable[Any]]
CAMERA_KEYS = ("transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
DEFAULT_TIMEOUT = 300.0


# ----------------------------------------------------------------------------- errors

class PHDError(Exception):
    """An error answer from the service (or no answer: status None)."""

    def __init__(self, message: str, *, status: int | None = None, code: str = "error", field: str | None = None,
                 retry_after: float | None = None):
        super().__init__(message)
        self.message = message
        self.status = status
        self.code = code
        self.field = field
        self.retry_after = retry_after

    def __str__(self) -> str:
        where = f" [{self.field}]" if self.field else ""
        status = f"{self.status} " if self.status is not None else ""
        return f"{status}{self.code}{where}: {self.message}"


class AuthenticationError(PHDError):
    """401: the API key is missing or wrong."""


class NotFoundError(PHDError):
    """404: unknown model, job or artefact id."""


class ConflictError(PHDError):
    """409: the model is not calibrated / has no training cameras, or the job was cancelled."""


class PayloadTooLargeError(PHDError):
    """413: the upload or body is over the server's cap."""


class UnsupportedModelError(PHDError):
    """415: the file is not a model the service reads (never a pickle)."""


class InvalidInputError(PHDError):
    """400/422: a field is invalid; `field` names it."""


class QueueFullError(PHDError):
    """429: the work queue is full; retry after `retry_after` seconds."""


class ServerError(PHDError):
    """5xx: the service failed."""


class ServiceUnavailableError(PHDError):
    """The service could not be reached (connection refused, timeout)."""


class JobFailedError(PHDError):
    """A job ended in state 'failed'; `job` holds it."""

    def __init__(self, job: Job):
        error = job.error
        super().__init__(error.message if error else "job failed", status=None,
                         code=error.code if error else "job_failed", field=error.field if error else None)
        self.job = job


class JobCancelledError(PHDError):
    """A job ended in state 'cancelled'."""

    def __init__(self, job: Job):
        super().__init__(f"job {job.id} was cancelled", code="job_cancelled")
        self.job = job


_BY_STATUS = {400: InvalidInputError, 401: AuthenticationError, 404: NotFoundError, 409: ConflictError,
              413: PayloadTooLargeError, 415: UnsupportedModelError, 422: InvalidInputError, 429: QueueFullError}


def _raise_for(response: httpx.Response) -> None:
    if response.status_code < 400:
        return
    try:
        error = response.json()["error"]
        code, message, field = error["code"], error["message"], error.get("field")
    except (ValueError, KeyError, TypeError):
        code, message, field = "http_error", response.text[:500] or response.reason_phrase, None
    retry = response.headers.get("retry-after")
    cls = _BY_STATUS.get(response.status_code, ServerError if response.status_code >= 500 else PHDError)
    raise cls(message, status=response.status_code, code=code, field=field,
              retry_after=float(retry) if retry and retry.replace(".", "", 1).isdigit() else None)


# ----------------------------------------------------------------------------- cameras

def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, or None if `path` is not a readable PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def _frames_of_transforms(data: dict, base: Path | None) -> list[dict]:
    """A transforms.json object -> self-contained frames (top-level defaults folded in)."""
    defaults = {k: v for k, v in data.items() if k in CAMERA_KEYS}
    frames = []
    for frame in data.get("frames", []):
        if not isinstance(frame, dict):
            frames.append(frame)  # the server names the bad entry
            continue
        merged = {**defaults, **{k: v for k, v in frame.items() if k in CAMERA_KEYS}}
        if base is not None and ("w" not in merged or "h" not in merged) and isinstance(frame.get("file_path"), str):
            path = base / frame["file_path"]
            size = _png_size(path) or _png_size(path.with_name(path.name + ".png"))
            if size is not None:
                merged["w"], merged["h"] = size
        frames.append(merged)
    return frames


def camera_frames(cameras: Cameras) -> list[dict]:
    """Frames (JSON-ready dicts) from Camera objects, frame dicts, a transforms.json object or path."""
    if isinstance(cameras, (str, Path)) and (Path(cameras).is_dir() or str(cameras).lower().endswith(".npy")):
        from phd_core.data import load_cameras  # a capture of any format (COLMAP, LLFF, ...): its train split

        try:
            return [c.to_frame() for c in load_cameras(cameras)]
        except ValueError as exc:
            raise InvalidInputError(str(exc), field="cameras") from None
    if isinstance(cameras, (str, Path)):
        path = Path(cameras)
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise InvalidInputError(f"cannot read camera JSON {path}: {exc}", field="cameras") from None
        if isinstance(data, list):
            return data
        if not isinstance(data, dict):
            raise InvalidInputError(f"{path} holds neither a frame list nor a transforms object", field="cameras")
        if "frames" not in data:
            return camera_frames(data)
        return _frames_of_transforms(data, path.parent)
    if isinstance(cameras, dict):
        if isinstance(cameras.get("training_cameras"), list):  # a trainer's sidecar <stem>.json
            return cameras["training_cameras"]
        return _frames_of_transforms(cameras, None) if "frames" in cameras else [cameras]
    if hasattr(cameras, "to_frame"):
        return [cameras.to_frame()]
    return [c.to_frame() if hasattr(c, "to_frame") else c for c in cast(Iterable[Any], cameras)]


# ----------------------------------------------------------------------------- the client

def _sidecar(sidecar: Path) -> tuple[list[float] | None, str | None, str | None]:
    """The background, capture format and name a `phd train` sidecar records (None for what it
    has not, or when it is unreadable)."""
    try:
        data = json.loads(sidecar.read_text())
        value, source, name = data.get("background"), data.get("dataset_format"), data.get("name")
    except (OSError, ValueError, AttributeError):
        return None, None, None
    return (list(value) if isinstance(value, (list, tuple)) and len(value) == 3 else None,
            source if isinstance(source, str) else None, name if isinstance(name, str) else None)


def _capture_format(cameras: Cameras | None) -> str | None:
    """The format of cameras given as a capture folder or file (COLMAP, LLFF, ...), else None."""
    if not isinstance(cameras, (str, Path)) or not (Path(cameras).is_dir() or str(cameras).lower().endswith(".npy")):
        return None
    from phd_core.data import locate

    try:
        return locate(cameras, "train")[0].name
    except ValueError:
        return None


def _known_format(name: str | None) -> str | None:
    """A capture format's name (phd_core.data.FORMATS, as `phd rank` reports it), else None."""
    if name is None:
        return None
    from phd_core.data import FORMATS

    return name if name in FORMATS else None


class PHDClient:
    """A synchronous client of the PH-Dropout service (thread-safe: one httpx.Client)."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = DEFAULT_TIMEOUT, *,
                 transport: httpx.BaseTransport | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.base_url = base_url.rstrip("/")
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "PHDClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as exc:
            raise ServiceUnavailableError(f"{method} {path} timed out: {exc}", code="timeout") from None
        except httpx.TransportError as exc:
            raise ServiceUnavailableError(f"{method} {path}: cannot reach {self.base_url}: {exc}",
                                          code="unreachable") from None
        _raise_for(response)
        return response

    # ------------------------------------------------------------------ models

    def health(self) -> Health:
        return Health.model_validate(self._request("GET", "/health").json())

    def upload_model(self, path: str | Path, cameras: Cameras | None = None, name: str | None = None,
                     background: str | Sequence[float] | None = None,
                     camera_format: str | None = None, other_capture: bool = False) -> ModelInfo:
        """Upload a 3DGS/2DGS PLY or NeRF checkpoint with its training cameras: `cameras`, else
        the trainer's sidecar `<stem>.json` next to a PLY when there is one (NeRF
        checkpoints carry theirs inside). `path` may be a trainer's output folder as is
        (`phd_core.renderers.outputs`): the reference 3DGS trainer's (its latest
        point_cloud.ply goes up with its cameras.json), nerfstudio splatfacto's or gsplat's
        (read here, checkpoints without unpickling code; the splats go up as a PLY moved into
        the user's frame, with the training cameras in that frame). `background` (splat
        models): the colour trained over, else the sidecar's or the folder's (else the
        service's rule, docs/service.md). `camera_format`: the pose convention of the cameras'
        source (ranked poses come back in it), else the folder's, the sidecar's capture's or
        that of a capture given as `cameras`. `name`: else the sidecar's (`phd train` records
        "<folder>/<stem>") or the run's, else the file's. Cameras most of which see almost none of
        the model (another capture's) are refused with InvalidInputError naming `cameras`, unless
        `other_capture`. The same bytes with the same cameras, background and capture format as a
        model stored under this key answer that model, with `note` saying so (no new entry)."""
        path = Path(path)
        if path.is_dir():
            from phd_core.renderers.gs3d import write_ply
            from phd_core.renderers.outputs import read_output

            output = read_output(path)                    # notes and warnings are issued as Python warnings
            if cameras is None and output.cameras:
                cameras = output.cameras                  # training views only, in the user's frame
                camera_format = camera_format or output.camera_format
            background = output.background if background is None else background
            name = name if name is not None else output.name      # the run, "<experiment>/<method>"
            if output.ply is None:         # splats moved out of the trainer's frame: upload them as a PLY
                with tempfile.TemporaryDirectory(prefix="phd-upload-") as tmp:
                    ply = Path(tmp) / f"{path.resolve().name}.ply"
                    write_ply(output.model, ply)
                    return self.upload_model(ply, cameras, name, background, camera_format, other_capture)
            path = output.ply
        sidecar = path.with_name(path.stem + ".json")
        if path.suffix.lower() == ".ply" and sidecar.is_file():
            sidecar_background, sidecar_format, sidecar_name = _sidecar(sidecar)
            name = name if name is not None else sidecar_name
            if cameras is None:
                cameras, camera_format = sidecar, camera_format or _known_format(sidecar_format)
            if background is None:
                background = sidecar_background
        camera_format = camera_format or _capture_format(cameras)
        data = {}
        if cameras is not None:
            data["cameras"] = json.dumps(camera_frames(cameras))
        if camera_format is not None:
            data["camera_format"] = camera_format
        if background is not None:
            data["background"] = json.dumps(background if isinstance(background, str) else list(background))
        if name is not None:
            data["name"] = name
        if other_capture:
            data["other_capture"] = "true"
        try:
            f = open(path, "rb")
        except OSError as exc:
            raise InvalidInputError(f"cannot open {path}: {exc.strerror or exc}", field="file") from None
        with f:
            response = self._request("POST", "/v1/models", data=data,
                                     files={"file": (path.name, f, "application/octet-stream")})
        return ModelInfo.model_validate(response.json())

    def list_models(self) -> list[ModelInfo]:
        return ModelList.model_validate(self._request("GET", "/v1/models").json()).models

    def get_model(self, model_id: str) -> ModelInfo:
        return ModelInfo.model_validate(self._request("GET", f"/v1/models/{model_id}").json())

    def cameras(self, model_id: str) -> TrainingCameras:
        """The model's stored training cameras (`frames`) and the capture's up (`up`, `up_rule`):
        the direction the generated poses stand on, for poses of your own."""
        return TrainingCameras.model_validate(self._request("GET", f"/v1/models/{model_id}/cameras").json())

    def training_cameras(self, model_id: str) -> list[dict]:
        """The model's stored training cameras as transforms-style frames ([] when it has none)."""
        return self.cameras(model_id).frames

    def delete_model(self, model_id: str) -> None:
        self._request("DELETE", f"/v1/models/{model_id}")

    # ------------------------------------------------------------------ work

    def calibrate(self, model_id: str, *, cameras: Cameras | None = None, epsilon: float | None = None,
                  step: float | None = None, samples: int | None = None, method: str = "linear", seed: int = 0,
                  downscale: float | None = None, width: int | None = None, height: int | None = None,
                  signal: str | None = None, run_async: bool = False, wait: bool = True,
                  progress: ProgressCallback | None = None, poll_interval: float = 0.2,
                  timeout: float | None = None) -> Calibration | Job:
        """PH-Dropout calibration; uses the stored training cameras unless `cameras` is given.
        `signal`: what the error is measured on ('composited', the paper's and the default, or
        'premultiplied': colour over black plus alpha); rank and select use it with this r_drop."""
        body = {"epsilon": epsilon, "step": step, "samples": samples, "method": method, "seed": seed,
                "signal": signal,
                "downscale": downscale, "width": width, "height": height, "async": run_async,
                "training_cameras": None if cameras is None else camera_frames(cameras)}
        return self._work(f"/v1/models/{model_id}/calibrate", body, Calibration, wait, progress, poll_interval, timeout)

    def rank(self, model_id: str, cameras: Cameras | None = None, *, candidates: str | dict | None = None,
             samples: int | None = None, seed: int = 0,
             dropout_ratio: float | None = None, top_k: int | None = None, strategy: str | None = None,
             captured: Cameras | None = None, targets: Cameras | None = None, heatmaps: str = "none",
             downscale: float | None = None, width: int | None = None, height: int | None = None,
             coarse: float | None = None, refine: int | None = None, signal: str | None = None,
             run_async: bool = False, wait: bool = True,
             progress: ProgressCallback | None = None, poll_interval: float = 0.2,
             timeout: float | None = None) -> RankResult | Job:
        """Candidate poses in the order to capture them (the service's default strategy unless `strategy`
        names another). The first `top_k` are a batch meant to be captured together. `captured`: poses
        already taken, default the model's training cameras. `targets`: the views the model will be
        looked at from; the coverage strategies then value a candidate by what it fixes in them.
        Instead of `cameras`, `candidates` lets the service make the poses: a spec "orbit:64,rings=2"
        or {"generator": ..., "count": ..., "options": ...}. `coarse` (a scale in (0, 1)) ranks every
        candidate that much smaller first and re-ranks the best `refine` at full size. `signal`: what
        zeta is measured on (default: the stored calibration's when its r_drop is used)."""
        if isinstance(candidates, str):
            from phd_core.uq.candidates import parse_spec

            name, count, options = parse_spec(candidates)
            candidates = {"generator": name, "count": count, "options": options}
        body = {"cameras": None if cameras is None else camera_frames(cameras), "candidates": candidates,
                "samples": samples, "seed": seed, "dropout_ratio": dropout_ratio,
                "top_k": top_k, "strategy": strategy, "heatmaps": heatmaps, "downscale": downscale,
                "width": width, "height": height, "coarse": coarse, "refine": refine, "signal": signal,
                "async": run_async,
                "captured": None if captured is None else camera_frames(captured),
                "targets": None if targets is None else camera_frames(targets)}
        return self._work(f"/v1/models/{model_id}/rank", body, RankResult, wait, progress, poll_interval, timeout)

    def select(self, model_a: str, model_b: str, cameras: Cameras, *, samples: int | None = None, seed: int = 0,
               ratio_a: float | None = None, ratio_b: float | None = None, rule: str | None = None,
               images: str = "none", both_images: bool = False,
               downscale: float | None = None, width: int | None = None, height: int | None = None,
               signal: str | None = None, run_async: bool = False, wait: bool = True,
               progress: ProgressCallback | None = None, poll_interval: float = 0.2,
               timeout: float | None = None) -> SelectResult | Job:
        """Per view, which of two models to trust (rule: the service's default 'coverage_checked', or
        'coverage_sigma', 'distance_sigma', the paper's 'sigma_mean')."""
        body = {"model_a": model_a, "model_b": model_b, "cameras": camera_frames(cameras), "samples": samples,
                "seed": seed, "ratio_a": ratio_a, "ratio_b": ratio_b, "rule": rule, "images": images,
                "both_images": both_images or None, "downscale": downscale,
                "width": width, "height": height, "signal": signal, "async": run_async}
        return self._work("/v1/select", body, SelectResult, wait, progress, poll_interval, timeout)

    def explain(self, model_id: str, *, pick: Any = None, samples: int | None = None, seed: int = 0,
                dropout_ratio: float | None = None, captured: Cameras | None = None, cap: int | None = None,
                downscale: float | None = None, width: int | None = None, height: int | None = None,
                signal: str | None = None, run_async: bool = False, wait: bool = True,
                progress: ProgressCallback | None = None, poll_interval: float = 0.2,
                timeout: float | None = None) -> ExplainResult | Job:
        """Per splat of the model's scene points (GET /v1/models/{id}/scene at `cap`): coverage by the
        captured views (default its training cameras), PH-Dropout fragility at its r_drop, and what
        `pick` (one pose: a Camera or a frame) would newly see; one byte per point, base64 (docs/service.md)."""
        body = {"pick": None if pick is None else camera_frames([pick])[0], "samples": samples, "seed": seed,
                "dropout_ratio": dropout_ratio, "cap": cap, "downscale": downscale, "width": width,
                "height": height, "signal": signal, "async": run_async,
                "captured": None if captured is None else camera_frames(captured)}
        return self._work(f"/v1/models/{model_id}/explain", body, ExplainResult, wait, progress, poll_interval,
                          timeout)

    def _work(self, path: str, body: dict, result_type: type[BaseModel], wait: bool,
              progress: ProgressCallback | None, poll_interval: float, timeout: float | None) -> Any:
        response = self._request("POST", path, json={k: v for k, v in body.items() if v is not None})
        if response.status_code == 202:
            job = Job.model_validate(response.json())
            if not wait:
                return job
            return self.wait_job(job.id, progress=progress, poll_interval=poll_interval, timeout=timeout)
        result = result_type.model_validate(response.json())
        if progress is not None:
            progress(1.0)
        return result

    # ------------------------------------------------------------------ captures: the capture loop

    def create_capture(self, photos: str | Path | Sequence[str | Path], *, name: str | None = None,
                       test: Sequence[str] = (), wait: bool = True, progress: ProgressCallback | None = None,
                       timeout: float | None = None, **sfm: Any) -> "Capture":
        """A capture from photos (a folder of them, photo files, or one video), reconstructed by the
        service (structure-from-motion, waited for unless `wait=False`). `test`: names of photos held
        out of training, on which every round's model is measured. `sfm`: matcher, camera_model,
        min_registered, fps, as `phd capture` takes them."""
        fields = {key: str(value) for key, value in sfm.items() if value is not None}
        if name is not None:
            fields["name"] = name
        if test:
            fields["test"] = json.dumps(list(test))
        info = self._send_photos("/v1/captures", photos, fields, video=True)
        capture = Capture(self, info)
        return capture.wait(progress=progress, timeout=timeout) if wait else capture

    def get_capture(self, capture_id: str) -> "Capture":
        return Capture(self, CaptureInfo.model_validate(self._request("GET", f"/v1/captures/{capture_id}").json()))

    def list_captures(self) -> list[CaptureInfo]:
        return CaptureList.model_validate(self._request("GET", "/v1/captures").json()).captures

    def delete_capture(self, capture_id: str) -> None:
        self._request("DELETE", f"/v1/captures/{capture_id}")

    def _send_photos(self, path: str, photos: str | Path | Sequence[str | Path], fields: dict[str, str], *,
                     video: bool) -> CaptureInfo:
        """POST the photos (one part each; a video as `video`), streamed from their files."""
        given = [Path(photos)] if isinstance(photos, (str, Path)) else [Path(p) for p in photos]
        if len(given) == 1 and given[0].is_dir():
            given = sorted(p for p in given[0].iterdir() if p.is_file() and not p.name.startswith("."))
        from phd_core.process.photos import is_video

        single = given[0] if len(given) == 1 else None
        part = ("archive" if single is not None and single.suffix.lower() == ".zip" else
                "video" if video and single is not None and is_video(single) else "photos")
        try:
            handles = [open(p, "rb") for p in given]
        except OSError as exc:
            raise InvalidInputError(f"cannot open {exc.filename}: {exc.strerror or exc}", field=part) from None
        try:
            files = [(part, (p.name, f, "application/octet-stream")) for p, f in zip(given, handles)]
            response = self._request("POST", path, data=fields, files=files)
        finally:
            for f in handles:
                f.close()
        return CaptureInfo.model_validate(response.json())

    # ------------------------------------------------------------------ jobs

    def get_job(self, job_id: str) -> Job:
        return Job.model_validate(self._request("GET", f"/v1/jobs/{job_id}").json())

    def cancel_job(self, job_id: str) -> Job:
        return Job.model_validate(self._request("DELETE", f"/v1/jobs/{job_id}").json())

    def wait_job(self, job_id: str, *, progress: ProgressCallback | None = None, poll_interval: float = 0.2,
                 timeout: float | None = None) -> Calibration | RankResult | SelectResult | ExplainResult:
        """Poll a job until it ends; its result, or JobFailedError / JobCancelledError."""
        deadline = None if timeout is None else time.monotonic() + timeout
        last = -1.0
        while True:
            job = self.get_job(job_id)
            if progress is not None and job.progress != last:
                last = job.progress
                progress(job.progress)
            if job.state == "succeeded":
                # the service sets a succeeded job's result; asserting it would change what a bad answer gives
                return job.result  # type: ignore[return-value]
            if job.state == "failed":
                raise JobFailedError(job)
            if job.state == "cancelled":
                raise JobCancelledError(job)
            if deadline is not None and time.monotonic() > deadline:
                raise ServiceUnavailableError(f"job {job_id} still {job.state} after {timeout} s", code="timeout")
            time.sleep(poll_interval)

    def download(self, url: str) -> bytes:
        """The bytes of an artefact (a heatmap_url or image_url from a result)."""
        return self._request("GET", url).content


class Capture:
    """A capture on the service, round after round: `add_photos`, `train`, `next_views`; `info`
    is the capture as last read (`refresh` reads it again)."""

    def __init__(self, client: PHDClient, info: CaptureInfo):
        self.client, self.info = client, info

    @property
    def id(self) -> str:
        return self.info.id

    def refresh(self) -> "Capture":
        self.info = self.client.get_capture(self.id).info
        return self

    def wait(self, *, progress: ProgressCallback | None = None, timeout: float | None = None) -> "Capture":
        """Wait for the structure-from-motion job the last call started (JobFailedError when it failed)."""
        if self.info.job is not None:
            self.client.wait_job(self.info.job, progress=progress, timeout=timeout)
        return self.refresh()

    def add_photos(self, photos: str | Path | Sequence[str | Path], *, test: Sequence[str] = (), wait: bool = True,
                   progress: ProgressCallback | None = None, timeout: float | None = None) -> "Capture":
        """Photos added: registered into the reconstruction, the others' poses unchanged (a new round)."""
        fields = {"test": json.dumps(list(test))} if test else {}
        self.info = self.client._send_photos(f"/v1/captures/{self.id}/photos", photos, fields, video=False)
        return self.wait(progress=progress, timeout=timeout) if wait else self

    def train(self, model: str | None = None, *, iterations: int | None = None, downscale: float | None = None,
              seed: int = 0, warm_start: bool = True, options: dict | None = None, samples: int | None = None,
              wait: bool = True, progress: ProgressCallback | None = None,
              timeout: float | None = None) -> TrainResult | Job:
        """A model trained on the capture (warm-started from the latest one), calibrated and measured on
        the test photos; its id is `result.summary.model_id` (an ordinary stored model)."""
        body = {"model": model, "iterations": iterations, "downscale": downscale, "seed": seed,
                "warm_start": warm_start, "options": options, "samples": samples, "async": True}
        result = self.client._work(f"/v1/captures/{self.id}/train", body, TrainResult, wait, progress, 0.2, timeout)
        self.refresh()
        return result

    def next_views(self, count: int = 2, *, candidates: str | dict | None = None, cameras: Cameras | None = None,
                   targets: str | Cameras | None = None, strategy: str | None = None, samples: int | None = None,
                   seed: int = 0, downscale: float | None = None, width: int | None = None,
                   height: int | None = None, wait: bool = True, progress: ProgressCallback | None = None,
                   timeout: float | None = None) -> RankResult | Job:
        """The next `count` views to capture, ranked with the capture's latest model; each view's
        `camera` is the pose, in the capture's frame. `targets="capture"`: the capture's own path
        as the views the model will be looked at from. `candidates`: a generator name or spec
        (default: 64 orbit poses around the capture)."""
        spec = {"generator": candidates} if isinstance(candidates, str) else candidates
        body = {"top_k": count, "candidates": spec, "strategy": strategy, "samples": samples, "seed": seed,
                "downscale": downscale, "width": width, "height": height,
                "cameras": None if cameras is None else camera_frames(cameras),
                "targets": targets if targets is None or targets == "capture" else camera_frames(targets)}
        result = self.client._work(f"/v1/captures/{self.id}/next", body, RankResult, wait, progress, 0.2, timeout)
        self.refresh()
        return result
