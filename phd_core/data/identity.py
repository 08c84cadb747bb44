"""What identifies a capture wherever it lies: a fingerprint of its image names and camera
centres.

A trainer records the fingerprint of the split it read (`phd_core.renderers.provenance`), so
that a capture given later is known to be that one after it moved, and in another format that
reads the same images at the same poses (a COLMAP model and the poses_bounds.npy made from
it: names are compared without folder and extension). Two captures of other scenes rendered
from the same kind of rig (lego_200 and donut_200: the same names, cameras at the same
radius) differ in their centres.
"""

from __future__ import annotations

import hashlib
from pathlib import PurePosixPath

import torch

from .frames import Dataset

CENTRE_QUANTUM = 1e-5    # centres are rounded to this share of their largest coordinate


def fingerprint(dataset: Dataset) -> str:
    """16 hex digits of a hash of the frames' (name, rounded centre) pairs, in sorted order (frames
    without names are numbered in their order)."""
    centres = torch.stack([camera.center for camera in dataset.cameras])             # [V, 3] float64
    quantum = CENTRE_QUANTUM * max(float(centres.abs().max()), 1e-12)
    rounded = (centres / quantum).round().long().tolist()
    names = dataset.names or [str(i) for i in range(len(dataset.cameras))]
    rows = sorted(f"{PurePosixPath(name).stem} {x} {y} {z}" for name, (x, y, z) in zip(names, rounded))
    return hashlib.sha256("\n".join(rows).encode()).hexdigest()[:16]
