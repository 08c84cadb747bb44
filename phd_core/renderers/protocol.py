"""The one interface every renderer implements, and the only one PH-Dropout sees.

A renderer holds a trained model whose dropout units are numbered 0..num_units-1
(splats for Gaussian Splatting, first-layer hidden units for NeRF). `render` takes ONE
camera and an optional batch of keep-masks and returns one image per mask. Everything
that does not depend on the mask (projection, culling, intersection lists and depth
order; ray sampling and the first layer) is computed once per call and shared by all
masks: that is where batched PH-Dropout gets its speed. `prepare` goes one step further:
it does that work once for a camera and returns a `View` that renders any number of mask
batches from it (calibration renders the same training views for every ratio it tries).
`signal` (phd_core.renderers.signals) names what a render returns: the colour over the
background (the paper's) or the colour over black plus alpha; every family composites both
from one pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch

from ..scene import Camera
from .signals import DEFAULT_SIGNAL

# What a model loaded or uploaded with no training cameras carries in its facts' notes (any family).
NO_CAMERAS_NOTE = ("the model has no training cameras: poses given and returned are in the frame its file holds "
                   "the model in (check that it is your capture's), calibration needs cameras, and candidate poses "
                   "are placed around the model")


@runtime_checkable
class View(Protocol):
    """One camera prepared for rendering many batches of keep-masks."""

    camera: Camera

    @property
    def nbytes(self) -> int:
        """Memory the prepared state holds (callers bound how many views they keep)."""
        ...

    def render(self, keep: torch.Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        """Same as `Renderer.render(self.camera, keep, signal)`."""
        ...


class CameraView:
    """The View of a renderer with no mask-independent state to keep: it renders anew."""

    nbytes = 0

    def __init__(self, renderer: "Renderer", camera: Camera):
        self.renderer = renderer
        self.camera = camera

    def render(self, keep: torch.Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        return self.renderer.render(self.camera, keep, signal)


@runtime_checkable
class Renderer(Protocol):
    """What PH-Dropout, ranking and ensemble selection need from a model."""

    training_cameras: list[Camera] | None   # the poses the model was trained on, when known

    @property
    def kind(self) -> str:
        """The model family (phd_core.renderers.FAMILIES); a class attribute in the families."""
        ...

    @property
    def num_units(self) -> int:
        """Number of dropout units (the width of a keep-mask)."""
        ...

    def render(self, camera: Camera, keep: torch.Tensor | None = None,
               signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        """Render `camera` once per keep-mask.

        keep: [N, num_units] bool, True = unit kept; None renders the full model (N = 1).
        Returns [N, H, W, C] float32 in [0, 1], `signal`'s image (`signals.SIGNALS`): C = 3,
        RGB composited on the background ("composited"), or C = 4, RGB over black plus
        alpha ("premultiplied").
        Dropped units are zeroed; survivors are not rescaled (unless the renderer was
        built with an explicit rescale option).
        """
        ...

    def prepare(self, camera: Camera) -> View:
        """The mask-independent work for `camera`, done once (`CameraView` when there is none)."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts about the model (kind, units, bounds, ...)."""
        ...


@dataclass(frozen=True)
class RenderMemory:
    """Upper bounds, in bytes, of what rendering one camera holds beyond the model itself.

    A family computes them before rendering (`Family.memory`) from a projection of the model
    into the camera: how many splats cover each pixel decides most of it, and no request
    size tells that. The service plans its memory budget from them (service.budget).
    """

    fixed: int      # whatever the number of masks: `prepare`'s peak, or each render call's mask-independent part
    kept: int       # what the prepared view keeps between render calls (its `nbytes`)
    per_mask: int   # what each keep-mask of one render call adds
    fragments: int = 0   # a bound on the view's fragments (splat/pixel pairs): what a visibility pass walks
    seen: int = 0        # what a view prepared to be seen (`visibility.prepare_seeing`) keeps for its pass

    @staticmethod
    def largest(items: "list[RenderMemory]") -> "RenderMemory":
        """Each bound's maximum over renders that run one after another."""
        return RenderMemory(max(m.fixed for m in items), max(m.kept for m in items), max(m.per_mask for m in items),
                            max(m.fragments for m in items), max(m.seen for m in items))


# Memory functions project the model in chunks of MEMORY_PROBE_UNITS units, so that what they
# hold themselves stays under `memory_probe_bytes` whatever the model (measured: 2DGS with SH
# degree 3 took 1.2 KB a unit, bench/bench_memory.py).
MEMORY_PROBE_UNITS = 1 << 14
MEMORY_PROBE_UNIT_BYTES = 2048


def memory_probe_bytes(units: int) -> int:
    """The most a family's `memory` function holds for a model of `units` units."""
    return min(units, MEMORY_PROBE_UNITS) * MEMORY_PROBE_UNIT_BYTES


def check_keep(keep: torch.Tensor | None, num_units: int) -> torch.Tensor | None:
    """Validate a keep-mask batch; returns it as bool [N, num_units] (or None)."""
    if keep is None:
        return None
    if keep.dim() == 1:
        keep = keep[None]
    if keep.dim() != 2 or keep.shape[1] != num_units:
        raise ValueError(f"keep must have shape [N, {num_units}], got {list(keep.shape)}")
    return keep.to(torch.bool)
