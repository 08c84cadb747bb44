"""What a ranking is made of, per coverage element (splats): how well the captured views saw
each part of the model, how fragile PH-Dropout finds it, and what a picked view would newly see.

Each view is rendered once with the full model and `samples` times under dropout at `ratio`
(the model's r_drop), as the ranking does; its Visibility (`phd_core.renderers.visibility`)
says, per element, the pixels it fills (alpha times transmittance: occlusion included) and
the same weights times zeta's channel max on those pixels. Per element u:

    coverage(u)  = sum over captured views v of share(u, v)
    fragility(u) = sum over views of weight(u) * zeta / sum over views of weight(u)
    novelty(u)   = share(u, pick) * prod over captured v of (1 - share(u, v))

- share(u, v) in [0, 1]: the part of u's footprint in v's image not hidden by what lies in
  front (`Visibility.visible_share`); 0 when v does not list u (outside the image, fully
  hidden, or not among the ELEMENTS_PER_PIXEL heaviest elements of any pixel);
- coverage counts views' worth of unhidden sight (0: no captured view saw u);
- fragility is the mean zeta of the pixels u fills, weighted by how much of each pixel it
  makes, over the captured views and the pick (NaN where no view shows u): high where the
  model's answer would change if parts of it were missing;
- novelty is how much of u the pick shows that no captured view showed.

Every view is measured under the same N sub-models (one mask draw from `seed`), one view at a
time, so memory holds one view's Visibility and five [U] float64 sums.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import InputError
from ..executors import LOCAL, Executor
from ..renderers import DEFAULT_SIGNAL, Renderer
from ..renderers.visibility import Visibility, reports_visibility
from ..scene import Camera
from .sampling import Progress, ProgressTicker
from .uncertainty import uncertainty

EXPLAIN_UNIT_BYTES = 40     # the five [U] float64 sums an explanation holds while it runs


@dataclass
class Explanation:
    """Per element of the model (splats: its dropout units), float64 [U] each."""

    coverage: Tensor            # views' worth of unhidden sight by the captured views (0: never seen)
    fragility: Tensor           # weighted mean zeta on the pixels it fills; NaN where no view shows it
    novelty: Tensor | None      # what the pick shows of it that no captured view did (None: no pick)
    ratio: float
    samples: int
    views: int                  # captured views measured (the pick apart)


def explain(renderer: Renderer, captured: list[Camera], *, ratio: float, samples: int, seed: int = 0,
            pick: Camera | None = None, signal: str = DEFAULT_SIGNAL, progress: Progress | None = None,
            executor: Executor = LOCAL) -> Explanation:
    """Coverage, fragility and (with a pick) novelty of every element (module docstring)."""
    if not reports_visibility(renderer):
        raise InputError("model", f"a {renderer.kind} model does not report what a view sees of it")
    if not captured:
        raise InputError("captured", "no captured views: give the model's training cameras")
    units = renderer.num_units
    coverage, unseen = torch.zeros(units, dtype=torch.float64), torch.ones(units, dtype=torch.float64)
    weight, valued = torch.zeros(units, dtype=torch.float64), torch.zeros(units, dtype=torch.float64)
    novelty = None
    views = captured + ([pick] if pick is not None else [])
    ticker = ProgressTicker(progress, len(views))
    for k, camera in enumerate(views):
        (measured,) = uncertainty(renderer, [camera], ratio=ratio, samples=samples, seed=seed,
                                  keep_visibility=True, signal=signal, executor=executor)
        vis = _elements_of(measured.visibility, units)
        weight.index_add_(0, vis.elements, vis.weight)
        valued.index_add_(0, vis.elements, vis.valued if vis.valued is not None else torch.zeros_like(vis.weight))
        share = vis.visible_share
        if k < len(captured):
            coverage.index_add_(0, vis.elements, share)
            unseen[vis.elements] *= 1.0 - share
        else:
            novelty = torch.zeros(units, dtype=torch.float64)
            novelty[vis.elements] = share
            novelty *= unseen
        ticker.tick(1)
    ticker.finish()
    fragility = torch.where(weight > 0, valued / weight.clamp_min(1e-300), torch.full_like(weight, float("nan")))
    return Explanation(coverage=coverage, fragility=fragility, novelty=novelty, ratio=ratio, samples=samples,
                       views=len(captured))


def _elements_of(vis: Visibility | None, units: int) -> Visibility:
    """The view's Visibility, whose elements must be the model's dropout units."""
    if vis is None:
        raise InputError("model", "the model reported no visibility for a view")
    if len(vis.elements) and int(vis.elements.max()) >= units:
        raise InputError("model", "its coverage elements are not its dropout units (no per-unit explanation)")
    return vis
