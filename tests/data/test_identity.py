"""A capture's fingerprint: the same wherever the capture lies and whichever format reads the same
images at the same poses, another when the camera centres differ (lego_200 and donut_200 share
their image names)."""

from __future__ import annotations

import dataclasses

import torch

from phd_core.data import load_dataset
from phd_core.data.identity import fingerprint
from phd_core.scene import Camera
from support.fixtures import LEGO

CUP = LEGO.parent / "cup_colmap"


def test_a_fingerprint_is_the_names_and_poses_not_the_format_or_the_order() -> None:
    colmap = load_dataset(CUP, "train", with_images=False)
    assert fingerprint(colmap) == fingerprint(load_dataset(CUP / "poses_bounds.npy", "train", with_images=False))
    order = list(reversed(range(len(colmap.cameras))))
    shuffled = dataclasses.replace(colmap, cameras=[colmap.cameras[i] for i in order],
                                   names=[colmap.names[i] for i in order])
    assert fingerprint(shuffled) == fingerprint(colmap)

    moved = colmap.cameras[5].c2w.clone()
    moved[0, 3] += 1e-3                                          # one camera a millimetre-scale step aside
    camera = colmap.cameras[5]
    nudged = dataclasses.replace(colmap, cameras=colmap.cameras[:5] + [
        Camera(moved, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)] + colmap.cameras[6:])
    assert fingerprint(nudged) != fingerprint(colmap)


def test_captures_with_the_same_names_at_other_poses_differ() -> None:
    lego, donut = (load_dataset(LEGO.parent / name, "train", with_images=False) for name in ("lego_200", "donut_200"))
    assert lego.names == donut.names
    assert not torch.equal(lego.cameras[0].center, donut.cameras[0].center)
    assert fingerprint(lego) != fingerprint(donut)
