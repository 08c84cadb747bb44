"""What every PH-Dropout computation shares: argument checks, nested keep-masks, batched
masked renders, progress reporting and the two-pass standard deviation.

Masks are nested: every (sample, unit) gets one uniform number u in [0, 1) from a seeded
generator and the unit is kept where u >= r. Raising r only ever drops more units, one
draw serves every ratio, r = 0 keeps everything and r = 1 drops everything.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Callable, Iterator, Sequence

import torch
from torch import Tensor

from ..errors import InputError, check_float, check_int
from ..renderers import DEFAULT_SIGNAL, SIGNALS, Renderer, View, signal_channels
from ..scene import Camera

MAX_MASKS_PER_RENDER = 64          # masks per renderer.render call (bounds renderer memory)
_MASK_BATCH: ContextVar[int] = ContextVar("mask_batch", default=MAX_MASKS_PER_RENDER)
VIEW_CACHE_BYTES = 256 << 20       # prepared views a computation keeps for re-use (PreparedViews)

# What the engine holds for each keep-mask, pixel and channel of a batch (C channels: the
# signal's, 3 or 4), beside the renderer's own work (service.budget adds these to a family's
# RenderMemory). While a batch renders, the loop that consumes `masked_renders` still holds the
# previous batch's images: [m, H, W, C] float32, 4 bytes a channel. Once a batch is rendered: its
# images (4) and one float64 copy that both `RunningStd.add` (the offsets) and calibration (the
# absolute differences) work on in place (8). `_checked` takes only the batch's minimum and maximum.
CHUNK_CHANNEL_BYTES = 4
ENGINE_CHANNEL_BYTES = 12

Progress = Callable[[float], None]


# ----------------------------------------------------------------------------------------
# Argument checks (every public function validates its numbers with InputError)

def check_ratio(value: Any, name: str = "ratio") -> float:
    value = check_float(value, name)
    if not 0.0 <= value <= 1.0:
        raise InputError(name, f"dropout ratio must lie in [0, 1], got {value}")
    return value


def check_seed(seed: Any) -> int:
    seed = check_int(seed, "seed", 0)
    if seed >= 2**63:
        raise InputError("seed", f"must be below 2**63, got {seed}")
    return seed


def check_samples(samples: Any, ddof: Any) -> tuple[int, int]:
    ddof = check_int(ddof, "ddof", 0)
    samples = check_int(samples, "samples", 1)
    if samples - ddof < 1:
        raise InputError("samples", f"need more than ddof={ddof} samples for a standard deviation, "
                         f"got {samples} (use at least {ddof + 1})")
    return samples, ddof


def check_cameras(cameras: Sequence[Camera], name: str = "cameras") -> list[Camera]:
    cameras = list(cameras)
    if not cameras:
        raise InputError(name, "no cameras given")
    for i, camera in enumerate(cameras):
        if not isinstance(camera, Camera):
            raise InputError(f"{name}[{i}]", f"must be a Camera, got {type(camera).__name__}")
    return cameras


def check_step(step: Any) -> float:
    step = check_float(step, "step")
    if not 0.0 < step < 1.0:
        raise InputError("step", f"must lie in (0, 1), got {step}")
    if step < 1e-4:
        raise InputError("step", f"must be at least 1e-4 (at most 10000 ratios), got {step}")
    return step


def check_images(images: Tensor | Sequence[Tensor], cameras: list[Camera], name: str = "images") -> list[Tensor]:
    """One float32 image [H, W, 3] per camera, at its camera's size: `images` is a tensor
    [V, H, W, 3] or a sequence of per-view tensors (views of several sizes, `Dataset.images`)."""
    if not isinstance(images, (Tensor, Sequence)) or not all(isinstance(image, Tensor) for image in images):
        raise InputError(name, f"must be a tensor [V, H, W, 3] or a list of [H, W, 3] tensors, "
                         f"got {type(images).__name__}")
    if len(images) != len(cameras):
        raise InputError(name, f"must hold one image per camera ({len(cameras)}), got {len(images)}")
    for i, (image, camera) in enumerate(zip(images, cameras)):
        if tuple(image.shape) != (camera.height, camera.width, 3):
            raise InputError(name, f"image {i} has shape {list(image.shape)} but its camera renders "
                             f"[{camera.height}, {camera.width}, 3]")
        if not torch.isfinite(image).all():
            raise InputError(name, f"image {i} contains NaN or infinite values")
    return [image.to(torch.float32) for image in images]


def check_signal(signal: Any) -> str:
    """The name of a registered signal (phd_core.renderers.SIGNALS): what zeta and the
    calibration error are measured on."""
    if not isinstance(signal, str):
        raise InputError("signal", f"must be a signal name, got {type(signal).__name__}")
    return SIGNALS.lookup(signal, "signal").name


def check_dtype(dtype: Any) -> torch.dtype:
    if dtype not in (torch.float32, torch.float64):
        raise InputError("dtype", f"accumulation dtype must be torch.float32 or torch.float64, got {dtype}")
    return dtype


# ----------------------------------------------------------------------------------------
# Masks and rendering

def dropout_uniforms(num_units: int, samples: int, seed: int) -> Tensor:
    """One uniform number per (sample, unit): [N, U] float32 in [0, 1), reproducible from `seed`."""
    num_units = check_int(num_units, "num_units", 0)
    samples = check_int(samples, "samples", 1)
    generator = torch.Generator().manual_seed(check_seed(seed))
    return torch.rand((samples, num_units), generator=generator, dtype=torch.float32)


def keep_masks(uniforms: Tensor, ratio: float) -> Tensor:
    """Keep-masks [N, U] bool for dropout ratio `ratio`: unit kept where u >= ratio.

    Masks of a larger ratio are subsets of those of a smaller one (nested).
    """
    return uniforms >= check_ratio(ratio)


def mask_batch() -> int:
    """Masks per renderer.render call in this context (MAX_MASKS_PER_RENDER unless limited)."""
    return _MASK_BATCH.get()


@contextmanager
def limit_mask_batch(masks: int) -> Iterator[None]:
    """Render at most `masks` masks per call inside the block (this thread only): peak memory
    then grows with `masks`, never with the number of samples N (the service sets it from its
    memory budget)."""
    token = _MASK_BATCH.set(min(check_int(masks, "masks", 1), MAX_MASKS_PER_RENDER))
    try:
        yield
    finally:
        _MASK_BATCH.reset(token)


def masked_renders(view: View, keep: Tensor, signal: str = DEFAULT_SIGNAL) -> Iterator[Tensor]:
    """The renders of a prepared view (`Renderer.prepare`) under keep [N, U], `mask_batch()`
    masks at a time: [m, H, W, C] float32 chunks of `signal`'s images, checked for shape and
    finiteness."""
    for chunk in keep.split(mask_batch()):
        yield _checked(view.render(chunk, signal), chunk.shape[0], view.camera, signal)


def render_masks(view: View, keep: Tensor | None, signal: str = DEFAULT_SIGNAL) -> Tensor:
    """Render a prepared view with a batch of keep-masks (None = full model), all N at once
    in memory. Returns [N, H, W, C] float32. Statistics over many masks use `masked_renders`.
    """
    if keep is None:
        return _checked(view.render(None, signal), 1, view.camera, signal)
    parts = list(masked_renders(view, keep, signal))
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _checked(images: Tensor, count: int, camera: Camera, signal: str) -> Tensor:
    shape = (count, camera.height, camera.width, signal_channels(signal))
    if tuple(images.shape) != shape:
        raise RuntimeError(f"renderer returned shape {list(images.shape)}, expected {list(shape)}")
    low, high = torch.aminmax(images)                       # NaN and +-inf reach them; no [N, H, W, C] temporary
    if not (torch.isfinite(low) and torch.isfinite(high)):
        raise RuntimeError("renderer returned NaN or infinite pixel values")
    return images.to(torch.float32)


class RunningStd:
    """Per-element mean and standard deviation over samples that arrive in chunks [m, ...].

    Each chunk is reduced by two passes around the first sample ever seen (the shift), and
    chunks are merged with Chan et al.'s pairwise update (Welford's method for blocks). So
    memory holds one chunk, never all N samples; identical samples give a std of exactly 0
    in any dtype, and nearly equal ones lose no precision to cancellation.
    """

    def __init__(self, dtype: torch.dtype = torch.float64):
        self.dtype = check_dtype(dtype)
        self.count = 0
        self.shift: Tensor | None = None     # [...] the first sample
        self.mean: Tensor | None = None      # [...] mean of (x - shift)
        self.m2: Tensor | None = None        # [...] sum of squared deviations from the mean

    def add(self, chunk: Tensor) -> None:
        if self.shift is None:
            self.shift = chunk[0].to(self.dtype)
            self.mean, self.m2 = torch.zeros_like(self.shift), torch.zeros_like(self.shift)
        assert self.mean is not None and self.m2 is not None      # set with the shift
        m = chunk.shape[0]
        if m == 0:
            return
        offsets = chunk.to(self.dtype, copy=True).sub_(self.shift)   # [m, ...], the only copy of the chunk
        chunk_mean = offsets.mean(0)
        offsets -= chunk_mean
        chunk_m2 = offsets.square_().sum(0)
        del offsets
        total = self.count + m
        delta = chunk_mean - self.mean
        self.mean += delta * (m / total)
        self.m2 += chunk_m2 + delta.square_() * (self.count * m / total)
        self.count = total

    def result(self, ddof: int = 1) -> tuple[Tensor, Tensor]:
        """(std, mean), both in the accumulation dtype; divides by N - ddof."""
        check_samples(self.count, ddof)
        assert self.shift is not None and self.mean is not None and self.m2 is not None   # count >= 1: added
        return (self.m2 / (self.count - ddof)).sqrt(), self.shift + self.mean


class PreparedViews:
    """`renderer.prepare` of each camera, kept for re-use while their total stays within
    `share` of VIEW_CACHE_BYTES; a view beyond it is prepared again on every use (same result,
    slower). Calibration renders every training view once per ratio it tries: this is what it
    re-uses (each executor chunk holds its share of the budget)."""

    def __init__(self, renderer: Renderer, cameras: Sequence[Camera], share: float = 1.0):
        self.renderer, self.cameras = renderer, list(cameras)
        self.budget = int(VIEW_CACHE_BYTES * share)
        self.kept: dict[int, View] = {}
        self.used = 0

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, i: int) -> View:
        if i in self.kept:
            return self.kept[i]
        view = self.renderer.prepare(self.cameras[i])
        if self.used + view.nbytes <= self.budget:
            self.kept[i] = view
            self.used += view.nbytes
        return view


def sample_std(images: Tensor, *, ddof: int = 1, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
    """Per-element standard deviation and mean over the first axis of images [N, ...],
    accumulated in `dtype` by `RunningStd`. Returns (std [...], mean [...]), both in `dtype`."""
    running = RunningStd(dtype)
    for chunk in images.split(MAX_MASKS_PER_RENDER):
        running.add(chunk)
    return running.result(ddof)


class ProgressTicker:
    """Turns 'views done' into progress(fraction) calls, never beyond 0.99 until done."""

    def __init__(self, progress: Progress | None, total: int):
        self.progress, self.total, self.done = progress, max(total, 1), 0

    def tick(self, views: int = 1) -> None:
        self.done += views
        if self.progress is not None:
            self.progress(min(self.done / self.total, 0.99))

    def finish(self) -> None:
        if self.progress is not None:
            self.progress(1.0)
