"""The coverage strategies' bookkeeping: what each candidate would show that no view counted
as captured saw from a nearby direction (`Coverage`), in compiled passes.

The quantities are defined in `strategies.visibility` (novelty, seen share, the direction kernel
`near`); the coverage strategies there and the target gain of `strategies.targets` build on this
module, which imports neither.
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ...renderers.visibility import Seen, Visibility

SEEN_SHARE = 0.25        # visible share at which a captured view counts as having seen an element
ANGLE_SCALE = 0.5        # 1 - cos(angle) at which `near` falls to 1/e (60 degrees)
SUPPORT = 1.0            # the share of an element's novelty one view that fully saw it from the same direction removes
EMPTY_WEIGHT = 0.1       # a pixel of empty box against a pixel of unseen model (0.5 lost 1.1 dB on lego, docs/nbv.md)


def near(a: Tensor, b: Tensor, scale: float = ANGLE_SCALE) -> Tensor:
    """[K] similarity of unit directions a, b [K, 3] (or b [3]): 1 when equal, falling with the angle."""
    return torch.exp(-(1.0 - (a * b).sum(-1)) / scale)


def directions(points: Tensor, camera_centre: Tensor) -> Tensor:
    """[K, 3] unit directions from points [K, 3] to a camera centre [3]."""
    d = camera_centre - points
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def viewing_axis(vis: Visibility | Seen) -> Tensor:
    """[3] float64 the direction the camera looks along (OpenGL: -z)."""
    return -vis.camera.c2w[:3, 2].double()


CAPTURE_CHUNK = 1 << 16          # (element, view) pairs, then entry x pair products, a capture handles at once (~10 MB)
CAPTURE_VIEW_ELEMENTS = 1 << 19  # listed elements of the views a capture reads at once (~8 MB)


class Coverage:
    """The candidates' novelty, conditioned on every view counted as captured so far.

    The elements of the candidates still in play sit in one list of entries ordered by element
    (those of union element u at first[u]:first[u + 1], one per candidate that lists u): `index`
    into the union of all their elements, the direction from each element to the candidate's
    camera, its weight (pixels it fills times its fragility), its novelty and its candidate
    (`owner`); a candidate's entries are at `where[c]`, ascending. Counting views as captured
    goes element by element: each entry's novelty is multiplied by the factors of every view that
    saw its element, in the views' order (the same products in the same order as counting one
    view at a time, which walked every entry once per view, out of cache). A candidate's value is
    summed again only when it is asked for after a capture changed it (`updates` counts those
    sums): a lazy greedy asks for few. A candidate `retire`d (picked) leaves the list once half of
    it is retired.
    """

    def __init__(self, candidates: list[Visibility], fragility: bool, angle_scale: float = ANGLE_SCALE,
                 support: float = SUPPORT):
        self.angle_scale = angle_scale
        self.support = support
        self.union = torch.unique(torch.cat([v.elements for v in candidates]))
        self.size = len(self.union)
        self.points = torch.zeros(self.size, 3, dtype=torch.float64)                  # [U, 3]
        counts = torch.tensor([len(v.elements) for v in candidates], dtype=torch.long)
        offsets = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)])     # [C + 1]
        total = int(offsets[-1])
        index = torch.empty(total, dtype=torch.long)
        dirs = torch.empty(total, 3, dtype=torch.float64)
        weight = torch.empty(total, dtype=torch.float64)
        reference = mean_zeta(candidates) if fragility else 0.0
        for c, vis in enumerate(candidates):
            part = slice(int(offsets[c]), int(offsets[c + 1]))
            index[part] = torch.searchsorted(self.union, vis.elements)
            self.points[index[part]] = vis.points
            dirs[part] = directions(vis.points, vis.camera.center)
            weight[part] = vis.weight
            if fragility and reference > 0 and vis.valued is not None:
                weight[part] *= 1.0 + vis.valued / vis.weight.clamp_min(1e-300) / reference
        order = stable_order(index, self.size)             # by element, then candidate
        self.index = index[order]                                                    # [S]
        del index                                          # each list by candidate goes once it is reordered
        self.dirs = dirs[order]                                                      # [S, 3]
        del dirs
        self.weight = weight[order]                                                  # [S]
        del weight
        self.owner = torch.repeat_interleave(torch.arange(len(candidates)), counts)[order]   # [S]
        self.novelty = torch.ones(total, dtype=torch.float64)                        # [S]
        self.ids = list(range(len(candidates)))           # the candidates with entries in the list
        self.retired: set[int] = set()
        self.empty = [vis.empty for vis in candidates]
        self.axes = torch.stack([viewing_axis(vis) for vis in candidates])            # [C, 3]
        self.axis_novelty = [1.0] * len(candidates)
        self.sums = [0.0] * len(candidates)
        self.changed = torch.ones(len(candidates), dtype=torch.bool)   # sums[c] is out of date
        self.updates = 0                                  # candidate sums computed
        self._locate()

    def _locate(self) -> None:
        """first[u]: where element u's run starts; where[c]: candidate c's entries, ascending."""
        self.first = torch.zeros(self.size + 1, dtype=torch.long)                      # [U + 1]
        torch.cumsum(torch.bincount(self.index, minlength=self.size), 0, out=self.first[1:])
        by_owner = stable_order(self.owner, len(self.changed))
        counts = torch.bincount(self.owner, minlength=len(self.changed)).tolist()
        self.where = dict(zip(range(len(counts)), by_owner.split(counts)))

    def _sum(self, c: int) -> float:
        """Candidate c's weight times novelty summed over its elements, summed again if a capture changed it."""
        if self.changed[c]:
            part = self.where[c]
            terms = np.empty(len(part))
            _products(part.numpy(), self.weight.numpy(), self.novelty.numpy(), terms)
            self.sums[c] = float(torch.from_numpy(terms).sum())          # torch's sum, as always
            self.changed[c] = False
            self.updates += 1
        return self.sums[c]

    def value(self, c: int) -> float:
        """What candidate c would show that no view counted as captured saw (module docstring)."""
        return self._sum(c) + EMPTY_WEIGHT * self.empty[c] * self.axis_novelty[c]

    def share(self, c: int) -> float:
        """The share of candidate c's image of the model left unseen (0 when it shows none)."""
        total = float(self.weight[self.where[c]].sum())
        return self._sum(c) / total if total > 0 else 0.0

    def capture(self, *views: Visibility | Seen) -> None:
        """Count `views` as captured, in order: every candidate's novelty of the elements they saw falls."""
        start = 0
        while start < len(views):     # consecutive views of at most CAPTURE_VIEW_ELEMENTS elements (or one view)
            stop, listed = start + 1, len(views[start].elements)
            while stop < len(views) and listed + len(views[stop].elements) <= CAPTURE_VIEW_ELEMENTS:
                listed += len(views[stop].elements)
                stop += 1
            if self.size:
                self._capture_views(views[start:stop])
            start = stop
        for vis in views:
            axis_near = near(self.axes, viewing_axis(vis), self.angle_scale).tolist()
            self.axis_novelty = [n * (1.0 - a) for n, a in zip(self.axis_novelty, axis_near)]

    def _capture_views(self, views: Sequence[Visibility | Seen]) -> None:
        """The novelty update of some consecutive views, by chunks of union elements that hold at
        most CAPTURE_CHUNK (element, view) pairs (or one element)."""
        ids = torch.cat([v.elements for v in views]).long().numpy()                  # [K] each view's ascending
        visible = torch.cat([v.visible_share for v in views]).double().numpy()       # [K]
        view_ptr = np.cumsum([0] + [len(v.elements) for v in views])                 # [V + 1]
        counts = np.zeros(self.size, dtype=np.int64)             # [U] views that saw each union element
        _count_pairs(self.union.numpy(), ids, visible, view_ptr, counts)
        centres = torch.stack([v.camera.center.double() for v in views])             # [V, 3]
        resume = view_ptr[:-1].copy()                            # where each view's walk goes on
        ends = np.cumsum(counts)
        begin = 0
        while begin < self.size:
            done = int(ends[begin - 1]) if begin else 0
            end = max(begin + 1, int(np.searchsorted(ends, done + CAPTURE_CHUNK, side="right")))
            self._capture_chunk(ids, visible, view_ptr, centres, begin, end, counts[begin:end], resume)
            begin = end

    def _capture_chunk(self, ids: np.ndarray, visible: np.ndarray, view_ptr: np.ndarray, centres: Tensor,
                       begin: int, end: int, counts: np.ndarray, resume: np.ndarray) -> None:
        """The novelty update for union elements begin..end-1 ([end - begin] pairs each in `counts`):
        their (element, view) pairs grouped by element in the views' order, then each entry times
        (1 - seen share * near) for each pair, compiled except the exp, which is torch's as
        everywhere else in the coverage."""
        ptr = np.zeros(end - begin + 1, dtype=np.int64)                             # [E + 1]
        np.cumsum(counts, out=ptr[1:])
        view = np.empty(int(ptr[-1]), dtype=np.int64)                               # [P]
        share = np.empty(int(ptr[-1]))                                              # [P]
        _gather_pairs(self.union.numpy(), ids, visible, view_ptr, begin, end, resume, ptr, view, share, self.support)
        element = torch.repeat_interleave(torch.arange(begin, end), torch.from_numpy(counts))
        toward = directions(self.points[element], centres[torch.from_numpy(view)]).T.contiguous().numpy()  # [3, P]
        room = max(CAPTURE_CHUNK, len(self.ids))      # an element has at most one entry per candidate
        exponent = np.empty(room)
        scratch = np.empty((3, len(self.ids)))
        first, dirs = self.first.numpy(), self.dirs.numpy()
        u, q = begin, 0
        while u < end:
            stop_u, stop_q, count = _exponents(begin, end, ptr, toward, first, dirs, self.angle_scale, u, q, exponent,
                                                 scratch)
            similar = torch.exp(torch.from_numpy(exponent[:count])).numpy()           # near(), in torch
            _lower(begin, u, q, stop_u, stop_q, ptr, share, first, similar, self.novelty.numpy(),
                   self.owner.numpy(), self.changed.numpy())
            u, q = stop_u, stop_q

    def retire(self, c: int) -> None:
        """Candidate c is out of play (picked): its value is no longer needed. Once half of the
        stored entries are retired candidates', they leave the list (each capture after costs less)."""
        self.retired.add(c)
        if 2 * sum(len(self.where[i]) for i in self.retired) <= len(self.index):
            return
        gone = torch.zeros(len(self.changed), dtype=torch.bool)
        gone[list(self.retired)] = True
        keep = ~gone[self.owner]
        self.index = self.index[keep]             # one array at a time: at most half of one is copied at once
        self.dirs = self.dirs[keep]
        self.weight = self.weight[keep]
        self.novelty = self.novelty[keep]
        self.owner = self.owner[keep]
        self.ids = [i for i in self.ids if i not in self.retired]
        self._locate()


