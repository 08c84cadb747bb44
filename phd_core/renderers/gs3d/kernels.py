"""Stages 2 and 3 of the 3DGS rasteriser compiled with numba, for renders without gradients.

Same rules as the torch stages (`phd_core.renderers.splats.intersect`, `render.splat_alpha`,
`splats.fragments`): a splat is listed in every tile its alpha >= 1/255 box overlaps, in
depth order; at every pixel of the tile alpha = min(ALPHA_MAX, opacity * exp(-d^T conic d / 2))
is evaluated (in float64) and kept when >= ALPHA_MIN. The output is the fused compositor's
layout: fragments grouped by pixel over ALL T * P pixels of the tile grid (pixels outside
the image have none), front to back within a pixel, each naming its projected splat.
Tiles are spread over the cores.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ..composite.fused import LAUNCH_LOCK
from ..splats import ALPHA_MAX, ALPHA_MIN, tile_boxes


@numba.njit(cache=True, nogil=True)
def _tile_lists(lo, hi, tiles_x, num_tiles):  # pragma: no cover
    """Pairs ordered by (tile, depth): (start [T + 1] int64, splat [M] int32). The splats
    arrive front to back, so appending them tile by tile keeps depth order."""
    start = np.zeros(num_tiles + 1, np.int64)
    for v in range(lo.shape[0]):
        for ty in range(lo[v, 1], hi[v, 1] + 1):
            for tx in range(lo[v, 0], hi[v, 0] + 1):
                start[ty * tiles_x + tx + 1] += 1
    start = np.cumsum(start)
    fill = start[:-1].copy()
    splat = np.empty(start[-1], np.int32)
    for v in range(lo.shape[0]):
        for ty in range(lo[v, 1], hi[v, 1] + 1):
            for tx in range(lo[v, 0], hi[v, 0] + 1):
                t = ty * tiles_x + tx
                splat[fill[t]] = v
                fill[t] += 1
    return start, splat


@numba.njit(inline="always")
def _alpha(means2d, conics, opacities, v, px, py):  # pragma: no cover
    dx = px + 0.5 - means2d[v, 0]
    dy = py + 0.5 - means2d[v, 1]
    power = -0.5 * (conics[v, 0] * dx * dx + conics[v, 2] * dy * dy) - conics[v, 1] * dx * dy
    return min(ALPHA_MAX, opacities[v] * math.exp(power))


@numba.njit(parallel=True, cache=True, nogil=True)
def _fragments(start, splat, means2d, conics, opacities, tiles_x, tile, width, height, row_ptr, alpha, index,
               fill):  # pragma: no cover
    """fill=False: row_ptr[1 + pixel] = number of fragments of the pixel (T * P pixels, tile layout).
    fill=True: write alpha [E] and index [E] at the offsets row_ptr gives."""
    pixels = tile * tile
    for t in numba.prange(start.shape[0] - 1):
        x0 = (t % tiles_x) * tile
        y0 = (t // tiles_x) * tile
        cols = min(tile, width - x0)
        rows = min(tile, height - y0)
        count = np.zeros(pixels, np.int64)
        for k in range(start[t], start[t + 1]):
            v = splat[k]
            for oy in range(rows):
                for ox in range(cols):
                    a = _alpha(means2d, conics, opacities, v, x0 + ox, y0 + oy)
                    if a >= ALPHA_MIN:
                        p = oy * tile + ox
                        if fill:
                            e = row_ptr[t * pixels + p] + count[p]
                            alpha[e] = a
                            index[e] = v
                        count[p] += 1
        if not fill:
            for p in range(pixels):
                row_ptr[1 + t * pixels + p] = count[p]


def splat_fragments(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, extents: torch.Tensor,
                    width: int, height: int, tile: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, int]:
    """Stages 2 and 3 for V projected splats in front-to-back order (means2d [V, 2], conics
    [V, 3], opacities [V], extents [V, 2], float64).

    Returns (row_ptr [T * P + 1] int64, alpha [E] float32, index [E] int32 into the V splats,
    tiles_x, tiles_y); the fragments of pixel q (tile layout) are row_ptr[q]:row_ptr[q + 1].
    """
    lo, hi, tiles_x, tiles_y = tile_boxes(means2d, extents, width, height, tile)
    num_pixels = tiles_x * tiles_y * tile * tile
    geometry = [t.detach().double().contiguous().numpy() for t in (means2d, conics, opacities)]
    with LAUNCH_LOCK:
        start, splat = _tile_lists(lo.numpy(), hi.numpy(), tiles_x, tiles_x * tiles_y)
        row_ptr = np.zeros(num_pixels + 1, np.int64)
        no_alpha, no_index = np.empty(0, np.float32), np.empty(0, np.int32)
        _fragments(start, splat, *geometry, tiles_x, tile, width, height, row_ptr, no_alpha, no_index, False)
        np.cumsum(row_ptr, out=row_ptr)
        alpha = np.empty(row_ptr[-1], np.float32)
        index = np.empty(row_ptr[-1], np.int32)
        _fragments(start, splat, *geometry, tiles_x, tile, width, height, row_ptr, alpha, index, True)
    return torch.from_numpy(row_ptr), torch.from_numpy(alpha), torch.from_numpy(index), tiles_x, tiles_y
