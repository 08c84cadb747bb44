"""Candidate-pose generators: the hemisphere poses, and a generator as one registry entry."""

from __future__ import annotations

import math

import pytest
import torch

from phd_core.errors import InputError
from phd_core.scene import look_at
from phd_core.uq.candidates import GENERATORS, Generator, get_generator, hemisphere_cameras


def test_hemisphere_poses_lie_on_the_band_and_look_at_the_centre() -> None:
    centre = torch.tensor([0.5, -0.2, 0.1], dtype=torch.float64)
    cameras = hemisphere_cameras(40, center=centre.tolist(), radius=3.0, min_elevation=0.2, max_elevation=1.0,
                                 width=32, height=24)
    assert len(cameras) == 40 and all((c.width, c.height) == (32, 24) for c in cameras)
    offsets = torch.stack([c.center for c in cameras]) - centre            # [40, 3]
    assert torch.allclose(offsets.norm(dim=1), torch.full((40,), 3.0, dtype=torch.float64))
    elevations = torch.asin(offsets[:, 2] / 3.0)
    assert elevations.min() >= 0.2 - 1e-9 and elevations.max() <= 1.0 + 1e-9
    for camera in cameras:          # the optical axis (-z of the OpenGL c2w) points at the centre
        forward = -camera.c2w[:3, 2]
        assert torch.allclose(forward, (centre - camera.center) / 3.0, atol=1e-12)
    assert len({tuple(c.center.tolist()) for c in cameras}) == 40


def test_the_registry_serves_hemisphere_and_refuses_unknown_names() -> None:
    generated = get_generator("hemisphere").generate(6, radius=2.0, width=8, height=8)
    expected = hemisphere_cameras(6, radius=2.0, width=8, height=8)
    assert all(torch.equal(a.c2w, b.c2w) and a.to_frame() == b.to_frame() for a, b in zip(generated, expected))
    with pytest.raises(InputError) as info:
        get_generator("zigzag")
    assert info.value.field == "generator" and "hemisphere" in info.value.reason


def test_a_generator_is_one_registry_entry() -> None:
    def orbit(count: int, *, radius: float = 4.0, width: int = 16, height: int = 16):
        return [look_at((radius * math.cos(2 * math.pi * i / count), radius * math.sin(2 * math.pi * i / count), 0),
                        (0, 0, 0), width=width, height=height, fov_x=0.7) for i in range(count)]

    GENERATORS.register(Generator("ring", "a horizontal ring", orbit))
    try:
        cameras = get_generator("ring").generate(4, radius=2.0)
        assert [round(float(c.center.norm()), 9) for c in cameras] == [2.0] * 4
        with pytest.raises(ValueError):
            GENERATORS.register(Generator("ring", "again", orbit))
    finally:
        del GENERATORS["ring"]


# ----------------------------------------------------------------------------- made for the user

from phd_core.scene import Camera  # noqa: E402
from phd_core.uq.candidates import candidate_cameras, parse_spec, scene_frame  # noqa: E402


