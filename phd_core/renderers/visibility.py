"""What one camera sees of a model: per coverage element, how much of the image it fills.

Next-best-view strategies that reason from the model (`phd_core.uq.strategies.visibility`)
need, for each captured or candidate view, which parts of the model the view actually sees,
occlusion included. One render of the full model gives it: an element's compositing weight
(alpha times the transmittance in front of it) summed over the pixels. A family that can
say this implements `Renderer.visibility(view, pixel_values=None) -> Visibility`; its
coverage elements are its splats (3DGS, 2DGS) or its occupancy-grid cells (NeRF). The pass
reads the view the camera's masked renders use: the splat families' fragment lists, NeRF's
densities gathered by those renders (`prepare_seeing`), so it renders nothing of its own.

`fragment_visibility` is the sum for any renderer that composites per-pixel lists of
fragments front to back (the splat families), with the compositors' rules: transmittance
in float64 log space, and a pixel stops at the fragment that would bring it below T_MIN.
It is one compiled pass holding nothing per fragment; `fragment_visibility_reference` is
its pure-torch twin (tested to agree), which holds ~9 float64 arrays per fragment (0.9 GB
for the 7M fragments of a 1M-splat model at 200x150).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, TypeGuard

import numba
import numpy as np
import torch
from torch import Tensor

from ..scene import Camera
from .protocol import Renderer, View
from .splats.maths import LOG_T_MIN

ELEMENTS_PER_PIXEL = 4     # a Visibility lists at most this many elements per image pixel


@dataclass
class Visibility:
    """One render of the full model from `camera`, reduced to the coverage elements it shows.

    Only the K elements with a weight are listed (`reduce_to_visibility`). weight / footprint
    is the share of an element that is not hidden (1: nothing in front of it, near 0: mostly
    occluded).
    """

    camera: Camera
    elements: Tensor          # [K] long, element ids (splats; NeRF: occupancy cells), ascending
    points: Tensor            # [K, 3] float64 world position of each element
    weight: Tensor            # [K] float64 sum over pixels of alpha * transmittance (pixels it fills)
    footprint: Tensor         # [K] float64 sum over pixels of alpha, occlusion ignored
    valued: Tensor | None     # [K] float64 sum over pixels of alpha * transmittance * pixel value, when given
    empty: float              # transmittance left at the end of the rays that cross the scene box, summed
    in_box: int               # pixels whose ray crosses the scene box

    @property
    def visible_share(self) -> Tensor:
        """[K] float64 in [0, 1]: how much of each element's footprint is not hidden."""
        return (self.weight / self.footprint.clamp_min(1e-300)).clamp(0.0, 1.0)

    def seen(self) -> "Seen":
        """What a captured view's coverage needs of it (`Seen`)."""
        return Seen(camera=self.camera, elements=self.elements, visible_share=self.visible_share)


@dataclass
class Seen:
    """What a captured view saw, as far as the coverage strategies use it: which elements it
    shows and how much of each is not hidden (`Visibility.visible_share`). SEEN_ELEMENT_BYTES
    an element instead of a Visibility's KEPT_ELEMENT_BYTES; what a model's captured views saw
    is stored in this form (`phd_core.uq.strategies.captured`)."""

    camera: Camera
    elements: Tensor          # [K] long, element ids, ascending
    visible_share: Tensor     # [K] float64 in [0, 1]


# What a visibility pass holds (a memory plan adds it to the view's render bounds), in bytes:
# nothing per fragment (`fragment_visibility` walks the lists the renders use in place); per unit of the model,
# the three float64 sums, summed by listed unit (at most one a unit: 3 x 8) and spread to the
# model's (3 x 8), and what `reduce_to_visibility` gathers of them (ids, points: 8 + 24); and
# what a Visibility keeps per element it lists (ids, points, weight, footprint, valued: 8 + 24 + 3 x 8).
PASS_UNIT_BYTES = 80
KEPT_ELEMENT_BYTES = 56
SEEN_ELEMENT_BYTES = 16
# A strategy's working copy of a candidate's element (`phd_core.uq.strategies.coverage.Coverage`):
# index, direction, weight, novelty, owner and its place in the by-element list (8 + 24 + 4 x 8), and
# per element of the union (at most every listed element) its id, point and first entry (8 + 24 + 8)
# and either the sort that lists entries by element (16, while the list is made) or the number of
# views a capture counts for the element and their running sum (16, while views are counted): 120.
# Counting views as captured reads at most CAPTURE_VIEW_ELEMENTS of their listed elements at once (ids
# and shares: 8 MB) and works on at most CAPTURE_CHUNK (element, view) pairs (their views, shares,
# points, camera centres and directions: 10 MB) and as many entry-by-pair products (1 MB) at once:
# COVERAGE_CAPTURE_BYTES whatever the views.
COVERAGE_ELEMENT_BYTES = 120
COVERAGE_CAPTURE_BYTES = 20 << 20
# A captured view's Seen keeps ids and shares (8 + 8); stored, they take 12 bytes an element.
# Reading a stored view holds the file's bytes, the tensors read and the ids widened (12 + 12 + 8):
# SEEN_LOADED_BYTES an element of a stored view. A rank that also writes a view holds, beside the
# kept views, its tensors narrowed, the serialised bytes and their copy (12 x 3): SEEN_STORED_BYTES
# an element of every view it stores (at most: the views are written one by one).
SEEN_LOADED_BYTES = 32
SEEN_STORED_BYTES = 56


