"""A job's memory plan and its work run within it: what a job renders (`Renders`), planned
against the memory budget before it is queued (a lower bound) and again once its models are
loaded (the bounds of every render), and the work run with that memory reserved (`Bounded`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

from phd_core import uq
from phd_core.renderers import DEFAULT_SIGNAL, FAMILIES, Renderer, RenderMemory, memory_probe_bytes, signal_channels
from phd_core.renderers.visibility import PASS_UNIT_BYTES
from phd_core.scene import Camera
from phd_core.uq import Progress
from phd_core.uq.sampling import VIEW_CACHE_BYTES
from phd_core.uq.strategies import CHEAPER_STRATEGY

from .budget import DEFAULT_MASK_PIXEL_BYTES, MemoryLedger, MemoryPlan, ModelSize, OverBudget, plan_work
from .settings import Settings
from .store import ModelRecord


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


def span(progress: Progress, start: float, end: float) -> Progress:
    """Progress of one phase mapped onto [start, end] of the job."""
    return lambda fraction: progress(start + (end - start) * fraction)
