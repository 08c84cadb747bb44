"""NeRF configuration: the network, encoding and sampling settings, checked when built
(`errors.check_*`, like every config in the project)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import torch

from ...errors import InputError, check_bool, check_color, check_float, check_int

ENCODINGS = ("pe", "spe", "hash")
# Memory bounds of one rendering step: samples per ray chunk, and elements of one
# [masks, kept samples, width] activation (2^23 float32 = 32 MB; a few are alive at once).
CHUNK_SAMPLES = 1 << 16
CHUNK_ELEMENTS = 1 << 23


# --------------------------------------------------------------------------- configuration

def check_encoding(encoding: Any) -> str:
    """`encoding` when it is one of ENCODINGS, else an InputError naming the field."""
    if encoding not in ENCODINGS:
        raise InputError("encoding", f"must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    return encoding


@dataclass
class NeRFConfig:
    """Everything needed to rebuild a model: stored as JSON in every checkpoint.

    Defaults are sized for 100x100 training on 2 shared CPU cores (docs/nerf.md): a
    4-layer, 64-wide trunk (64 dropout units) costs about 27k multiply-adds per sample
    (128 wide: 91k, for +0.4 dB), and the occupancy grid keeps only the samples in
    occupied cells.
    """

    encoding: str = "pe"
    depth: int = 4                  # trunk layers, the first one included
    width: int = 64                 # trunk width = number of dropout units
    skip: bool = True               # re-inject the encoded position at layer depth // 2 (depth >= 3)
    color_width: int = 32           # hidden width of the view-dependent colour branch
    pos_freqs: int = 10             # PE frequencies for the position (pe, spe)
    dir_freqs: int = 4              # PE frequencies for the view direction (all encodings)
    hash_levels: int = 8
    hash_features: int = 2
    hash_log2_size: int = 15
    hash_base_resolution: int = 16
    hash_max_resolution: int = 512
    samples: int = 64               # samples per ray over [near, far] clipped to the box
    near: float = 2.0
    far: float = 6.0
    bounds: list[list[float]] = field(default_factory=lambda: [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    background: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    grid_resolution: int = 32
    grid_threshold: float = 0.01    # a cell is empty if a ray crossing its diagonal loses < 1% of its light
    freenerf_frequency: bool = False  # provenance: trained with FreeNeRF's frequency mask
    freenerf_occlusion: bool = False  # provenance: trained with FreeNeRF's occlusion penalty

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> "NeRFConfig":
        """Raise `InputError` naming the first field out of range; return self."""
        check_encoding(self.encoding)
        for name, lo, hi in (("depth", 1, 16), ("width", 1, 1024), ("color_width", 1, 1024),
                             ("pos_freqs", 0, 16), ("dir_freqs", 0, 8), ("hash_levels", 1, 32),
                             ("hash_features", 1, 8), ("hash_log2_size", 8, 24),
                             ("hash_base_resolution", 1, 4096), ("hash_max_resolution", 1, 8192),
                             ("samples", 1, 4096), ("grid_resolution", 1, 256)):
            check_int(getattr(self, name), name, lo, hi)
        if self.hash_max_resolution < self.hash_base_resolution:
            raise InputError("hash_max_resolution", f"must be >= hash_base_resolution ({self.hash_base_resolution}), "
                             f"got {self.hash_max_resolution}")
        for name in ("skip", "freenerf_frequency", "freenerf_occlusion"):
            check_bool(getattr(self, name), name)
        check_float(self.near, "near", 0.0)
        check_float(self.far, "far", 0.0)
        if not self.far > self.near:
            raise InputError("far", f"must exceed near ({self.near}), got {self.far}")
        check_float(self.grid_threshold, "grid_threshold", 0.0, 1.0, open_min=True, open_max=True)
        self.bounds = _check_bounds(self.bounds)
        self.background = list(check_color(self.background, "background"))
        return self

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "NeRFConfig":
        """Validated config from a dict (unknown keys are an error)."""
        if not isinstance(values, dict):
            raise InputError("config", f"must be an object, got {type(values).__name__}")
        known = {f.name for f in fields(cls)}
        for key in values:
            if key not in known:
                raise InputError(str(key), "unknown NeRF setting")
        return cls(**values).validate()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check_bounds(bounds: Any) -> list[list[float]]:
    try:
        box = torch.as_tensor(bounds, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise InputError("bounds", f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {bounds!r}") from None
    if tuple(box.shape) != (2, 3) or not torch.isfinite(box).all():
        raise InputError("bounds", f"must be two finite 3-vectors [min, max], got {bounds!r}")
    if not (box[1] > box[0]).all():
        raise InputError("bounds", f"max must exceed min on every axis, got {box.tolist()}")
    return box.tolist()
