"""Scene geometry: the visual hull against a pixel-by-pixel recount; which cameras of two lists
coincide, and which see none of a scene."""

from __future__ import annotations

import math

import torch

from phd_core.scene import Camera, footprint, look_at, pose_matches, unseen_cameras, visual_hull


def test_a_point_is_carved_by_the_one_pixel_it_projects_into() -> None:
    gen = torch.Generator().manual_seed(0)
    cameras = [look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0, 0, 0), width=13, height=11, fov_x=0.8)
               for a in (0.0, 2.0, 4.0)]
    alphas = torch.rand(3, 11, 13, generator=gen)
    points = (torch.rand(400, 3, generator=gen, dtype=torch.float64) - 0.5) * 3
    hull = visual_hull(points, cameras, alphas, threshold=0.5)
    for i, point in enumerate(points):           # brute force: one point, one view at a time
        kept = True
        for camera, alpha in zip(cameras, alphas):
            p = camera.world_to_camera() @ torch.cat([point, torch.ones(1, dtype=torch.float64)])
            if p[2] <= 0:
                continue
            u = int(torch.floor(camera.fx * p[0] / p[2] + camera.cx))
            v = int(torch.floor(camera.fy * p[1] / p[2] + camera.cy))
            if 0 <= u < camera.width and 0 <= v < camera.height and alpha[v, u] <= 0.5:
                kept = False
        assert bool(hull[i]) == kept, i
    assert 0 < hull.float().mean() < 1


def test_a_ball_covers_the_pixels_its_image_can_touch() -> None:
    camera = look_at((0, -4, 0), (0, 0, 0), width=40, height=40, fov_x=0.8)
    centre = torch.zeros(1, 3, dtype=torch.float64)
    point, ball = footprint(camera, centre), footprint(camera, centre, radius=0.3)
    assert (point.u1 - point.u0).item() == 1 and (point.v1 - point.v0).item() == 1
    # The ball's image has radius about f r / (d - r) pixels; the block holds it plus a pixel each side.
    reach = camera.fx * 0.3 / (4 - 0.3)
    assert (ball.u1 - ball.u0).item() >= 2 * reach + 2 and bool(ball.inside)
    alpha = torch.zeros(1, 40, 40)
    alpha[0, int(ball.v0) + 1, int(ball.u1) - 2] = 1.0            # one foreground pixel inside the block
    assert visual_hull(centre, [camera], alpha, radius=0.3).item()
    assert not visual_hull(centre, [camera], torch.zeros(1, 40, 40), radius=0.3).item()


def ring(count: int, *, size: int = 20, height: float = 1.0) -> list[Camera]:
    return [look_at((3 * math.cos(a), 3 * math.sin(a), height), (0, 0, 0), width=size, height=size, fov_x=0.8)
            for a in torch.arange(count, dtype=torch.float64) * 2 * math.pi / count]


def test_pose_matches_pairs_the_same_poses_whatever_their_image_size() -> None:
    cameras = ring(6)
    others = [ring(12, size=64)[2 * i] for i in (4, 0, 5)] + ring(5)        # three of them, at another size
    assert pose_matches(cameras, others) == [1, None, None, None, 0, 2]
    turned = [look_at((3.0, 0.0, 1.0), (0, 0.01, 0), width=20, height=20, fov_x=0.8)]   # same centre, 3 mrad off
    assert pose_matches(cameras[:1], turned) == [None] and pose_matches(cameras, []) == [None] * 6


def test_unseen_cameras_are_those_that_see_none_of_the_points_when_they_are_most() -> None:
    points = (torch.rand(500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5)
    seeing = ring(4)                                              # level with the points, looking at them
    away = [Camera(c.c2w @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64)), c.fx, c.fy,
                   c.cx, c.cy, c.width, c.height) for c in ring(3)]   # the same turned round, looking outwards
    assert unseen_cameras(points, seeing[:2] + away) == [2, 3, 4]
    assert unseen_cameras(points, seeing + away[:2]) == []                   # not most of them: a few stray views
    assert unseen_cameras(points, seeing) == []
