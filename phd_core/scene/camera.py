"""Pinhole cameras: the `Camera`, its one world-to-pixel projection, pose checks, look-at,
which cameras of two lists stand at the same pose, and which cameras see almost none of a scene.

A `Camera` stores a camera-to-world matrix in the OpenGL convention used by Blender and
nerfstudio frames (+x right, +y up, the camera looks down -z) plus pinhole intrinsics in
pixels. Pixel (i, j) has its centre at image coordinates (i + 0.5, j + 0.5), so a
principal point of (W / 2, H / 2) is the image centre. Renderers use the OpenCV
world-to-camera matrix (+y down, looks down +z) from `world_to_camera()`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import torch

from ..errors import InputError, check_int

DEFAULT_MAX_SIZE = 4096
ORTHONORMAL_TOL = 1e-3
MAX_INTRINSIC = 1e7        # |focal length| and |principal point| in pixels: larger ones overflow projections
MAX_COORDINATE = 1e6       # |camera position| in scene units: beyond it float32 splat maths loses every digit
SAME_POSE = 1e-3           # centres this close (x the cameras' spread) and directions this close (radians) coincide
UNSEEN_SHARE = 0.01        # a camera with fewer than 1% of a scene's points in its frustum sees almost none of it
CHECKED_POINTS = 20_000    # `unseen_cameras` projects up to this many of the points (every n-th)
# OpenGL camera axes -> OpenCV camera axes: flip y and z.
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass(frozen=True)
class Camera:
    """A validated pinhole camera. `c2w`: [4, 4] float64, OpenGL convention."""

    c2w: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    max_size: int = field(default=DEFAULT_MAX_SIZE, compare=False, repr=False)

    def __post_init__(self) -> None:
        c2w = torch.as_tensor(self.c2w, dtype=torch.float64)
        object.__setattr__(self, "c2w", c2w)
        validate_pose(c2w, "transform_matrix")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not math.isfinite(value) or not 0 < value <= MAX_INTRINSIC:
                raise InputError(name, f"focal length must be a positive finite number up to {MAX_INTRINSIC:g} "
                                       f"pixels, got {value}")
        for name in ("cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value) or abs(value) > MAX_INTRINSIC:
                raise InputError(name, f"principal point must be finite and within +-{MAX_INTRINSIC:g} pixels, "
                                       f"got {value}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, float) and not math.isfinite(value) or int(value) != value or value <= 0:
                raise InputError(name, f"image size must be a positive integer, got {value}")
            if value > self.max_size:
                raise InputError(name, f"image size {value} exceeds the cap of {self.max_size} pixels")
            object.__setattr__(self, name, int(value))

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates: [3] float64."""
        return self.c2w[:3, 3]

    def world_to_camera(self) -> torch.Tensor:
        """OpenCV world-to-camera view matrix [4, 4] float64 (+y down, looks down +z)."""
        c2w_cv = self.c2w @ _GL_TO_CV
        rot, trans = c2w_cv[:3, :3], c2w_cv[:3, 3]
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = rot.T
        w2c[:3, 3] = -rot.T @ trans
        return w2c

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points [P, 3] -> the OpenCV camera frame [P, 3] (z is the depth)."""
        w2c = self.world_to_camera().to(points.dtype)
        return points @ w2c[:3, :3].T + w2c[:3, 3]

    def to_pixels(self, p_cam: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Camera-frame points [P, 3] over depths z [P] -> pixel coordinates [P, 2] (centres at
        +0.5): the one perspective division. Callers choose z (clamped, or 1 for culled rows)."""
        return torch.stack([self.fx * p_cam[:, 0] / z + self.cx, self.fy * p_cam[:, 1] / z + self.cy], dim=-1)

    def project(self, points: torch.Tensor, min_depth: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
        """World points [P, 3] -> pixel coordinates [P, 2] (pixel centres at +0.5) and camera
        depth [P] (OpenCV z). The division uses the depth clamped to `min_depth`, so points
        behind the camera stay finite: callers keep those with depth > 0 (or their own margin)."""
        p = self.to_camera(points)                                       # [P, 3] OpenCV camera frame
        return self.to_pixels(p, p[:, 2].clamp_min(min_depth)), p[:, 2]

    def scaled(self, factor: float) -> "Camera":
        """The same view at 1/factor of the resolution (factor 2 halves width and height)."""
        if not math.isfinite(factor) or factor <= 0:
            raise InputError("downscale", f"must be a positive number, got {factor}")
        largest = max(self.width, self.height) / factor        # inf for a subnormal factor: no round() of it
        if not largest <= self.max_size:
            raise InputError("downscale", f"{factor} renders {self.width}x{self.height} at {largest:.4g} pixels "
                                          f"per side, above the cap of {self.max_size}")
        width = max(1, round(self.width / factor))
        height = max(1, round(self.height / factor))
        return self.resized(width, height)

    def resized(self, width: int, height: int) -> "Camera":
        """The same view rendered at width x height; intrinsics scale with the size."""
        for name, value in (("width", width), ("height", height)):
            check_int(value, name, 1, self.max_size)         # before a division by it can overflow
        sx, sy = width / self.width, height / self.height
        return Camera(self.c2w, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      width, height, self.max_size)

    def to_frame(self) -> dict[str, Any]:
        """nerfstudio-style frame dict, which `camera_from_frame` reads back exactly."""
        return {
            "fl_x": self.fx, "fl_y": self.fy, "cx": self.cx, "cy": self.cy,
            "w": self.width, "h": self.height,
            "transform_matrix": self.c2w.tolist(),
        }


def validate_pose(c2w: torch.Tensor, name: str = "transform_matrix") -> None:
    """Raise `InputError` unless c2w is a finite 4x4 rigid transform (rotation tol 1e-3)."""
    if tuple(c2w.shape) not in ((4, 4), (3, 4)):
        raise InputError(name, f"must be a 4x4 (or 3x4) matrix, got shape {list(c2w.shape)}")
    if not torch.isfinite(c2w).all():
        raise InputError(name, "contains NaN or infinite values")
    if c2w[:3, 3].abs().max() > MAX_COORDINATE:
        raise InputError(name, f"camera position lies beyond +-{MAX_COORDINATE:g} scene units")
    rot = c2w[:3, :3]
    err = (rot.T @ rot - torch.eye(3, dtype=rot.dtype)).abs().max().item()
    if err > ORTHONORMAL_TOL:
        raise InputError(name, f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {ORTHONORMAL_TOL})")
    if torch.det(rot).item() < 0:
        raise InputError(name, "rotation has determinant -1 (a reflection), not a rotation")
    if c2w.shape[0] == 4 and (c2w[3] - torch.tensor([0, 0, 0, 1.0], dtype=c2w.dtype)).abs().max() > ORTHONORMAL_TOL:
        raise InputError(name, "last row must be [0, 0, 0, 1]")


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0, 0, 1), *,
            width: int, height: int, fov_x: float) -> Camera:
    """A camera at `eye` looking at `target` (OpenGL c2w), `fov_x` in radians."""
    eye_t = torch.tensor(eye, dtype=torch.float64)
    forward = torch.tensor(target, dtype=torch.float64) - eye_t
    if forward.norm() < 1e-12:
        raise InputError("target", "eye and target coincide")
    forward = forward / forward.norm()
    up_t = torch.tensor(up, dtype=torch.float64)
    right = torch.linalg.cross(forward, up_t)
    if right.norm() < 1e-9:  # looking straight along `up`: pick any perpendicular axis
        right = torch.linalg.cross(forward, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    right = right / right.norm()
    true_up = torch.linalg.cross(right, forward)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye_t
    focal = 0.5 * width / math.tan(0.5 * fov_x)
    return Camera(c2w, focal, focal, width / 2, height / 2, width, height)


def pose_matches(cameras: Sequence[Camera], others: Sequence[Camera]) -> list[int | None]:
    """For each of `cameras`, the index of a camera of `others` at the same centre (within
    SAME_POSE times the spread of `cameras`) looking the same way (within SAME_POSE radians),
    or None: which views two captures share, whatever their image sizes."""
    if not cameras or not others:
        return [None] * len(cameras)
    centres = torch.stack([c.center for c in cameras])                                 # [N, 3]
    spread = float((centres - centres.median(dim=0).values).norm(dim=-1).median()) or 1.0
    forward = torch.stack([-c.c2w[:3, 2] for c in cameras])                            # [N, 3]
    other_centres = torch.stack([c.center for c in others])                            # [M, 3]
    other_forward = torch.stack([-c.c2w[:3, 2] for c in others])                       # [M, 3]
    close = torch.cdist(centres, other_centres) <= SAME_POSE * spread                  # [N, M]
    aligned = (forward @ other_forward.T).clamp(-1, 1).acos() <= SAME_POSE             # [N, M]
    same = close & aligned
    return [int(row.nonzero()[0]) if row.any() else None for row in same]


def unseen_cameras(points: torch.Tensor, cameras: Sequence[Camera]) -> list[int]:
    """The cameras that see almost none of points [P, 3] (fewer than UNSEEN_SHARE of them in their
    frustum) when they are most of `cameras`, as cameras in another world frame than the points
    are; [] otherwise."""
    if not cameras or len(points) == 0:
        return []
    checked = points[::max(1, len(points) // CHECKED_POINTS)].double()               # [S, 3]
    unseen = []
    for i, camera in enumerate(cameras):
        pixels, depth = camera.project(checked)                                       # [S, 2], [S]
        inside = ((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] <= camera.width)
                  & (pixels[:, 1] >= 0) & (pixels[:, 1] <= camera.height))
        if inside.double().mean() < UNSEEN_SHARE:
            unseen.append(i)
    return unseen if len(unseen) * 2 > len(cameras) else []
