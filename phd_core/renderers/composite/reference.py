"""The reference compositing backend: pure torch, differentiable, batched over keep-masks.

Front-to-back compositing of the fragments (`phd_core.renderers.splats.maths.Fragments`) in log
space, once per keep-mask; per-pixel sums are sparse CSR products (`PixelSums`).
"""

from __future__ import annotations

import warnings

import torch

from ..splats.maths import LOG_T_MIN, Fragments

# Per-pixel sums use CSR products, which torch flags as beta; they are checked in the tests.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")


class PixelSums(torch.autograd.Function):
    """sums[s, n, c] = sum over the entries e of covered pixel s of weight[e, n] * values[e, c].

    Forward: one CSR (pixels x entries, holding a value channel) times dense
    (entries x masks) product per channel. Backward: each entry gathers its pixel's
    gradient, O(E * N * C). (Autograd through CSR values would densify to S x E.)
    """

    @staticmethod
    def forward(ctx, weight: torch.Tensor, values: torch.Tensor, row: torch.Tensor,
                row_ptr: torch.Tensor) -> torch.Tensor:
        # weight: [E, N], values: [E, C] -> [S, N, C]
        ctx.save_for_backward(weight, values, row)
        entries = torch.arange(len(row))
        size = (len(row_ptr) - 1, len(row))
        return torch.stack([torch.sparse_csr_tensor(row_ptr, entries, channel.contiguous(), size=size) @ weight
                            for channel in values.T], dim=-1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        weight, values, row = ctx.saved_tensors
        per_entry = grad.index_select(0, row)                              # [E, N, C]
        grad_weight = (per_entry * values[:, None, :]).sum(-1) if ctx.needs_input_grad[0] else None
        grad_values = (per_entry * weight[:, :, None]).sum(1) if ctx.needs_input_grad[1] else None
        return grad_weight, grad_values, None, None


def composite(frags: Fragments, values: torch.Tensor, keep: torch.Tensor | None, unit: torch.Tensor,
              num_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 4: front-to-back compositing, once per keep-mask.

    values: [E, C] per-entry quantities (colour, depth); keep: [N, U] bool or None; unit: [E]
    the keep column of each entry.
    Returns (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]).
    Transmittance is a running sum of log(1 - alpha) in float64 along the entries,
    rebased at each pixel's first entry. Per-pixel sums go through `PixelSums`.
    """
    alpha = frags.alpha[None] if keep is None else frags.alpha[None] * keep[:, unit]   # [N, E]
    log_1ma = torch.log1p(-alpha).double()
    inclusive = torch.cumsum(log_1ma, dim=1)
    exclusive = inclusive - log_1ma
    base = exclusive.index_select(1, frags.start)      # log T before the pixel's first entry
    # An entry that would bring T below T_MIN ends the pixel, itself excluded.
    weight = torch.where(inclusive - base >= LOG_T_MIN, alpha * (exclusive - base).exp().float(),
                         torch.zeros_like(alpha))       # [N, E]
    channels = torch.cat([values, torch.ones_like(values[:, :1])], dim=1)     # [E, C + 1]
    sums = PixelSums.apply(weight.T.contiguous(), channels, frags.row, frags.row_ptr)  # [S, N, C + 1]
    totals = sums.new_zeros(weight.shape[0], num_pixels, sums.shape[-1])
    totals = totals.index_copy(1, frags.pixel, sums.transpose(0, 1))
    return totals[..., :-1], totals[..., -1]
