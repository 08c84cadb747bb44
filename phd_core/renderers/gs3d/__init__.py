"""3D Gaussian Splatting: the model (`model`), the PLY format and its sidecar (`ply`), the
batched CPU rasteriser behind the renderer protocol (`render`) and the family entry
(`family`)."""

from .model import SH_COEFFS, GaussianModel
from .ply import (SIDECAR_FORMAT, is_ply, parse_ply, property_names, read_ply, read_sidecar, sidecar_path,
                  write_ply)
from .render import GaussianRenderer, RenderOutput, rasterize, set_background

__all__ = ["SH_COEFFS", "SIDECAR_FORMAT", "GaussianModel", "GaussianRenderer", "RenderOutput", "is_ply", "set_background",
           "parse_ply", "property_names", "rasterize", "read_ply", "read_sidecar", "sidecar_path", "write_ply"]
