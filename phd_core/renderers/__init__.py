"""Renderers: every model family behind one protocol, and the registry that recognises them.

    protocol   the Renderer protocol PH-Dropout sees (render with keep-masks, prepare a View,
               num_units, training_cameras, describe)
    families   FAMILIES: sniff, load, store and train each model family; load_model
    gs3d/      3D Gaussian Splatting (model, PLY, rasteriser)
    gs2d/      2D Gaussian Splatting, surfels (model, PLY layout, rasteriser)
    nerf/      NeRF (config, field, volume rendering, renderer, checkpoint)

A new family is one module defining a `Family` plus one entry in the tuple below (the order
is the one messages list the families in).
"""

from .families import (FAMILIES, SNIFF_BYTES, Family, UnknownModelError, family_of, load_model, load_model_bytes,
                       model_kind)
from .gs2d.family import GS2D
from .gs3d.family import GS3D
from .nerf.family import NERF
from .protocol import CameraView, Renderer, RenderMemory, View, check_keep, memory_probe_bytes

for _family in (GS3D, NERF, GS2D):
    FAMILIES.register(_family)

__all__ = ["FAMILIES", "SNIFF_BYTES", "CameraView", "Family", "RenderMemory", "Renderer", "View", "UnknownModelError",
           "check_keep", "family_of", "load_model", "load_model_bytes", "memory_probe_bytes", "model_kind"]
