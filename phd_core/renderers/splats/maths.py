"""Splat maths every splat renderer shares (3DGS and 2DGS): the reference
rasteriser's constants and compositing rules, SH colour, and the mask-independent stages
that turn projected splats into per-pixel fragments; and the lock compiled kernels launch under.

    tile_boxes  the tiles each splat's screen box overlaps
    intersect   tile/splat pairs ordered by (tile, depth)
    fragments   the (pair, pixel) entries with alpha >= 1/255, grouped by pixel
    untile      tile layout -> image (tile_layout: the inverse)
    box_counts  how many pairs and fragments a view will have, before it is rasterised

Stage 4, compositing the fragments once per keep-mask, is a backend (`composite`).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import torch

# Reference constants (Kerbl et al. 2023 rasteriser).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4            # stop compositing below this transmittance
LOG_T_MIN = math.log(T_MIN)
DEFAULT_TILE = 4        # pixels per tile side; see bench/bench_gaussians.py
# Upper bound on elements of one [masks, fragments] compositing chunk (about 1 GB of temporaries).
CHUNK_ELEMENTS = 1 << 24
BOX_MARGIN = 0.5        # px added to each side of a splat box when bounding its fragments (box_counts)

# numba's default threading layer runs one parallel region at a time per process; the
# service renders on several worker threads, so every compiled splat kernel (the fused
# compositor's, a family's projection) launches under this lock (each uses every core).
LAUNCH_LOCK = threading.Lock()


def sh_basis(dirs: torch.Tensor, k: int) -> torch.Tensor:
    """The first k real SH basis functions (the reference's order and signs) at unit
    directions dirs: [..., 3] -> [..., k]."""
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if k > 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if k > 4:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy),
                  SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if k > 9:
        basis += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                  SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(basis, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour from SH coefficients sh: [G, K, 3] along unit directions dirs: [G, 3].

    Same basis, signs and +0.5 offset as the reference; clamped at 0 like it.
    """
    basis_t = sh_basis(dirs, sh.shape[1]).to(sh.dtype)  # [G, K]
    return ((basis_t[..., None] * sh).sum(dim=1) + 0.5).clamp_min(0.0)


def sh_rotation(rotation: torch.Tensor, k: int) -> torch.Tensor:
    """[K, K] float64 M such that M @ sh are the coefficients of the colour field turned by
    `rotation` ([3, 3]): eval_sh(M @ sh, R d) == eval_sh(sh, d) for every direction d.

    Each SH band is closed under rotation, so M is exact; it is solved by least squares from
    the basis at 64 spiral directions and at the same directions turned back by R^T."""
    n = 64
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (3 - math.sqrt(5)) * i
    r = (1 - z * z).sqrt()
    dirs = torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)                # [64, 3]
    rotation = torch.as_tensor(rotation, dtype=torch.float64)
    # Coefficients c' with basis(d) @ c' = basis(R^T d) @ c for all d: basis(D) @ M = basis(D R).
    return torch.linalg.lstsq(sh_basis(dirs, k), sh_basis(dirs @ rotation, k)).solution   # [K, K]


@dataclass
class Pairs:
    """Stage 2 output: (tile, splat) pairs ordered by tile, then depth."""

    tile: torch.Tensor       # [M] long, tile index (row-major over the tile grid)
    splat: torch.Tensor      # [M] long, index into the projected splats (front-to-back order)
    tile_start: torch.Tensor  # [M] long, position of the first pair of this pair's tile
    tiles_x: int
    tiles_y: int


