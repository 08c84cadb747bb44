"""What every splat family (3DGS, 2DGS) shares; the families are siblings built on it.

    maths     reference constants, SH colour, stages 2-3 (tile pairs, fragments), stage 4's
              batching over compositing backends, the lock compiled kernels launch under
    model     GaussianModel: the splats as the reference trainer stores them (`scale_axes` per family)
    ply       the splat PLY (read by property name, written atomically) and the `phd train` sidecar
    renderer  SplatRenderer: the renderer protocol over a model and its rasteriser; the
              family entry's background setter and sidecar reader

This package re-exports maths, model and ply; `renderer` is imported from its module (it
uses the compositing backends, which use the maths).
"""

from .maths import (
    ALPHA_MAX,
    ALPHA_MIN,
    BOX_MARGIN,
    CHUNK_ELEMENTS,
    DEFAULT_TILE,
    LAUNCH_LOCK,
    LOG_T_MIN,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    T_MIN,
    Fragments,
    Pairs,
    box_counts,
    composite_images,
    eval_sh,
    fragments,
    intersect,
    sh_basis,
    sh_rotation,
    tile_boxes,
    tile_layout,
    untile,
)
from .model import SH_COEFFS, GaussianModel
from .ply import (
    SIDECAR_FORMAT,
    is_ply,
    parse_ply,
    ply_bytes,
    property_names,
    read_ply,
    read_sidecar,
    scale_axes,
    sidecar_path,
    write_ply,
)

__all__ = ["ALPHA_MAX", "ALPHA_MIN", "BOX_MARGIN", "CHUNK_ELEMENTS", "DEFAULT_TILE", "LAUNCH_LOCK", "LOG_T_MIN",
           "SH_C0", "SH_C1", "SH_C2", "SH_C3", "SH_COEFFS", "SIDECAR_FORMAT", "T_MIN", "Fragments", "GaussianModel",
           "Pairs", "box_counts", "composite_images", "eval_sh", "fragments", "intersect", "is_ply", "parse_ply",
           "ply_bytes", "property_names", "read_ply", "read_sidecar", "scale_axes", "sh_basis", "sh_rotation",
           "sidecar_path", "tile_boxes", "tile_layout", "untile", "write_ply"]
