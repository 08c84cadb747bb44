"""2D Gaussian Splatting (surfels, Huang et al. 2024): the model (`model`), the reference
trainer's PLY layout (`ply`), the batched CPU rasteriser behind the renderer protocol
(`render`) and the family entry (`family`)."""

from .model import SurfelModel
from .ply import is_2dgs_ply, parse_surfel_ply, read_surfel_ply, write_surfel_ply
from .render import SurfelOutput, SurfelRenderer, SurfelView, rasterize_surfels, surfel_view

__all__ = ["SurfelModel", "SurfelOutput", "SurfelRenderer", "SurfelView", "is_2dgs_ply", "parse_surfel_ply",
           "rasterize_surfels", "read_surfel_ply", "surfel_view", "write_surfel_ply"]
