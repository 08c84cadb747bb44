"""Similarity transforms between world frames: p -> s R p + t, one uniform scale s > 0 and a
proper rotation R.

Trainers that normalise the world (nerfstudio's dataparser, gsplat's COLMAP parser) train
in a frame that is a similarity of the capture's; the model loaders use this to move splats
and cameras between the two, so every pose in and out of the project stays in the user's
frame. A camera moved by a similarity sees the same image: its centre moves with the points
and its axes turn with R (the scale changes only depths).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..errors import InputError
from .camera import Camera

ROTATION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Similarity:
    """`matrix`: [4, 4] float64 [[s R, t], [0, 0, 0, 1]]."""

    matrix: torch.Tensor

    @classmethod
    def from_matrix(cls, matrix, field: str = "transform") -> "Similarity":
        """Check that `matrix` ([3, 4] or [4, 4]) is s R | t with s > 0 and R a rotation; the
        error names `field`."""
        try:
            m = torch.as_tensor(matrix, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise InputError(field, "must be a 3x4 or 4x4 matrix of numbers") from None
        if tuple(m.shape) == (3, 4):
            m = torch.cat([m, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
        if tuple(m.shape) != (4, 4):
            raise InputError(field, f"must be a 3x4 or 4x4 matrix, got shape {list(m.shape)}")
        if not torch.isfinite(m).all():
            raise InputError(field, "contains NaN or infinite values")
        if not torch.equal(m[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
            raise InputError(field, f"the last row must be 0 0 0 1, got {m[3].tolist()}")
        det = torch.linalg.det(m[:3, :3])
        if not det > 0:
            raise InputError(field, f"the 3x3 part must be a scaled rotation (determinant > 0), got determinant "
                                    f"{float(det):.6g}")
        scale = float(det) ** (1.0 / 3.0)
        rotation = m[:3, :3] / scale
        error = float((rotation.T @ rotation - torch.eye(3, dtype=torch.float64)).abs().max())
        if error > ROTATION_TOLERANCE:
            raise InputError(field, f"the 3x3 part must be a uniform scale times a rotation (R^T R deviates from "
                                    f"the identity by {error:.3g})")
        return cls(m)

    @classmethod
    def make(cls, scale: float, rotation: torch.Tensor, translation: torch.Tensor) -> "Similarity":
        """p -> scale * rotation @ p + translation."""
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = scale * torch.as_tensor(rotation, dtype=torch.float64)
        m[:3, 3] = torch.as_tensor(translation, dtype=torch.float64)
        return cls(m)

    @property
    def scale(self) -> float:
        return float(torch.linalg.det(self.matrix[:3, :3])) ** (1.0 / 3.0)

    @property
    def rotation(self) -> torch.Tensor:
        """[3, 3] float64."""
        return self.matrix[:3, :3] / self.scale

    def inverse(self) -> "Similarity":
        s, r = self.scale, self.rotation
        return Similarity.make(1.0 / s, r.T, -(r.T @ self.matrix[:3, 3]) / s)

    def then(self, other: "Similarity") -> "Similarity":
        """This transform followed by `other`."""
        return Similarity(other.matrix @ self.matrix)

    def points(self, points: torch.Tensor) -> torch.Tensor:
        """[P, 3] -> [P, 3], computed in float64 and returned in the input's dtype."""
        p = points.double() @ self.matrix[:3, :3].T + self.matrix[:3, 3]
        return p.to(points.dtype)

    def camera(self, camera: Camera) -> Camera:
        """The same view in the other frame: centre moved, axes turned, intrinsics unchanged."""
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = self.rotation @ camera.c2w[:3, :3]
        c2w[:3, 3] = self.points(camera.c2w[None, :3, 3])[0]
        return Camera(c2w, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
                      camera.max_size)

    def cameras(self, cameras: list[Camera]) -> list[Camera]:
        return [self.camera(c) for c in cameras]


IDENTITY = Similarity(torch.eye(4, dtype=torch.float64))
