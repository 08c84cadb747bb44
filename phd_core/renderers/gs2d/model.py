"""The 2D Gaussian Splatting model (Huang et al. 2024): G surfels, flat Gaussian disks.

Stored like a 3DGS model except that each splat has two scales, along the first two
columns of its rotation (the tangent axes t_u, t_v); the third column is the surfel's
normal. Everything else (means, wxyz quaternions, opacity logits, SH colour) and every
method comes from the splat model, `GaussianModel`.
"""

from __future__ import annotations

from ..splats.model import GaussianModel


class SurfelModel(GaussianModel):
    """G surfels: log_scales is [G, 2], the log std along t_u and t_v."""

    scale_axes = 2