def stable_order(keys: Tensor, size: int) -> Tensor:
    """[K] long: the order that sorts keys [K] (ints in [0, size)) stably, as
    torch.argsort(keys, stable=True) does, by counting (linear in K + size)."""
    order = np.empty(len(keys), dtype=np.int64)
    _counting_order(keys.numpy(), size, order)
    return torch.from_numpy(order)


@numba.njit(cache=True, nogil=True)
def _counting_order(keys, size, order):  # pragma: no cover
    """order: where each place of the sorted list takes its key from (a stable counting sort)."""
    start = np.zeros(size + 1, dtype=np.int64)
    for k in keys:
        start[k + 1] += 1
    for i in range(size):
        start[i + 1] += start[i]
    for i in range(len(keys)):
        order[start[keys[i]]] = i
        start[keys[i]] += 1


@numba.njit(cache=True, nogil=True)
def _products(part, weight, novelty, terms):  # pragma: no cover
    """terms[i] = weight[part[i]] * novelty[part[i]]: a candidate's terms, gathered in one pass."""
    for i in range(len(part)):
        terms[i] = weight[part[i]] * novelty[part[i]]


@numba.njit(cache=True, nogil=True)
def _count_pairs(union, ids, visible, view_ptr, counts):  # pragma: no cover
    """counts[u] += 1 for each view (its ascending ids[view_ptr[j]:view_ptr[j + 1]], and their
    visible shares) that saw union element u with a share above 0, by a merge of two ascending lists."""
    for j in range(len(view_ptr) - 1):
        u = 0
        for i in range(view_ptr[j], view_ptr[j + 1]):
            while u < len(union) and union[u] < ids[i]:
                u += 1
            if u == len(union):
                break
            if union[u] == ids[i] and visible[i] > 0:
                counts[u] += 1