def ring(count: int, centre=(1.0, -2.0, 0.5), radius: float = 5.0, width: int = 40, height: int = 30) -> list:
    """Training cameras on a ring 0.4 rad above the centre, looking at it, with fx != fy."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = [centre[0] + radius * math.cos(0.4) * math.cos(a), centre[1] + radius * math.cos(0.4) * math.sin(a),
               centre[2] + radius * math.sin(0.4)]
        c = look_at(eye, centre, width=width, height=height, fov_x=0.8)
        cams.append(Camera(c.c2w, c.fx, c.fx * 1.05, c.cx + 1, c.cy, width, height))
    return cams


def test_orbit_rings_around_the_training_cameras_centre_with_their_intrinsics() -> None:
    training = ring(12)
    centre = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    frame = scene_frame(training)
    assert torch.allclose(frame.center, centre, atol=1e-9) and frame.radius == pytest.approx(5.0)
    assert frame.elevation == pytest.approx(0.4) and torch.allclose(frame.up, torch.tensor([0, 0, 1.0],
                                                                                           dtype=torch.float64))
    poses = candidate_cameras("orbit", 12, cameras=training, rings=3, spread=0.3)
    offsets = torch.stack([p.center for p in poses]) - centre
    assert torch.allclose(offsets.norm(dim=1), torch.full((12,), 5.0, dtype=torch.float64))
    elevations = sorted({round(float(torch.asin(o[2] / 5.0)), 9) for o in offsets})
    assert elevations == pytest.approx([0.1, 0.4, 0.7])
    for pose in poses:
        assert torch.allclose(-pose.c2w[:3, 2], (centre - pose.center) / 5.0, atol=1e-12)
        assert (pose.fx, pose.fy, pose.cx, pose.width, pose.height) == (training[0].fx, training[0].fy,
                                                                        training[0].cx, 40, 30)
    # A given size wins over the training intrinsics.
    assert candidate_cameras("sphere", 3, cameras=training, width=8, height=6, fov_x=1.0)[0].width == 8


def test_centre_and_radius_from_splats_ignore_floaters() -> None:
    g = torch.Generator().manual_seed(0)
    body = torch.randn(2000, 3, generator=g, dtype=torch.float64) * 0.3 + torch.tensor([2.0, 0, 1],
                                                                                      dtype=torch.float64)
    floaters = torch.randn(60, 3, generator=g, dtype=torch.float64) * 40
    clean, noisy = scene_frame(points=body), scene_frame(points=torch.cat([body, floaters]))
    assert torch.allclose(clean.center, torch.tensor([2.0, 0, 1], dtype=torch.float64), atol=0.05)
    assert (noisy.center - clean.center).norm() < 0.05 and noisy.radius == pytest.approx(clean.radius, rel=0.1)
    poses = candidate_cameras("hemisphere", 20, points=torch.cat([body, floaters]))
    for pose in poses:      # the body fills the view: every pose sees its centre near the image middle
        uv, depth = pose.project(clean.center[None])
        assert depth.item() > 0 and (uv[0] - torch.tensor([50.0, 50.0], dtype=torch.float64)).abs().max() < 5


def test_spiral_stays_in_front_and_looks_at_the_focus() -> None:
    # A forward-facing capture: cameras on a 2 x 1 grid patch, all looking down -y at a wall at depth 6.
    training = [look_at((x, 0, z), (x, -6, z), width=32, height=24, fov_x=1.0)
                for x in (-1.0, 0.0, 1.0) for z in (-0.5, 0.5)]
    points = torch.tensor([[0.3, -6.0, 0.1], [-0.2, -6.5, 0.0], [0.0, -5.5, -0.2]], dtype=torch.float64)
    poses = candidate_cameras("spiral", 24, cameras=training, points=points)
    focus = torch.tensor([0, -6.0, 0], dtype=torch.float64)
    eyes = torch.stack([p.center for p in poses])
    assert eyes[:, 1].abs().max() < 0.8 and eyes[:, 0].abs().max() <= 1.0 + 1e-9
    assert eyes[:, 0].abs().max() > 0.5                                   # the spiral covers the patch
    for pose in poses:
        forward = -pose.c2w[:3, 2]
        assert torch.allclose(forward, (focus - pose.center) / (focus - pose.center).norm(), atol=1e-9)
    with pytest.raises(InputError) as info:
        candidate_cameras("spiral", 4)
    assert info.value.field == "cameras"


def test_jitter_moves_training_poses_a_little_and_is_seeded() -> None:
    training = ring(4)
    poses = candidate_cameras("jitter", 40, cameras=training, position=0.02, angle=3.0, seed=1)
    again = candidate_cameras("jitter", 40, cameras=training, position=0.02, angle=3.0, seed=1)
    assert all(torch.equal(a.c2w, b.c2w) for a, b in zip(poses, again))
    moves = torch.stack([(p.center - training[k % 4].center).norm() for k, p in enumerate(poses)])
    turns = torch.stack([torch.acos(((p.c2w[:3, :3].T @ training[k % 4].c2w[:3, :3]).trace() - 1) / 2)
                         for k, p in enumerate(poses)])
    assert 0 < moves.mean() < 0.02 * 5.0 * 2.5 and 0 < turns.mean() < math.radians(3.0) * 2
    assert len({round(float(m), 12) for m in moves}) == 40


def test_spec_strings_and_option_errors() -> None:
    assert parse_spec("orbit:64") == ("orbit", 64, {})
    assert parse_spec("orbit:48,rings=3,elevation=0.4,up=0;1;0") == ("orbit", 48, {"rings": 3, "elevation": 0.4,
                                                                                   "up": [0, 1, 0]})
    assert parse_spec("sphere") == ("sphere", 64, {})
    for bad, field in (("orbit:x", "candidates"), ("zigzag:4", "generator"), ("orbit:4,rings=many", "options.rings")):
        with pytest.raises(InputError) as info:
            parse_spec(bad)
        assert info.value.field == field
    with pytest.raises(InputError) as info:
        candidate_cameras("orbit", 4, cameras=ring(3), wobble=2)
    assert info.value.field == "options.wobble" and "rings" in info.value.reason
    with pytest.raises(InputError) as info:
        candidate_cameras("orbit", 4, cameras=ring(3), rings=9)
    assert info.value.field == "options.rings"


# ----------------------------------------------------------------------------- the upright frame

from phd_core.renderers.gs3d import GaussianRenderer  # noqa: E402
from phd_core.scene import capture_up  # noqa: E402
from support.upright import UP, column, mean_up, one_side  # noqa: E402


def lean(image: torch.Tensor) -> float:
    """Degrees from the image's up to the line from the blue pixels' centroid to the red ones'
    (image [H, W, 3]): 0 when the column's red top stands straight above its blue foot."""
    rows, cols = torch.meshgrid(torch.arange(image.shape[0]), torch.arange(image.shape[1]), indexing="ij")
    red = (image[..., 0] > 0.6) & (image[..., 1] < 0.4) & (image[..., 2] < 0.4)
    blue = (image[..., 2] > 0.6) & (image[..., 0] < 0.4) & (image[..., 1] < 0.4)
    assert red.sum() > 10 and blue.sum() > 10, "the column is out of the picture"
    dx = float(cols[red].double().mean() - cols[blue].double().mean())
    dy = float(rows[blue].double().mean() - rows[red].double().mean())         # rows grow downwards
    return math.degrees(math.atan2(dx, dy))


