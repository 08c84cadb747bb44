"""Stages 1-3 of the 3DGS rasteriser compiled with numba, for renders without gradients.

Stage 1 (`project_splats`) is the EWA projection of `render.project`, one splat per loop
step in float64 instead of a dozen [G, 3, 3] torch temporaries. Stages 2-3 follow the same
rules as the torch stages (`phd_core.renderers.splats.maths.intersect`, `render.splat_alpha`,
`splats.fragments`): a splat is listed in every tile its alpha >= 1/255 box overlaps, in
depth order; at every pixel of the tile alpha = min(ALPHA_MAX, opacity * exp(-d^T conic d / 2))
is kept when >= ALPHA_MIN (decided in float64; the kept alphas are one vectorised float32 exp).
The output is the fused compositor's layout: fragments grouped by pixel over ALL T * P pixels
of the tile grid (pixels outside the image have none), front to back within a pixel, each
naming its projected splat. Runs of splats, then tiles, are spread over the cores.

A render that knows its masks (none: the full model) needs less: `splat_fragments(...,
cut_for=...)` walks each tile's pairs front to back instead and ends a pixel's list after the
fragment where the transmittance of every one of those masks is spent, so the fragments behind
are neither evaluated nor listed (`_cut_log_alpha`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from ...scene import Camera
from ..splats.maths import ALPHA_MAX, ALPHA_MIN, LAUNCH_LOCK, LOG_T_MIN, SH_C0, SH_C1, SH_C2, SH_C3


@numba.njit(parallel=True, cache=True, nogil=True)
def _ewa(p_cam, quats, log_scales, opacity_logits, rot_wc, fx, fy, cx, cy, width, height, near, dilation,
         means2d, conics, opacities, extents, visible):  # pragma: no cover
    """Per splat: screen centre, inverse 2D covariance, opacity, alpha >= 1/255 box, culling."""
    lim_x_pos = (width - cx) / fx + 0.3 * width / (2 * fx)
    lim_x_neg = cx / fx + 0.3 * width / (2 * fx)
    lim_y_pos = (height - cy) / fy + 0.3 * height / (2 * fy)
    lim_y_neg = cy / fy + 0.3 * height / (2 * fy)
    for g in numba.prange(p_cam.shape[0]):
        x, y, depth = p_cam[g, 0], p_cam[g, 1], p_cam[g, 2]
        in_front = depth > near
        z = depth if in_front else 1.0
        means2d[g, 0] = fx * x / z + cx
        means2d[g, 1] = fy * y / z + cy
        tx = min(max(x / z, -lim_x_neg), lim_x_pos) * z
        ty = min(max(y / z, -lim_y_neg), lim_y_pos) * z
        j00, j02 = fx / z, -fx * tx / (z * z)
        j11, j12 = fy / z, -fy * ty / (z * z)
        # T = J W: [2, 3] (W the world-to-camera rotation)
        t00 = j00 * rot_wc[0, 0] + j02 * rot_wc[2, 0]
        t01 = j00 * rot_wc[0, 1] + j02 * rot_wc[2, 1]
        t02 = j00 * rot_wc[0, 2] + j02 * rot_wc[2, 2]
        t10 = j11 * rot_wc[1, 0] + j12 * rot_wc[2, 0]
        t11 = j11 * rot_wc[1, 1] + j12 * rot_wc[2, 1]
        t12 = j11 * rot_wc[1, 2] + j12 * rot_wc[2, 2]
        qw, qx, qy, qz = (np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]),
                          np.float64(quats[g, 3]))
        norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)
        s0 = math.exp(min(max(np.float64(log_scales[g, 0]), -30.0), 30.0))
        s1 = math.exp(min(max(np.float64(log_scales[g, 1]), -30.0), 30.0))
        s2 = math.exp(min(max(np.float64(log_scales[g, 2]), -30.0), 30.0))
        # U = T R S: [2, 3]; cov2d = U U^T
        u00 = (t00 * r00 + t01 * r10 + t02 * r20) * s0
        u01 = (t00 * r01 + t01 * r11 + t02 * r21) * s1
        u02 = (t00 * r02 + t01 * r12 + t02 * r22) * s2
        u10 = (t10 * r00 + t11 * r10 + t12 * r20) * s0
        u11 = (t10 * r01 + t11 * r11 + t12 * r21) * s1
        u12 = (t10 * r02 + t11 * r12 + t12 * r22) * s2
        a = u00 * u00 + u01 * u01 + u02 * u02 + dilation
        b = u00 * u10 + u01 * u11 + u02 * u12
        c = u10 * u10 + u11 * u11 + u12 * u12 + dilation
        det = max(a * c - b * b, 1e-30)
        conics[g, 0], conics[g, 1], conics[g, 2] = c / det, -b / det, a / det
        opacity = 1.0 / (1.0 + math.exp(-np.float64(opacity_logits[g])))
        opacities[g] = opacity
        level = 2.0 * math.log(max(opacity * 255.0, 1.0))
        ex, ey = math.sqrt(level * a), math.sqrt(level * c)
        extents[g, 0], extents[g, 1] = ex, ey
        on_screen = (means2d[g, 0] + ex > 0 and means2d[g, 1] + ey > 0 and means2d[g, 0] - ex < width
                     and means2d[g, 1] - ey < height)
        finite = np.isfinite(conics[g, 0]) and np.isfinite(conics[g, 1]) and np.isfinite(conics[g, 2])
        visible[g] = in_front and opacity * 255.0 > 1.0 and on_screen and finite


def project_splats(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                   opacity_logits: torch.Tensor, camera: Camera, near: float, dilation: float
                   ) -> tuple[torch.Tensor, ...]:
    """Stage 1 for all G splats: (means2d [G, 2], conics [G, 3], opacities [G], extents [G, 2],
    depths [G], visible [G] bool), float64, the same quantities as `render.project`."""
    p_cam = camera.to_camera(means.detach().double()).contiguous()
    g = p_cam.shape[0]
    means2d, conics, extents = torch.empty(g, 2, dtype=torch.float64), torch.empty(g, 3, dtype=torch.float64), \
        torch.empty(g, 2, dtype=torch.float64)
    opacities, visible = torch.empty(g, dtype=torch.float64), torch.empty(g, dtype=torch.bool)
    rot_wc = camera.world_to_camera()[:3, :3].contiguous()
    with LAUNCH_LOCK:
        _ewa(p_cam.numpy(), *(t.detach().float().contiguous().numpy() for t in (quats, log_scales, opacity_logits)),
             rot_wc.numpy(), camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, near, dilation,
             means2d.numpy(), conics.numpy(), opacities.numpy(), extents.numpy(), visible.numpy())
    return means2d, conics, opacities, extents, p_cam[:, 2], visible


SH_BLOCK = 256      # visible splats per parallel work item of `_sh_values` (one scratch basis each)


@numba.njit(parallel=True, cache=True, nogil=True)
def _sh_values(ids, means, sh, center, depths, values):  # pragma: no cover
    """values[v] = (SH colour of splat ids[v] seen from `center`, its depth), for the V
    visible splats only: `splats.eval_sh` (its tested twin) per splat, in float64."""
    k = sh.shape[1]
    count = ids.shape[0]
    for block in numba.prange((count + SH_BLOCK - 1) // SH_BLOCK):
        basis = np.empty(16)
        for v in range(block * SH_BLOCK, min(count, (block + 1) * SH_BLOCK)):
            g = ids[v]
            x = np.float64(means[g, 0]) - center[0]
            y = np.float64(means[g, 1]) - center[1]
            z = np.float64(means[g, 2]) - center[2]
            norm = max(math.sqrt(x * x + y * y + z * z), 1e-12)
            x /= norm
            y /= norm
            z /= norm
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            basis[0] = SH_C0
            basis[1] = -SH_C1 * y
            basis[2] = SH_C1 * z
            basis[3] = -SH_C1 * x
            basis[4] = SH_C2[0] * xy
            basis[5] = SH_C2[1] * yz
            basis[6] = SH_C2[2] * (2 * zz - xx - yy)
            basis[7] = SH_C2[3] * xz
            basis[8] = SH_C2[4] * (xx - yy)
            basis[9] = SH_C3[0] * y * (3 * xx - yy)
            basis[10] = SH_C3[1] * xy * z
            basis[11] = SH_C3[2] * y * (4 * zz - xx - yy)
            basis[12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
            basis[13] = SH_C3[4] * x * (4 * zz - xx - yy)
            basis[14] = SH_C3[5] * z * (xx - yy)
            basis[15] = SH_C3[6] * x * (xx - 3 * yy)
            for c in range(3):
                total = 0.5
                for j in range(k):
                    total += basis[j] * np.float64(sh[g, j, c])
                values[v, c] = max(total, 0.0)
            values[v, 3] = depths[g]


def splat_values(means: torch.Tensor, sh: torch.Tensor, ids: torch.Tensor, camera: Camera,
                 depths: torch.Tensor) -> torch.Tensor:
    """[V, 4] float32: the SH colour (`render.splat_colors`) and camera depth of the splats
    `ids` ([V] long into the model's G; means [G, 3], sh [G, K, 3], depths [G])."""
    values = torch.empty(len(ids), 4, dtype=torch.float32)
    with LAUNCH_LOCK:
        _sh_values(ids.numpy(), means.detach().float().contiguous().numpy(), sh.detach().float().contiguous().numpy(),
                   camera.center.numpy(), depths.double().contiguous().numpy(), values.numpy())
    return values


PAIR_CHUNKS = 16    # runs of visible splats listed in parallel (each keeps a cursor per tile)
NO_FRAGMENT = 1.0   # a pair's entry at a pixel it does not reach (a log alpha is never above 0)
# A cut list runs on until every mask's log transmittance is this far below LOG_T_MIN. The compositor
# sums float32 log(1 - alpha) of the float32 alphas; the cut, float64 ones of its own float64 alphas: the
# two sums differ by about 1e-4 at most over a spent pixel, so the compositor has stopped every mask
# inside the list, and composites the cut list exactly as the whole one.
CUT_MARGIN = 0.01


@numba.njit(cache=True, nogil=True)
def _tile_lists(means2d, extents, tiles_x, tiles_y, tile, chunks):  # pragma: no cover
    """Where the pairs go, before any is listed: box [V, 4] (each splat's tile box x0, y0, x1,
    y1, `splats.intersect`'s), start [T + 1] (tile t's pairs are start[t]:start[t + 1]) and
    cursor [chunks, T], the first slot of each run of splats in each tile. Runs are
    consecutive in depth order and each tile holds them run after run, so the pairs of a
    tile stay in depth order whichever run is listed first."""
    count = means2d.shape[0]
    box = np.empty((count, 4), np.int64)
    limit = (tiles_x - 1, tiles_y - 1)
    run = max(1, (count + chunks - 1) // chunks)
    tiles = tiles_x * tiles_y
    per_run = np.zeros((chunks, tiles), np.int64)
    for v in range(count):
        for k in range(2):
            centre = means2d[v, k] - 0.5                 # pixel centres sit at integer + 0.5
            box[v, k] = max(0, math.floor((centre - extents[v, k]) / tile))
            box[v, 2 + k] = min(limit[k], math.floor((centre + extents[v, k]) / tile))
        for ty in range(box[v, 1], box[v, 3] + 1):
            for tx in range(box[v, 0], box[v, 2] + 1):
                per_run[v // run, ty * tiles_x + tx] += 1
    start = np.zeros(tiles + 1, np.int64)
    cursor = np.empty((chunks, tiles), np.int64)
    for t in range(tiles):
        at = start[t]
        for c in range(chunks):
            cursor[c, t] = at
            at += per_run[c, t]
        start[t + 1] = at
    return box, start, cursor


@numba.njit(inline="always", cache=True, nogil=True)
def _power(tx, ty, ox, oy, tile, mx, my, ca, cb, cc):  # pragma: no cover
    """The Gaussian's exponent at pixel (ox, oy) of tile (tx, ty): -d^T conic d / 2, float64."""
    dy = ty * tile + oy + 0.5 - my
    dx = tx * tile + ox + 0.5 - mx
    return -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy


@numba.njit(parallel=True, cache=True, nogil=True)
def _pair_log_alpha(box, cursor, means2d, conics, opacities, tiles_x, tile, width, height, splat,
                    pair_log_alpha):  # pragma: no cover
    """Each visible splat, run by run, lists itself in every tile of its box (splat[k]) with
    pair_log_alpha[k, p] = log(opacity) + power at pixel p of the tile where alpha >=
    ALPHA_MIN (decided in float64), NO_FRAGMENT elsewhere and outside the image. Walking
    splats rather than tiles reads each splat once; the exp is left to one vectorised call
    over the fragments (`splat_fragments`)."""
    chunks = cursor.shape[0]
    count = means2d.shape[0]
    run = max(1, (count + chunks - 1) // chunks)
    for c in numba.prange(chunks):
        for v in range(c * run, min(count, (c + 1) * run)):
            log_opacity = math.log(opacities[v])
            cutoff = math.log(ALPHA_MIN) - log_opacity       # alpha >= ALPHA_MIN <=> power >= cutoff
            mx, my = means2d[v, 0], means2d[v, 1]
            ca, cb, cc = conics[v, 0], conics[v, 1], conics[v, 2]
            for ty in range(box[v, 1], box[v, 3] + 1):
                rows = min(tile, height - ty * tile)
                for tx in range(box[v, 0], box[v, 2] + 1):
                    t = ty * tiles_x + tx
                    k = cursor[c, t]
                    cursor[c, t] = k + 1
                    splat[k] = v
                    cols = min(tile, width - tx * tile)
                    for oy in range(tile):
                        for ox in range(tile):
                            power = _power(tx, ty, ox, oy, tile, mx, my, ca, cb, cc)
                            kept = oy < rows and ox < cols and power >= cutoff
                            pair_log_alpha[k, oy * tile + ox] = power + log_opacity if kept else NO_FRAGMENT


@numba.njit(parallel=True, cache=True, nogil=True)
def _pair_splats(box, cursor, tiles_x, opacities, splat, log_opacity):  # pragma: no cover
    """Each visible splat, run by run, lists itself in every tile of its box (splat[k]), where
    `_pair_log_alpha` would, without evaluating anything; and its log opacity (as
    `_pair_log_alpha` takes it)."""
    chunks = cursor.shape[0]
    count = box.shape[0]
    run = max(1, (count + chunks - 1) // chunks)
    for c in numba.prange(chunks):
        for v in range(c * run, min(count, (c + 1) * run)):
            log_opacity[v] = math.log(opacities[v])
            for ty in range(box[v, 1], box[v, 3] + 1):
                for tx in range(box[v, 0], box[v, 2] + 1):
                    t = ty * tiles_x + tx
                    splat[cursor[c, t]] = v
                    cursor[c, t] += 1


@numba.njit(parallel=True, cache=True, nogil=True)
def _cut_log_alpha(start, splat, means2d, conics, log_opacity, tiles_x, tile, width, height, unit, keep_t,
                   pair_log_alpha, stop, row_ptr):  # pragma: no cover
    """Tile by tile, front to back over its pairs (start, splat: the pair lists), the entries
    `_pair_log_alpha` writes, for the pixels still open only (NO_FRAGMENT at the others).

    unit [V] and keep_t [U, N]: visible splat v is kept by mask n when keep_t[unit[v], n]. A
    pixel closes after the fragment that brings the transmittance of every mask below T_MIN
    by CUT_MARGIN (float64, from a float64 alpha: min(ALPHA_MAX, exp(log alpha))), a tile
    when all its pixels are closed; stop[t]: the end of tile t's pairs that were walked, and
    row_ptr[1 + q] the fragments of pixel q (as `_pixel_counts` counts them).
    A pair's entries are one branch-free pass over all the tile's pixels (SIMD lanes), then the
    fragments found at open pixels take the exp and the masks' update, the others are cleared."""
    pixels = tile * tile
    masks = keep_t.shape[1]
    t_cut = math.exp(LOG_T_MIN - CUT_MARGIN)
    log_alpha_min = math.log(ALPHA_MIN)
    for t in numba.prange(start.shape[0] - 1):
        tx, ty = t % tiles_x, t // tiles_x
        rows, cols = min(tile, height - ty * tile), min(tile, width - tx * tile)
        trans = np.ones(pixels * masks)                     # transmittance per pixel and mask
        counts = row_ptr[1 + t * pixels:1 + (t + 1) * pixels]
        counts[:] = 0
        open_ = np.zeros(pixels, np.bool_)
        for p in range(pixels):
            open_[p] = p // tile < rows and p % tile < cols
        left = rows * cols if rows > 0 and cols > 0 else 0
        k = start[t]
        while k < start[t + 1] and left > 0:
            v = splat[k]
            lo = log_opacity[v]
            cutoff = log_alpha_min - lo
            mx, my = means2d[v, 0], means2d[v, 1]
            ca, cb, cc = conics[v, 0], conics[v, 1], conics[v, 2]
            entries = pair_log_alpha[k]
            for oy in range(tile):
                for ox in range(tile):
                    power = _power(tx, ty, ox, oy, tile, mx, my, ca, cb, cc)
                    entries[oy * tile + ox] = power + lo if power >= cutoff else NO_FRAGMENT
            u = unit[v]
            for p in range(pixels):
                if entries[p] == NO_FRAGMENT:
                    continue
                if not open_[p]:
                    entries[p] = NO_FRAGMENT
                    continue
                counts[p] += 1
                step = 1.0 - min(math.exp(np.float64(entries[p])), ALPHA_MAX)
                live = 0
                for n in range(masks):
                    q = p * masks + n
                    if keep_t[u, n] and trans[q] >= t_cut:
                        trans[q] *= step
                    live += trans[q] >= t_cut
                if live == 0:
                    open_[p] = False
                    left -= 1
            k += 1
        stop[t] = k


@numba.njit(parallel=True, cache=True, nogil=True)
def _pixel_counts(start, stop, pair_log_alpha, row_ptr):  # pragma: no cover
    """row_ptr[1 + q]: the number of fragments of pixel q (tile layout) among tile t's pairs
    start[t]:stop[t]."""
    pixels = pair_log_alpha.shape[1]
    for t in numba.prange(start.shape[0] - 1):
        for p in range(pixels):
            n = 0
            for k in range(start[t], stop[t]):
                n += pair_log_alpha[k, p] != NO_FRAGMENT
            row_ptr[1 + t * pixels + p] = n


@numba.njit(parallel=True, cache=True, nogil=True)
def _gather(start, stop, splat, pair_log_alpha, row_ptr, log_alpha, index):  # pragma: no cover
    """The fragments, pixel by pixel, front to back: one pass over a tile's pairs (in depth
    order, start[t]:stop[t]) appends each pair's fragments at its pixels' cursors."""
    pixels = pair_log_alpha.shape[1]
    for t in numba.prange(start.shape[0] - 1):
        cursor = row_ptr[t * pixels:(t + 1) * pixels].copy()     # next free entry of each pixel
        for k in range(start[t], stop[t]):
            for p in range(pixels):
                a = pair_log_alpha[k, p]
                if a != NO_FRAGMENT:
                    e = cursor[p]
                    log_alpha[e] = a
                    index[e] = splat[k]
                    cursor[p] = e + 1


def splat_fragments(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, extents: torch.Tensor,
                    width: int, height: int, tile: int,
                    cut_for: tuple[torch.Tensor, torch.Tensor] | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, int]:
    """Stages 2 and 3 for V projected splats in front-to-back order (means2d [V, 2], conics
    [V, 3], opacities [V], extents [V, 2], float64).

    Returns (row_ptr [T * P + 1] int64, alpha [E] float32, index [E] int32 into the V splats,
    tiles_x, tiles_y); the fragments of pixel q (tile layout) are row_ptr[q]:row_ptr[q + 1].
    Which pixels a splat reaches is decided in float64; the alphas are one float32 exp over
    the fragments (numpy's vectorised exp, 4e-7 of the float64 value), clamped at ALPHA_MAX.

    cut_for: None lists every fragment (lists that serve any keep-mask); (unit [V] long,
    keep_t [U, N] bool), with splat v kept by mask n when keep_t[unit[v], n], ends each
    pixel's list once all N masks are spent (`_cut_log_alpha`): a prefix of the whole list,
    the same bit for bit, that composites to the same images under those masks only.
    """
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    means2d_np, conics_np, opacities_np, extents_np = (t.detach().double().contiguous().numpy()
                                                       for t in (means2d, conics, opacities, extents))
    row_ptr = np.zeros(tiles_x * tiles_y * tile * tile + 1, np.int64)
    with LAUNCH_LOCK:
        box, start, cursor = _tile_lists(means2d_np, extents_np, tiles_x, tiles_y, tile, PAIR_CHUNKS)
        splat = np.empty(start[-1], np.int32)
        pair_log_alpha = np.empty((len(splat), tile * tile), np.float32)      # [M, P], written up to stop
        if cut_for is None:
            _pair_log_alpha(box, cursor, means2d_np, conics_np, opacities_np, tiles_x, tile, width, height, splat,
                            pair_log_alpha)
            stop = start[1:]
            _pixel_counts(start, stop, pair_log_alpha, row_ptr)
        else:
            unit, keep_t = cut_for
            log_opacity = np.empty(len(opacities_np))
            _pair_splats(box, cursor, tiles_x, opacities_np, splat, log_opacity)
            stop = np.empty(len(start) - 1, np.int64)
            _cut_log_alpha(start, splat, means2d_np, conics_np, log_opacity, tiles_x, tile, width, height,
                           unit.long().contiguous().numpy(), keep_t.bool().numpy(), pair_log_alpha, stop, row_ptr)
        np.cumsum(row_ptr, out=row_ptr)
        alpha = np.empty(row_ptr[-1], np.float32)
        index = np.empty(row_ptr[-1], np.int32)
        _gather(start, stop, splat, pair_log_alpha, row_ptr, alpha, index)
    np.exp(alpha, out=alpha)
    np.minimum(alpha, np.float32(ALPHA_MAX), out=alpha)
    return torch.from_numpy(row_ptr), torch.from_numpy(alpha), torch.from_numpy(index), tiles_x, tiles_y