@numba.njit(cache=True, nogil=True)
def _gather_pairs(union, ids, visible, view_ptr, begin, end, resume, ptr, view, share, support):  # pragma: no cover
    """The (element, view) pairs of union elements begin..end-1, grouped by element (element
    begin + i's at ptr[i]:ptr[i + 1]), the views in order: the view and its seen share,
    support * min(1, visible share / SEEN_SHARE) as `seen_share`. resume[j]: where view j's ids are read
    on from (the chunks come in order)."""
    fill = ptr[:-1].copy()
    last = union[end - 1]
    for j in range(len(view_ptr) - 1):
        i, u = resume[j], begin
        while i < view_ptr[j + 1] and ids[i] <= last:
            while union[u] < ids[i]:
                u += 1
            if union[u] == ids[i] and visible[i] > 0:
                k = fill[u - begin]
                view[k] = j
                share[k] = support * min(visible[i] / SEEN_SHARE, 1.0)
                fill[u - begin] = k + 1
            i += 1
        resume[j] = i


@numba.njit(cache=True, nogil=True)
def _exponents(begin, end, ptr, toward, first, dirs, scale, u, q, exponent, scratch):  # pragma: no cover
    """From union element u's pair q on, while the buffer holds them: near()'s exponent,
    -(1 - dir . toward) / scale (the same float operations as `near`), for each of the
    element's pairs in order against each of its entries. Returns the element and pair it
    stopped at and the exponents listed. (The loops run over contiguous slices with the
    loop-invariant values in registers, which the compiler turns into vector instructions;
    scratch [3, R], R at least any element's entries, holds an element's directions by axis.)"""
    m = 0
    while u < end:
        run = first[u + 1] - first[u]
        p0, p1 = ptr[u - begin], ptr[u - begin + 1]
        if run == 0 or p0 == p1:
            u, q = u + 1, 0
            continue
        fit = (len(exponent) - m) // run
        if fit == 0:
            break
        stop = min(p1, p0 + q + fit)
        x, y, z = scratch[0, :run], scratch[1, :run], scratch[2, :run]      # the entries' directions
        for e in range(run):
            x[e], y[e], z[e] = dirs[first[u] + e, 0], dirs[first[u] + e, 1], dirs[first[u] + e, 2]
        for p in range(p0 + q, stop):
            tx, ty, tz = toward[0, p], toward[1, p], toward[2, p]
            out = exponent[m:m + run]
            for e in range(run):
                out[e] = -(1.0 - (x[e] * tx + y[e] * ty + z[e] * tz)) / scale
            m += run
        if stop < p1:
            q = stop - p0
            break
        u, q = u + 1, 0
    return u, q, m