def test_orbit_renders_of_an_upright_object_stand_upright() -> None:
    # Photos from one side, looking down: the frame of the rule before (the cameras' mean up)
    # tilts toward them, and so would every orbit around it.
    training = one_side(size=(64, 64))
    renderer = GaussianRenderer(column())
    poses = candidate_cameras("orbit", 8, cameras=training, rings=2)
    leans = [lean(renderer.render(pose)[0]) for pose in poses]
    assert max(abs(a) for a in leans) < 4.0, leans     # the estimate is 0.8 degrees off; a view from 60 degrees
                                                       # above sees that as up to twice the lean, plus a pixel
    before = candidate_cameras("orbit", 8, cameras=training, rings=2, up=mean_up(training).tolist())
    assert max(abs(lean(renderer.render(pose)[0])) for pose in before) > 15.0


def test_spiral_and_jitter_poses_are_as_level_as_the_capture() -> None:
    training = one_side()
    up = capture_up(training).vector
    for pose in candidate_cameras("spiral", 12, cameras=training):
        assert abs(float(pose.c2w[:3, 0] @ up)) < 1e-9                 # a horizontal right axis: no roll
    assert abs(float(up @ UP)) > math.cos(math.radians(2))
    # Jittered copies turn about up and their own right axis: each keeps its source's roll.
    copies = candidate_cameras("jitter", 60, cameras=training, angle=10.0, seed=3)
    for k, pose in enumerate(copies):
        source = training[k % len(training)]
        assert float(pose.c2w[:3, 0] @ up) == pytest.approx(float(source.c2w[:3, 0] @ up), abs=1e-9)
        assert not torch.allclose(pose.c2w[:3, :3], source.c2w[:3, :3], atol=1e-3)
