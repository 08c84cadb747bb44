"""3D Gaussian Splatting: the batched CPU rasteriser behind the renderer protocol (`render`,
compiled stages in `kernels`), its PLY sniff (`ply`) and the family entry (`family`). The
model, the PLY format and its sidecar are the splats' (`phd_core.renderers.splats`), which
3DGS uses as they are, so they are importable from here too."""

from ..splats.model import SH_COEFFS, GaussianModel
from ..splats.ply import (
    SIDECAR_FORMAT,
    is_ply,
    parse_ply,
    property_names,
    read_ply,
    read_sidecar,
    sidecar_path,
    write_ply,
)
from ..splats.renderer import RenderOutput
from .render import GaussianRenderer, rasterize

__all__ = ["SH_COEFFS", "SIDECAR_FORMAT", "GaussianModel", "GaussianRenderer", "RenderOutput", "is_ply", "parse_ply",
           "property_names", "rasterize", "read_ply", "read_sidecar", "sidecar_path", "write_ply"]
