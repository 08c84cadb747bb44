"""NeRF on the CPU, behind the same renderer protocol as Gaussian Splatting.

A radiance field in the original NeRF shape, sized for two CPU cores:

    points -> encoding -> FIRST layer (the dropout units) -> trunk (with one skip) -> density
                                                                 \\-> feature + view direction -> RGB

Encodings: `pe` (positional encoding, ReLU after the first layer), `spe` (the same PE with a
sine after the first layer: sinusoidal PE, Sun et al. 2024) and `hash` (multiresolution hash
grid, InstantNGP style). `hash` is kept on purpose: hash collisions make any ensemble method,
PH-Dropout included, blind to what the model got wrong (paper, Section 3.4), and users should
be able to see that on their own scenes.

Rendering (`render_rays`): rays are clipped to the scene box and to [near, far], cut into
`samples` equal bins (a random point per bin in training, the bin centre at inference), the
samples in cells the occupancy grid marks empty are dropped, the network runs on the rest
and the compositing gives the dropped samples zero density. Transmittance is accumulated in
log space. Everything up to and including the first layer is computed once per ray chunk;
the rest of the network runs once per keep-mask, batched.

Checkpoints (`save_nerf` / `load_nerf`) are safetensors files: tensors that cannot execute
code on load, plus a JSON config in the header and the training cameras as JSON frames.

    config      NeRFConfig (validated), colour parsing
    field       encodings (pe, spe, hash), occupancy grid, RadianceField, mask_scale
    volume      camera rays, box clipping, samples, log-space compositing, render_rays
    renderer    NeRFRenderer (the renderer protocol)
    checkpoint  save_nerf / load_nerf (safetensors)
"""

from .checkpoint import (
                         CAMERAS_TENSOR,
                         CHECKPOINT_FORMAT,
                         CHECKPOINT_VERSION,
                         is_nerf_checkpoint,
                         load_nerf,
                         load_nerf_bytes,
                         nerf_bytes,
                         save_nerf,
)
from .config import ENCODINGS, NeRFConfig
from .field import (
                         DENSITY_SHIFT,
                         HASH_PRIMES,
                         HashEncoding,
                         OccupancyGrid,
                         PositionalEncoding,
                         RadianceField,
                         band_weights,
                         mask_scale,
)
from .renderer import NeRFOutput, NeRFRenderer
from .volume import RayOutput, camera_rays, composite, ray_box, ray_samples, render_rays

__all__ = [
    "CAMERAS_TENSOR", "CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "DENSITY_SHIFT", "ENCODINGS", "HASH_PRIMES",
    "HashEncoding", "NeRFConfig", "NeRFOutput", "NeRFRenderer", "OccupancyGrid", "PositionalEncoding",
    "RadianceField", "RayOutput", "band_weights", "camera_rays", "composite", "is_nerf_checkpoint", "load_nerf",
    "load_nerf_bytes", "mask_scale", "nerf_bytes", "ray_box", "ray_samples", "render_rays",
    "save_nerf",
]