def listed_elements(num_units: int, camera: Camera) -> int:
    """The most elements a view's Visibility lists: ELEMENTS_PER_PIXEL a pixel, at most the model's units."""
    return min(num_units, ELEMENTS_PER_PIXEL * camera.width * camera.height)


def visibility_bytes(num_units: int, camera: Camera) -> int:
    """The most one view's Visibility and a strategy's copy of it hold."""
    return (KEPT_ELEMENT_BYTES + COVERAGE_ELEMENT_BYTES) * listed_elements(num_units, camera)


def seen_bytes(num_units: int, cameras: Sequence[Camera]) -> int:
    """The most the captured views a rank renders hold: each one's Seen, kept and stored, and one
    Visibility at a time while it is reduced to its Seen."""
    listed = [listed_elements(num_units, camera) for camera in cameras]
    return SEEN_STORED_BYTES * sum(listed) + KEPT_ELEMENT_BYTES * max(listed, default=0)


class ReportsVisibility(Renderer, Protocol):
    """A Renderer whose family also reports what a view sees of the model (for type checking:
    `reports_visibility` tells one apart)."""

    def visibility(self, view: View, pixel_values: Tensor | None = None) -> Visibility:
        ...


def reports_visibility(renderer: object) -> TypeGuard[ReportsVisibility]:
    """True when the renderer's family implements `visibility(view, pixel_values=None)`."""
    return callable(getattr(renderer, "visibility", None))


def prepare_seeing(renderer: Renderer, camera: Camera) -> View:
    """`renderer.prepare(camera)` for a view that will be asked what it sees (`visibility`) after
    its masked renders. A family whose renders can gather that on the way says so with its own
    `prepare_seeing` (NeRF: the full model's densities from the samples and first layer its
    masks share); the splat families' pass walks the prepared view's lists, so `prepare` serves."""
    seeing = getattr(renderer, "prepare_seeing", None)
    return seeing(camera) if callable(seeing) else renderer.prepare(camera)


@dataclass
class FragmentSums:
    """Per-element and per-pixel sums of one front-to-back compositing of the full model."""

    weight: Tensor            # [U] float64 alpha * transmittance summed per element
    footprint: Tensor         # [U] float64 alpha summed per element
    valued: Tensor | None     # [U] float64 weight * pixel value summed per element
    left: Tensor              # [S] float64 transmittance at the end of each row's fragments


def fragment_visibility(row_ptr: Tensor, alpha: Tensor, index: Tensor, units: Tensor, num_elements: int,
                        row_values: Tensor | None = None) -> FragmentSums:
    """Sum compositing weights per element over S pixel rows of fragments, in one compiled pass.

    row_ptr [S + 1]: the fragments of row s are row_ptr[s]:row_ptr[s + 1], front to back;
    alpha [E]; fragment e belongs to element units[index[e]] (index [E] of any integer type,
    units [V] long in [0, num_elements)): the lists a prepared view keeps, walked in place, with
    no per-fragment array made for the pass; row_values [S] (e.g. zeta) or None.
    """
    # Sums by listed unit when the view lists no more units than the model has (3DGS: its visible
    # splats, so the sums stay in cache), spread to the model's at the end (added, as 2DGS lists
    # a surfel once per tile pair); else (many pairs) straight by element, in bounded memory.
    units = units.long()
    by_unit = len(units) <= num_elements
    size = len(units) if by_unit else num_elements
    weight, footprint = np.zeros(size), np.zeros(size)
    valued = np.zeros(size if row_values is not None else 0)
    left = np.empty(len(row_ptr) - 1)
    values = (row_values.double().contiguous().numpy() if row_values is not None else np.zeros(0))
    _visibility_kernel(row_ptr.long().contiguous().numpy(), alpha.detach().contiguous().numpy(),
                       index.contiguous().numpy(), units.numpy(), by_unit, values, weight, footprint, valued, left)

    def spread(sums: np.ndarray) -> Tensor:     # distinct units land unchanged, bit for bit
        out = torch.from_numpy(sums)
        return torch.zeros(num_elements, dtype=torch.float64).index_add_(0, units, out) if by_unit else out
    return FragmentSums(weight=spread(weight), footprint=spread(footprint),
                        valued=None if row_values is None else spread(valued), left=torch.from_numpy(left))


