"""The lines reference of bench_up (bench/vanishing.py) on a generated scene whose up is known
(support/upright.py): vertical and horizontal 3D lines projected into hand-held photos as
segments with a little pixel noise."""

from __future__ import annotations

import numpy as np
import torch

from bench.vanishing import interpretation_normals, vanishing_direction, vanishing_pixel
from support.upright import TILT, UP, one_side, turn


def segments(camera, starts: torch.Tensor, direction: torch.Tensor, noise: float, rng) -> np.ndarray:
    """[L, 4] pixel ends of the 3D lines from `starts` [L, 3] along `direction` [3] (length 0.5)."""
    ends = torch.cat([starts, starts + 0.5 * direction])                   # [2L, 3]
    pixels, depth = camera.project(ends)
    assert (depth > 0).all()
    pixels = pixels.numpy() + rng.normal(0, noise, (len(ends), 2))
    return np.hstack([pixels[: len(starts)], pixels[len(starts):]])


def test_the_vertical_direction_of_projected_vertical_lines() -> None:
    rng = np.random.default_rng(0)
    gen = torch.Generator().manual_seed(0)
    cameras = one_side(20, size=(640, 480))
    east, north = TILT[:, 0], TILT[:, 1]                                     # two horizontal directions
    normals, kinds = [], []
    for camera in cameras:
        for direction, is_vertical in ((UP, True), (east, False), (north, False)):
            starts = (torch.rand(6, 3, generator=gen, dtype=torch.float64) - 0.5) @ TILT.T    # near the origin
            lines = segments(camera, starts, direction, 0.3, rng)
            normals.append(interpretation_normals(camera, lines))
            kinds += [is_vertical] * len(lines)
    normals_all, vertical = np.concatenate(normals), np.array(kinds)
    # A guess 20 degrees off (the window is 30): it chooses among the vanishing directions only.
    guess = (turn((1.0, -1.0, 0.3), 20.0) @ UP).numpy()
    found = vanishing_direction(normals_all, guess)
    angle = np.degrees(np.arccos(min(1.0, float(found.direction @ UP.numpy()))))
    assert angle < 0.2                                                      # and on the guess's side
    # Every vertical segment is an inlier; a horizontal one only where its image happens to run
    # through the vertical's vanishing point (then its plane holds both directions).
    assert found.inliers[vertical].all() and found.inliers[~vertical].mean() < 0.05
    # Without noise the lines meet exactly where the direction projects, in every photo.
    for camera in cameras[:3]:
        meet = vanishing_pixel(camera, UP.numpy())
        lines = segments(camera, torch.zeros(1, 3, dtype=torch.float64), UP, 0.0, rng)
        line = np.cross([*lines[0, :2], 1.0], [*lines[0, 2:], 1.0])           # the segment's image line
        assert abs(line @ meet) < 1e-9 * np.linalg.norm(line) * np.linalg.norm(meet)
