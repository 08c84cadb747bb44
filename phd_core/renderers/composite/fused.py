"""The fused compositing backend: one compiled pass over the fragments for N keep-masks.

Per covered pixel, front to back over its fragments, every mask at once: a fragment whose
unit a mask drops is skipped by that mask; a mask stops at the fragment that would bring
its transmittance below T_MIN (that fragment excluded), and the pixel stops when every
mask has. Transmittance is a float64 running sum of log(1 - alpha), as in the reference
(`reference.py`, its tested twin); weights and sums are float64 until the final store.
Pixels are spread over the cores (numba `prange`).

Two entry points share the kernel:
- `composite`, the `COMPOSITORS` signature: values [E, C] per entry, keep [N, U] with the
  unit of each entry. Differentiable in alpha and values: its backward is a second compiled
  pass (`_composite_grad_kernel`), so training composites compiled too;
- `composite_indexed`, for callers that keep one value row per unit instead of per entry
  (entry e reads row `index[e]`, and row v is dropped by mask n when not keep[n, unit[v]]),
  so a batch of masks costs no [N, E] gather. No gradients.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from ..splats.maths import LAUNCH_LOCK, LOG_T_MIN, Fragments

PIXEL_BLOCK = 64    # pixels per parallel work item (scratch space is allocated per block)


@numba.njit(parallel=True, cache=True, nogil=True)
def _composite_kernel(row_ptr, alpha, log_1ma, index, unit, keep_t, values, out_values,
                      out_alpha):  # pragma: no cover
    """row_ptr [S + 1] int64: fragments of pixel s are row_ptr[s]:row_ptr[s + 1], front to back;
    alpha [E] float32 and log_1ma = log1p(-alpha) [E] float32 (as the reference takes it);
    index [E] int32 (value row of each fragment); unit [V] int64 (keep row of each value row);
    keep_t [U, N] bool (one unit's N flags share a cache line); values [V, C] float32.
    Writes out_values [N, S, C] and out_alpha [N, S] (float32, all).

    The loops over the N masks have no branches (selects instead), so they run as SIMD
    lanes; state is laid out mask-last for that. The stop rule reads the log
    transmittance; the weight uses the same transmittance kept as a float64 running
    value (T - alpha T, one exp fewer per fragment and mask)."""
    num_pixels = row_ptr.shape[0] - 1
    masks = keep_t.shape[1]
    channels = values.shape[1]
    blocks = (num_pixels + PIXEL_BLOCK - 1) // PIXEL_BLOCK
    for block in numba.prange(blocks):
        log_t = np.empty(masks)                     # log transmittance per mask
        trans = np.empty(masks)                     # the same, exp'd
        live = np.empty(masks, dtype=np.uint8)      # 1 until the mask's transmittance is spent
        weight = np.empty(masks)                    # this fragment's weight per mask (0: skipped)
        acc = np.empty((channels + 1, masks))       # colour/depth sums, then accumulated alpha
        for s in range(block * PIXEL_BLOCK, min(num_pixels, (block + 1) * PIXEL_BLOCK)):
            log_t[:] = 0.0
            trans[:] = 1.0
            live[:] = 1
            acc[:] = 0.0
            for e in range(row_ptr[s], row_ptr[s + 1]):
                a = np.float64(alpha[e])
                step = np.float64(log_1ma[e])
                v = index[e]
                u = unit[v]
                alive = 0
                for n in range(masks):
                    after = log_t[n] + step
                    kept = live[n] & keep_t[u, n]               # the mask keeps this unit, still live
                    room = np.uint8(after >= LOG_T_MIN)         # 0: this fragment would spend the pixel
                    use = kept & room
                    live[n] &= room | (1 - kept)                # a kept fragment without room stops the mask
                    w = a * trans[n] if use else 0.0
                    weight[n] = w
                    log_t[n] = after if use else log_t[n]
                    trans[n] -= w
                    alive += live[n]
                for c in range(channels):
                    x = np.float64(values[v, c])
                    for n in range(masks):
                        acc[c, n] += weight[n] * x
                for n in range(masks):
                    acc[channels, n] += weight[n]
                if alive == 0:
                    break
            for n in range(masks):
                for c in range(channels):
                    out_values[n, s, c] = acc[c, n]
                out_alpha[n, s] = acc[channels, n]


@numba.njit(parallel=True, cache=True, nogil=True)
def _composite_grad_kernel(row_ptr, alpha, log_1ma, unit, keep_t, values, grad_values, grad_alpha,
                           out_grad_alpha, out_grad_values):  # pragma: no cover
    """The gradient of `_composite_kernel` with one value row per entry (index = identity).

    grad_values [N, S, C] and grad_alpha [N, S] float32: dL/d(accumulated values, alpha).
    Writes out_grad_alpha [E] and out_grad_values [E, C] (float32), summed over the masks
    (terms in float64).
    Per pixel and mask, with w_i = a_i T_i over the fragments the mask uses (the same stop
    rule as the forward, the set of used fragments held fixed) and g.u_i = dL/dvalues . v_i
    + dL/dalpha:
        dL/dv_i = w_i dL/dvalues
        dL/da_i = T_i g.u_i - (sum over used j > i of w_j g.u_j) / (1 - a_i)
    Two front-to-back passes: the first sums w_j g.u_j, the second takes the suffix as the
    total minus the prefix. Each fragment belongs to one pixel, so blocks write disjoint rows."""
    num_pixels = row_ptr.shape[0] - 1
    masks = keep_t.shape[1]
    channels = values.shape[1]
    blocks = (num_pixels + PIXEL_BLOCK - 1) // PIXEL_BLOCK
    for block in numba.prange(blocks):
        for s in range(block * PIXEL_BLOCK, min(num_pixels, (block + 1) * PIXEL_BLOCK)):
            first, end = row_ptr[s], row_ptr[s + 1]
            for e in range(first, end):
                out_grad_alpha[e] = 0.0
                for c in range(channels):
                    out_grad_values[e, c] = 0.0
            for n in range(masks):
                total = 0.0
                for sweep in range(2):
                    log_t, trans, prefix = 0.0, 1.0, 0.0
                    for e in range(first, end):
                        if not keep_t[unit[e], n]:
                            continue
                        after = log_t + np.float64(log_1ma[e])
                        if after < LOG_T_MIN:
                            break
                        a = np.float64(alpha[e])
                        w = a * trans
                        gu = np.float64(grad_alpha[n, s])
                        for c in range(channels):
                            gu += np.float64(grad_values[n, s, c]) * np.float64(values[e, c])
                        if sweep == 0:
                            total += w * gu
                        else:
                            prefix += w * gu
                            out_grad_alpha[e] += trans * gu - (total - prefix) / (1.0 - a)
                            for c in range(channels):
                                out_grad_values[e, c] += w * np.float64(grad_values[n, s, c])
                        log_t = after
                        trans -= w


class _Composite(torch.autograd.Function):
    """`_composite_kernel` over per-entry values, with `_composite_grad_kernel` as its backward."""

    @staticmethod
    def forward(ctx, alpha: torch.Tensor, values: torch.Tensor, row_ptr: torch.Tensor, unit: torch.Tensor,
                keep_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        log_1ma = torch.log1p(-alpha.detach().float())
        entries = torch.arange(len(alpha), dtype=torch.int32)
        ctx.save_for_backward(alpha, log_1ma, values, row_ptr, unit, keep_t)
        return _launch(row_ptr, alpha, log_1ma, entries, unit, keep_t, values)

    @staticmethod
    def backward(ctx, grad_values: torch.Tensor, grad_alpha: torch.Tensor):
        alpha, log_1ma, values, row_ptr, unit, keep_t = ctx.saved_tensors
        out_alpha = torch.empty(len(alpha), dtype=torch.float32)
        out_values = torch.empty(values.shape, dtype=torch.float32)
        arrays = [t.detach().contiguous().numpy() for t in (row_ptr.long(), alpha.float(), log_1ma, unit.long())]
        with LAUNCH_LOCK:
            _composite_grad_kernel(*arrays, keep_t.bool().contiguous().numpy(),
                                   values.detach().float().contiguous().numpy(),
                                   grad_values.float().contiguous().numpy(), grad_alpha.float().contiguous().numpy(),
                                   out_alpha.numpy(), out_values.numpy())
        return out_alpha.to(alpha.dtype), out_values.to(values.dtype), None, None, None


def _launch(row_ptr: torch.Tensor, alpha: torch.Tensor, log_1ma: torch.Tensor, index: torch.Tensor,
            unit: torch.Tensor, keep_t: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the kernel; keep_t [U, N] may be a strided view (it is read, never copied)."""
    masks, pixels, channels = keep_t.shape[1], len(row_ptr) - 1, values.shape[1]
    out_values = torch.empty(masks, pixels, channels, dtype=torch.float32)
    out_alpha = torch.empty(masks, pixels, dtype=torch.float32)
    arrays = [t.detach().contiguous().numpy() for t in (row_ptr.long(), alpha.float(), log_1ma.float(), index.int(),
                                                         unit.long())]
    with LAUNCH_LOCK:
        _composite_kernel(*arrays, keep_t.bool().numpy(), values.detach().float().contiguous().numpy(),
                          out_values.numpy(), out_alpha.numpy())
    return out_values, out_alpha


def composite_indexed(row_ptr: torch.Tensor, alpha: torch.Tensor, index: torch.Tensor, unit: torch.Tensor,
                      keep: torch.Tensor | None, values: torch.Tensor,
                      log_1ma: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite S pixels once per keep-mask (see the module docstring for the layout).

    keep: [N, U] bool or None (every unit kept, N = 1); log_1ma: log1p(-alpha) [E] float32
    when the caller keeps it (a prepared view), else computed here. Returns (accumulated
    values [N, S, C], accumulated alpha [N, S]) float32, pixel s of row_ptr.
    """
    if log_1ma is None:
        log_1ma = torch.log1p(-alpha.float())
    return _launch(row_ptr, alpha, log_1ma, index, *keep_columns(keep, unit), values)


def keep_columns(keep: torch.Tensor | None, unit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit, keep_t [U, N]) for the kernels: keep None is one mask keeping every unit.
    Units are looked up in any order: one unit's N flags share a cache line ([U, N] copy, small)."""
    if keep is None:
        return torch.zeros_like(unit), torch.ones(1, 1, dtype=torch.bool)
    return unit, keep.T.contiguous()


def composite(frags: Fragments, values: torch.Tensor, keep: torch.Tensor | None, unit: torch.Tensor,
              num_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 4 with the `COMPOSITORS` signature: values [E, C], keep [N, U] bool or None, unit [E].
    Differentiable with respect to frags.alpha and values.

    Returns (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]).
    """
    sums, alpha = _Composite.apply(frags.alpha, values, frags.row_ptr, *keep_columns(keep, unit))
    totals = sums.new_zeros(sums.shape[0], num_pixels, sums.shape[-1]).index_copy(1, frags.pixel, sums)
    acc_alpha = alpha.new_zeros(alpha.shape[0], num_pixels).index_copy(1, frags.pixel, alpha)
    return totals, acc_alpha