@numba.njit(cache=True, nogil=True)
def _lower(begin, u, q, stop_u, stop_q, ptr, share, first, similar, novelty, owner, changed):  # pragma: no cover
    """The walk `_exponents` made from (u, q) to (stop_u, stop_q): for each pair in order, every
    entry of its element times (1 - seen share * near), the entries' candidates marked changed."""
    m = 0
    while u < stop_u or (u == stop_u and q < stop_q):
        p0, p1 = ptr[u - begin], ptr[u - begin + 1]
        stop = p1 if u < stop_u else p0 + stop_q
        run = first[u + 1] - first[u]
        if run and stop > p0 + q:
            entries = novelty[first[u]:first[u + 1]]
            for p in range(p0 + q, stop):
                seen = share[p]
                near = similar[m:m + run]
                for e in range(run):
                    entries[e] *= 1.0 - seen * near[e]
                m += run
            for e in range(first[u], first[u + 1]):
                changed[owner[e]] = True
        u, q = u + 1, 0


def seen_share(vis: Visibility | Seen, support: float = SUPPORT) -> Tensor:
    """[K] how fully the view saw each of its elements: support * min(1, visible share / SEEN_SHARE)."""
    return support * (vis.visible_share / SEEN_SHARE).clamp_max(1.0)


def mean_zeta(views: list[Visibility]) -> float:
    """Mean zeta per pixel of model weight over every candidate (the fragility scale)."""
    valued = sum(float(v.valued.sum()) for v in views if v.valued is not None)
    weight = sum(float(v.weight.sum()) for v in views if v.valued is not None)
    return valued / weight if weight > 0 else 0.0
