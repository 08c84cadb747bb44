"""A reference up from straight lines in the photos: the scene's vertical vanishing direction,
which neither the cameras' roll nor the SfM points decide (bench_up judges the up estimate with
it, since the estimate may stand on the SfM points' floor).

A straight 3D line and the camera centre span the segment's interpretation plane, whose unit
normal in world coordinates is n = R (K^-1 p1 x K^-1 p2), for the segment's ends p1, p2
(homogeneous pixels), the camera's intrinsics K and its rotation R (camera to world, OpenCV
axes). A line along the direction v lies in that plane: n . v = 0, in every photo that shows
it. The vertical edges of a scene (corners of walls, door frames, legs, pillars, the sides of a
cup) share v = up, so up is the direction orthogonal to the most normals:

- segments: OpenCV's line segment detector on each undistorted photo (straight lines stay
  straight only there), those at least MIN_LENGTH of the photo's longer side long;
- RANSAC: TRIALS seeded pairs of normals, each giving v = n1 x n2, scored by the normals
  within INLIER_DEG of orthogonal to v. Only v within WINDOW_DEG of a guess (the cameras'
  estimate) are scored: that tells the vertical vanishing direction from the horizontal ones,
  some 90 degrees away, and nothing more (the answer inside the window is the lines');
- refit: the eigenvector of the smallest eigenvalue of sum n n^T over the inliers, the
  inliers chosen again from it, REFITS times; the sign is the guess's side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from phd_core.scene import Camera

MIN_LENGTH = 0.05                     # of the photo's longer side: shorter segments tell little of their direction
INLIER_DEG = 1.5                      # a normal this near orthogonal to v: its line runs along v
WINDOW_DEG = 30.0                     # v is sought this near the guess (vertical, not horizontal, directions)
TRIALS = 4000
REFITS = 5


@dataclass
class Vanishing:
    direction: np.ndarray     # [3] unit, on the guess's side
    inliers: np.ndarray       # [N] bool: the normals orthogonal to it (within INLIER_DEG)


def photo_segments(image: np.ndarray) -> np.ndarray:
    """The straight segments of a photo [H, W, 3] (float in [0, 1]) at least MIN_LENGTH of its
    longer side long: [S, 4] float64 pixel coordinates x1, y1, x2, y2, the project's convention
    (a pixel's centre at +0.5)."""
    import cv2  # here: the bench extra; tests of the maths below need no OpenCV

    grey = cv2.cvtColor((np.clip(image, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
    found = cv2.createLineSegmentDetector().detect(grey)[0]
    if found is None:
        return np.zeros((0, 4))
    segments = found.reshape(-1, 4).astype(np.float64) + 0.5       # OpenCV puts a pixel's centre at +0
    lengths = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    return segments[lengths >= MIN_LENGTH * max(grey.shape)]


def interpretation_normals(camera: Camera, segments: np.ndarray) -> np.ndarray:
    """[S, 3] unit world normals of the planes through the camera centre and segments [S, 4]."""
    inverse = np.linalg.inv(intrinsics(camera))
    ones = np.ones((len(segments), 1))
    rays_1 = np.hstack([segments[:, :2], ones]) @ inverse.T                  # [S, 3] camera (OpenCV) rays
    rays_2 = np.hstack([segments[:, 2:], ones]) @ inverse.T
    normals = np.cross(rays_1, rays_2) @ camera.world_to_camera()[:3, :3].numpy()    # to world: R^T n, row-wise
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def vanishing_direction(normals: np.ndarray, guess: np.ndarray, seed: int = 0) -> Vanishing:
    """The direction orthogonal to the most interpretation-plane normals [N, 3] within
    WINDOW_DEG of `guess` [3] (module docstring)."""
    rng = np.random.default_rng(seed)
    guess = guess / np.linalg.norm(guess)
    inlier = math.sin(math.radians(INLIER_DEG))
    pairs = rng.integers(0, len(normals), (TRIALS, 2))
    candidates = np.cross(normals[pairs[:, 0]], normals[pairs[:, 1]])         # [T, 3]
    lengths = np.linalg.norm(candidates, axis=1)
    candidates = candidates[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    candidates = candidates[np.abs(candidates @ guess) >= math.cos(math.radians(WINDOW_DEG))]
    if len(candidates) == 0:
        raise ValueError(f"no pair of the {len(normals)} segments meets within {WINDOW_DEG} degrees of the guess")
    scores = np.concatenate([(np.abs(normals @ chunk.T) < inlier).sum(0) for chunk in np.split(
        candidates, range(500, len(candidates), 500))])                       # [T'] 500 at a time
    direction = candidates[scores.argmax()]
    for _ in range(REFITS):
        inliers = np.abs(normals @ direction) < inlier
        direction = np.linalg.eigh(normals[inliers].T @ normals[inliers])[1][:, 0]
    inliers = np.abs(normals @ direction) < inlier
    return Vanishing(direction if direction @ guess >= 0 else -direction, inliers)


def vanishing_pixel(camera: Camera, direction: np.ndarray) -> np.ndarray:
    """Where lines along `direction` [3] meet in the camera's image: [3] homogeneous pixel
    (last entry 0 when they are parallel in it)."""
    return intrinsics(camera) @ camera.world_to_camera()[:3, :3].numpy() @ direction


def intrinsics(camera: Camera) -> np.ndarray:
    """The pinhole matrix K [3, 3] (pixel centres at +0.5, the project's convention)."""
    return np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1.0]])