@numba.njit(cache=True, nogil=True)
def _visibility_kernel(row_ptr, alpha, index, units, by_unit, row_values, weight, footprint, valued,
                       left):  # pragma: no cover
    """Per row, front to back: every fragment adds its alpha to its unit's footprint; until
    the fragment that would bring the row's transmittance below T_MIN, it adds alpha times the
    transmittance in front of it to the weight (and times row_values[s] to valued, when given).
    Fragment e's sums go to index[e] (by_unit) or to its element units[index[e]]. left[s]: the
    row's transmittance after its used fragments. Serial: rows share units."""
    with_values = len(row_values) > 0
    for s in range(len(row_ptr) - 1):
        log_t = 0.0
        used = True
        for e in range(row_ptr[s], row_ptr[s + 1]):
            a = np.float64(alpha[e])
            u = index[e] if by_unit else units[index[e]]
            footprint[u] += a
            if used:
                after = log_t + np.log1p(-a)
                if after >= LOG_T_MIN:
                    w = a * np.exp(log_t)
                    weight[u] += w
                    if with_values:
                        valued[u] += w * row_values[s]
                    log_t = after
                else:
                    used = False
        left[s] = np.exp(log_t)


def fragment_visibility_reference(row_ptr: Tensor, alpha: Tensor, index: Tensor, units: Tensor, num_elements: int,
                                  row_values: Tensor | None = None) -> FragmentSums:
    """`fragment_visibility` in pure torch (its tested twin): the same sums by cumulative sums."""
    element = units.long()[index.long()]                                       # [E]
    alpha = alpha.double()
    counts = row_ptr[1:] - row_ptr[:-1]                                        # [S]
    row = torch.repeat_interleave(torch.arange(len(counts)), counts)          # [E] the row of each fragment
    log_1ma = torch.log1p(-alpha)
    inclusive = torch.cumsum(log_1ma, 0)
    exclusive = inclusive - log_1ma
    first = row_ptr[:-1].clamp_max(max(len(alpha) - 1, 0))
    base = exclusive[first][row] if len(alpha) else exclusive                  # log T before each row's first fragment
    used = inclusive - base >= LOG_T_MIN                                       # the stop rule of the compositors
    weight = torch.where(used, alpha * (exclusive - base).exp(), torch.zeros_like(alpha))   # [E]
    zeros = torch.zeros(num_elements, dtype=torch.float64)
    per_row_log = torch.zeros(len(counts), dtype=torch.float64).index_add_(0, row, torch.where(used, log_1ma, 0.0))
    return FragmentSums(weight=zeros.clone().index_add_(0, element, weight),
                        footprint=zeros.clone().index_add_(0, element, alpha),
                        valued=None if row_values is None else
                        zeros.clone().index_add_(0, element, weight * row_values.double()[row]),
                        left=per_row_log.exp())


def reduce_to_visibility(camera: Camera, sums: FragmentSums, points: Tensor, row_in_box: Tensor,
                         in_box: int) -> Visibility:
    """The elements the view shows (points [U, 3] of all elements), and the transmittance left
    on the in_box pixels whose rays cross the scene box (row_in_box [S]: which rows are such
    pixels; a pixel with no row has nothing on it, transmittance 1).

    Only elements with a weight are listed, at most ELEMENTS_PER_PIXEL per pixel of the image
    (the heaviest): fully hidden elements change no strategy's answer, and the bound makes a
    Visibility's size known from the image size alone (`visibility_bytes`)."""
    seen = (sums.weight > 0).nonzero().squeeze(1)
    limit = ELEMENTS_PER_PIXEL * camera.width * camera.height
    if len(seen) > limit:
        seen = seen[sums.weight[seen].topk(limit).indices].sort().values
    covered = float((1.0 - sums.left)[row_in_box].sum())
    return Visibility(camera=camera, elements=seen, points=points[seen].double(), weight=sums.weight[seen],
                      footprint=sums.footprint[seen],
                      valued=None if sums.valued is None else sums.valued[seen],
                      empty=max(0.0, in_box - covered), in_box=in_box)


def robust_box(points: Tensor, share: float = 0.005, margin: float = 0.05) -> tuple[Tensor, Tensor]:
    """The box [lo, hi] (float64 [3] each) holding all but `share` of points [P, 3] on each side
    of each axis (a few far floaters do not stretch it), widened by `margin` of its size."""
    points = points.double()
    count = len(points)
    if count == 0:
        zero = torch.zeros(3, dtype=torch.float64)
        return zero, zero
    k = int(share * count)
    lo = points.kthvalue(k + 1, dim=0).values
    hi = points.kthvalue(count - k, dim=0).values
    pad = (hi - lo) * margin
    return lo - pad, hi + pad
