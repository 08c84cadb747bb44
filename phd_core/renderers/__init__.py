"""Renderers: every model family behind one protocol, and the registry that recognises them.

    protocol   the Renderer protocol PH-Dropout sees (render with keep-masks, prepare a View,
               num_units, training_cameras, describe)
    signals    SIGNALS: what a render returns (colour over the background, or over black plus alpha)
    families   FAMILIES: what the library, the CLI and the service know of each family; load_model
    splats/    what the splat families share (maths, model, PLY and sidecar, renderer)
    gs3d/      3D Gaussian Splatting (rasteriser, compiled stages)
    gs2d/      2D Gaussian Splatting, surfels (model, PLY layout, rasteriser)
    nerf/      NeRF (config, field, volume rendering, renderer, checkpoint)

A new family is one module defining a `Family` plus one entry in the tuple below (the order
is the one messages list the families in).
"""

from .families import (
    FAMILIES,
    SNIFF_BYTES,
    Family,
    UnknownModelError,
    accepts_background,
    family_of,
    family_titles,
    load_model,
    load_model_bytes,
    model_kind,
    option,
    set_background,
    unseen_views,
)
from .gs2d.family import GS2D
from .gs3d.family import GS3D
from .nerf.family import NERF
from .protocol import NO_CAMERAS_NOTE, CameraView, Renderer, RenderMemory, View, check_keep, memory_probe_bytes
from .signals import DEFAULT_SIGNAL, PREMULTIPLIED, SIGNALS, Signal, signal_channels, signals_help

for _family in (GS3D, NERF, GS2D):
    FAMILIES.register(_family)
DEFAULT_FAMILY = GS3D.name      # what `phd train` trains unless told otherwise

__all__ = ["DEFAULT_FAMILY", "DEFAULT_SIGNAL", "FAMILIES", "NO_CAMERAS_NOTE", "PREMULTIPLIED", "SIGNALS",
           "SNIFF_BYTES", "CameraView", "Family", "RenderMemory", "Renderer", "Signal", "View", "UnknownModelError",
           "accepts_background", "check_keep", "family_of", "family_titles", "load_model", "load_model_bytes",
           "memory_probe_bytes", "model_kind", "option", "set_background", "signal_channels", "signals_help",
           "unseen_views"]
