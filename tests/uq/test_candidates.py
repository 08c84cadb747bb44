"""Candidate-pose generators: the hemisphere poses, and a generator as one registry entry."""

from __future__ import annotations

import math

import pytest
import torch

from phd_core.errors import InputError
from phd_core.scene import look_at
from phd_core.uq.candidates import GENERATORS, Generator, get_generator, hemisphere_cameras, register


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

    register(Generator("ring", "a horizontal ring", orbit))
    try:
        cameras = get_generator("ring").generate(4, radius=2.0)
        assert [round(float(c.center.norm()), 9) for c in cameras] == [2.0] * 4
        with pytest.raises(ValueError):
            register(Generator("ring", "again", orbit))
    finally:
        del GENERATORS["ring"]
