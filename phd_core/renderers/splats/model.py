"""The splat model: G splats in the parameterisation the reference 3DGS trainer stores
(log-scales, unnormalised wxyz quaternions, opacity logits and spherical-harmonic colour
coefficients). 3DGS uses it as is; 2DGS surfels are the subclass with two scale axes."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Self

import numpy as np
import torch

from ...errors import InputError
from ...scene import Similarity
from ...scene.rotations import quaternion_multiply, quaternion_to_rotation, rotation_to_quaternion
from .maths import SH_C0, sh_rotation

SH_COEFFS = (1, 4, 9, 16)  # K = (degree + 1) ** 2 for SH degrees 0..3


@dataclass
class GaussianModel:
    """G Gaussian splats as a trainer stores them (all tensors float32)."""

    scale_axes: ClassVar[int] = 3  # local axes with a scale (2DGS surfels have 2)

    means: torch.Tensor           # [G, 3] centres
    log_scales: torch.Tensor      # [G, scale_axes] log of the std along each local axis
    quats: torch.Tensor           # [G, 4] rotation, wxyz, not necessarily normalised
    opacity_logits: torch.Tensor  # [G] opacity before the sigmoid
    sh: torch.Tensor              # [G, K, 3] SH colour coefficients, sh[:, 0] is the DC term

    @property
    def num_splats(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return math.isqrt(self.sh.shape[1]) - 1

    def validate(self) -> None:
        """Raise `InputError` naming the field unless shapes agree, K is 1, 4, 9 or 16,
        every tensor is float32 and every value is finite."""
        axes = self.scale_axes
        described = {"means": "[G, 3]", "log_scales": f"[G, {axes}]", "quats": "[G, 4]",
                     "opacity_logits": "[G]", "sh": "[G, K, 3]"}
        for name in described:
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor):
                raise InputError(name, f"must be a torch.Tensor, got {type(value).__name__}")
            if value.dtype != torch.float32:
                raise InputError(name, f"must be float32, got {value.dtype}")
        num = self.means.shape[0] if self.means.dim() > 0 else -1
        k = self.sh.shape[1] if self.sh.dim() == 3 else -1
        expected = {"means": (num, 3), "log_scales": (num, axes), "quats": (num, 4),
                    "opacity_logits": (num,), "sh": (num, k, 3)}
        for name, shape in expected.items():
            if tuple(getattr(self, name).shape) != shape:
                detail = "" if name == "means" else f" with G = {num} (the rows of means)"
                raise InputError(name, f"must have shape {described[name]}{detail}, "
                                       f"got {list(getattr(self, name).shape)}")
        if k not in SH_COEFFS:
            raise InputError("sh", f"must have K = 1, 4, 9 or 16 coefficients (SH degree 0-3), got {k}")
        for name in expected:
            if not torch.isfinite(getattr(self, name)).all():
                raise InputError(name, "contains NaN or infinite values")

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """The model's tensors, in field order."""
        return self.means, self.log_scales, self.quats, self.opacity_logits, self.sh

    def subset(self, index: torch.Tensor | slice) -> Self:
        """The splats selected by `index`: [M] integer indices, a [G] bool mask or a slice."""
        return type(self)(self.means[index], self.log_scales[index], self.quats[index],
                             self.opacity_logits[index], self.sh[index])

    def transformed(self, frame: Similarity) -> "GaussianModel":
        """The same splats in another world frame (p -> s R p + t): centres moved, rotations
        turned, log-scales raised by log s and SH colours turned with R. A camera moved by
        `frame` renders the new model as the old camera rendered this one. Float64 inside."""
        rotation = frame.rotation                                                        # [3, 3]
        turn = rotation_to_quaternion(rotation)                                          # [4]
        sh = torch.einsum("jk,gkc->gjc", sh_rotation(rotation, self.sh.shape[1]), self.sh.double())  # [G, K, 3]
        return type(self)(frame.points(self.means.double()).float(),
                          (self.log_scales.double() + math.log(frame.scale)).float(),
                          quaternion_multiply(turn, self.quats.double()).float(),
                          self.opacity_logits.clone(), sh.float())

    def bounds(self, quantile: float = 0.0) -> tuple[list[float], list[float]]:
        """Per-axis (low, high) of the splat centres: the min/max for quantile 0, else the
        `quantile` and `1 - quantile` quantiles, which ignore stray floaters.
        An empty model has no bounds: ([], [])."""
        if not 0.0 <= quantile < 0.5:
            raise InputError("quantile", f"must lie in [0, 0.5), got {quantile}")
        if self.num_splats == 0:
            return [], []
        means = self.means.detach().cpu().double().numpy()  # [G, 3]
        low, high = np.quantile(means, [quantile, 1.0 - quantile], axis=0)  # [3] each
        return low.tolist(), high.tolist()

    def covariances(self) -> torch.Tensor:
        """[G, 3, 3] float64 world-space covariances R S S^T R^T (for viewers and exports); with
        two scale axes (2DGS surfels) the third is flat, so the covariance is rank 2."""
        axes = self.log_scales.shape[1]
        scales = self.log_scales.double().clamp(-30.0, 30.0).exp()[:, None, :]          # [G, 1, axes]
        m = quaternion_to_rotation(self.quats.double())[:, :, :axes] * scales            # [G, 3, axes]
        return m @ m.transpose(1, 2)

    def base_colours(self) -> torch.Tensor:
        """[G, 3] the view-independent (SH degree 0) colour in [0, 1]."""
        return (0.5 + SH_C0 * self.sh[:, 0].double()).clamp(0.0, 1.0)
