"""The 3DGS PLY: the splat PLY (`phd_core.renderers.splats.ply`) with three scale columns."""

from __future__ import annotations

from ..splats.ply import is_ply, scale_axes


def is_3dgs_ply(head: bytes) -> bool:
    """A PLY that is not a 2DGS one (exactly two scale columns); exclusive with the 2DGS sniff,
    and a header longer than `head` counts as 3DGS, whose reader then names what is missing."""
    return is_ply(head) and scale_axes(head) != 2