def tile_boxes(means2d: torch.Tensor, extents: torch.Tensor, width: int, height: int,
               tile: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """The tiles each splat's box overlaps: (first [V, 2], last [V, 2]) tile column and row,
    inclusive (last < first: none), and the grid size (tiles_x, tiles_y)."""
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    centre = means2d.detach() - 0.5                    # pixel centres sit at integer + 0.5
    lo = ((centre - extents) / tile).floor().long()
    hi = ((centre + extents) / tile).floor().long()
    lo = torch.maximum(lo, torch.zeros_like(lo))
    hi = torch.minimum(hi, torch.tensor([tiles_x - 1, tiles_y - 1]))
    return lo, hi, tiles_x, tiles_y


def intersect(means2d: torch.Tensor, extents: torch.Tensor, width: int, height: int, tile: int) -> Pairs:
    """Stage 2: list every tile each splat's box overlaps (means2d [V, 2], half-sizes extents
    [V, 2] in pixels; the splats in front-to-back order)."""
    lo, hi, tiles_x, tiles_y = tile_boxes(means2d, extents, width, height, tile)
    span = (hi - lo + 1).clamp_min(0)                  # [V, 2] tiles in x and y
    counts = span[:, 0] * span[:, 1]
    splat = torch.repeat_interleave(torch.arange(len(counts)), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(len(splat)) - first[splat]
    tx = lo[splat, 0] + local % span[splat, 0]
    ty = lo[splat, 1] + local // span[splat, 0]
    tile_id = ty * tiles_x + tx
    order = torch.argsort(tile_id, stable=True)         # splats are already front to back
    tile_id, splat = tile_id[order], splat[order]
    per_tile = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    tile_first = torch.cumsum(per_tile, 0) - per_tile
    return Pairs(tile=tile_id, splat=splat, tile_start=tile_first[tile_id], tiles_x=tiles_x, tiles_y=tiles_y)


def box_counts(centres: torch.Tensor, extents: torch.Tensor, width: int, height: int, tile: int) -> tuple[int, int]:
    """(pairs, pixels) of splat boxes (centres and half-sizes [V, 2], px): the tile/splat pairs
    `intersect` lists for them, and the image pixels their boxes cover, each box one pixel
    wider by BOX_MARGIN on every side (against rounding). A fragment (alpha >= 1/255) lies in
    its splat's box, so `pixels` bounds the fragments a rasteriser keeps: the memory of a
    view, known from a projection."""
    lo, hi, _, _ = tile_boxes(centres, extents, width, height, tile)
    span = (hi - lo + 1).clamp_min(0)                  # [V, 2] tiles in x and y
    first = (centres - extents - BOX_MARGIN - 0.5).ceil().clamp_min(0)   # pixel centres sit at integer + 0.5
    last = torch.minimum((centres + extents + BOX_MARGIN - 0.5).floor(),
                         torch.tensor([width - 1, height - 1], dtype=centres.dtype))
    pixels = (last - first + 1).clamp_min(0).prod(-1)
    return int((span[:, 0] * span[:, 1]).sum()), int(pixels.sum())


@dataclass
class Fragments:
    """Stage 3 output: the (pair, pixel) entries with alpha >= 1/255, grouped by pixel.

    Entries of one pixel are contiguous and front to back, because they are taken from
    alpha[M, P] in pixel-major order and pairs are sorted by (tile, depth). The S covered
    pixels are the rows of a CSR matrix over the E entries (`row_ptr`), which turns
    per-pixel sums into sparse-dense products.
    """

    alpha: torch.Tensor    # [E]
    pair: torch.Tensor     # [E] long, index into Pairs
    start: torch.Tensor    # [E] long, position of the first entry of this entry's pixel
    row: torch.Tensor      # [E] long, which covered pixel (0..S-1) the entry belongs to
    row_ptr: torch.Tensor  # [S + 1] long, entries of covered pixel s are row_ptr[s]:row_ptr[s+1]
    pixel: torch.Tensor    # [S] long, covered pixel in tile layout (tile * P + pixel-in-tile)


def fragments(alpha: torch.Tensor, pairs: Pairs) -> Fragments:
    """Keep the nonzero entries of alpha [M, P], pixel by pixel."""
    m, p = alpha.shape
    flat = alpha.detach().T.reshape(-1).nonzero().squeeze(1)   # pixel-major positions
    in_tile, pair = flat // m, flat % m
    pixel = pairs.tile[pair] * p + in_tile                     # [E]
    first = torch.ones_like(pixel, dtype=torch.bool)
    first[1:] = pixel[1:] != pixel[:-1]
    position = torch.arange(len(pixel))
    start = torch.cummax(torch.where(first, position, torch.zeros_like(position)), 0).values
    begin = first.nonzero().squeeze(1)
    return Fragments(alpha=alpha.reshape(-1).index_select(0, pair * p + in_tile), pair=pair, start=start,
                     row=torch.cumsum(first, 0) - 1, row_ptr=torch.cat([begin, torch.tensor([len(pixel)])]),
                     pixel=pixel[begin])


def untile(x: torch.Tensor, pairs: Pairs, tile: int, width: int, height: int) -> torch.Tensor:
    """[N, T * P, C] tile layout -> [N, H, W, C] image."""
    n, c = x.shape[0], x.shape[-1]
    x = x.reshape(n, pairs.tiles_y, pairs.tiles_x, tile, tile, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(n, pairs.tiles_y * tile, pairs.tiles_x * tile, c)[:, :height, :width]


def tile_layout(image: torch.Tensor, tiles_x: int, tiles_y: int, tile: int) -> torch.Tensor:
    """[H, W] image -> [T * P] tile layout (the inverse of `untile`; pixels past the image are 0)."""
    height, width = image.shape
    padded = image.new_zeros(tiles_y * tile, tiles_x * tile)
    padded[:height, :width] = image
    return padded.reshape(tiles_y, tile, tiles_x, tile).permute(0, 2, 1, 3).reshape(-1)


def composite_images(composite, frags: Fragments, values: torch.Tensor, keep: torch.Tensor | None,
                     unit: torch.Tensor, pairs: Pairs, tile: int, width: int, height: int,
                     background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage 4 with a compositing backend, in mask batches of at most CHUNK_ELEMENTS values,
    back to images. values: [E, C]; keep: [N, U] bool or None (all kept); unit: [E] the keep
    column of each entry.

    Returns (accumulated values [N, H, W, C], alpha [N, H, W], rgb [N, H, W, 3]: values[..., :3]
    over `background`).
    """
    num_pixels = pairs.tiles_x * pairs.tiles_y * tile * tile
    if keep is None:
        acc_v, acc_a = composite(frags, values, None, unit, num_pixels)
    else:
        chunk = max(1, CHUNK_ELEMENTS // max(1, len(unit)))
        parts = [composite(frags, values, keep[i:i + chunk], unit, num_pixels)
                 for i in range(0, keep.shape[0], chunk)]
        acc_v = torch.cat([v for v, _ in parts])
        acc_a = torch.cat([a for _, a in parts])
    acc_v = untile(acc_v, pairs, tile, width, height)                               # [N, H, W, C]
    acc_a = untile(acc_a[..., None], pairs, tile, width, height)[..., 0]            # [N, H, W]
    rgb = acc_v[..., :3] + (1.0 - acc_a)[..., None].clamp_min(0.0) * background.to(acc_v.dtype)
    return acc_v, acc_a, rgb
