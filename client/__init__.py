"""Python client of the PH-Dropout service: `PHDClient` and its typed exceptions.

Results are the service's pydantic schemas (`service.schemas`, pure pydantic: importing
the client imports neither FastAPI nor torch).
"""

from service.schemas import (
    Calibration,
    CaptureInfo,
    Health,
    Job,
    ModelInfo,
    RankedCandidate,
    RankResult,
    SelectedView,
    SelectResult,
    TrainResult,
)

from .client import (
    AuthenticationError,
    Capture,
    ConflictError,
    InvalidInputError,
    JobCancelledError,
    JobFailedError,
    NotFoundError,
    PayloadTooLargeError,
    PHDClient,
    PHDError,
    QueueFullError,
    ServerError,
    ServiceUnavailableError,
    UnsupportedModelError,
    camera_frames,
)

__all__ = [
    "PHDClient", "Capture", "camera_frames",
    "PHDError", "AuthenticationError", "NotFoundError", "ConflictError", "PayloadTooLargeError",
    "UnsupportedModelError", "InvalidInputError", "QueueFullError", "ServerError", "ServiceUnavailableError",
    "JobFailedError", "JobCancelledError",
    "Calibration", "Health", "Job", "ModelInfo", "RankedCandidate", "RankResult", "SelectedView", "SelectResult",
    "CaptureInfo", "TrainResult",
]
