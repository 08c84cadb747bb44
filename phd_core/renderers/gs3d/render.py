"""3D Gaussian Splatting on the CPU, built for batches of PH-Dropout keep-masks.

One entry point, `rasterize`, over four named stages:

1. `project`:    world -> camera, EWA 2D covariance (+0.3 px dilation), SH colour,
                 near-plane culling, exact screen extents. Float64, once per view.
2. `intersect`:  tile/splat pairs ordered by (tile, depth). Once per view.
3. `splat_alpha`, `fragments`: the alpha of every pair at every pixel of its tile, kept
                 where alpha >= 1/255 and grouped by pixel. Once per view.
4. `composite`:  front-to-back compositing in log space, once per keep-mask, batched.

Stages 1-3 do not depend on the keep-mask, so N masks cost one projection, one sort and
one alpha evaluation plus N cheap compositing passes. A dropped splat has opacity 0:
it contributes nothing and leaves the transmittance unchanged; survivors are untouched.

Compositing follows the reference rasteriser: alpha = min(0.99, opacity * G(x)), pairs
with alpha < 1/255 are skipped, and a pixel stops at the splat that would bring its
transmittance below 1e-4. A splat is listed in every tile its alpha >= 1/255 ellipse
touches, so the image does not depend on the tile size (the reference cuts splats at a
3-sigma square, which makes its images depend on the tiling).

Pixel (i, j) has its centre at (i + 0.5, j + 0.5); see `phd_core.scene.camera`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import torch

from ...scene import Camera
from ..protocol import check_keep
from .model import GaussianModel

# Per-pixel sums use CSR products, which torch flags as beta; they are checked in the tests.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled")

# Reference constants (Kerbl et al. 2023 rasteriser).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
NEAR_PLANE = 0.2
DILATION = 0.3          # px^2 added to the 2D covariance diagonal (anti-aliasing low-pass)
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4            # stop compositing below this transmittance
LOG_T_MIN = math.log(T_MIN)
DEFAULT_TILE = 4        # pixels per tile side; see bench/bench_gaussians.py
# Upper bound on elements of one [masks, fragments] compositing chunk (about 1 GB of temporaries).
CHUNK_ELEMENTS = 1 << 24


@dataclass
class Projected:
    """Per-view, mask-independent state of the visible splats (V of the model's G)."""

    ids: torch.Tensor       # [V] long, index into the model's splats, sorted front to back
    means2d: torch.Tensor   # [V, 2] pixel coordinates of the centres
    conics: torch.Tensor    # [V, 3] inverse 2D covariance (a, b, c): a dx^2 + 2 b dx dy + c dy^2
    opacities: torch.Tensor  # [V]
    colors: torch.Tensor    # [V, 3]
    depths: torch.Tensor    # [V] camera-space z
    extents: torch.Tensor   # [V, 2] half-width/height of the alpha >= 1/255 ellipse, px


@dataclass
class RenderOutput:
    rgb: torch.Tensor       # [N, H, W, 3] composited on the background
    alpha: torch.Tensor     # [N, H, W] accumulated opacity
    depth: torch.Tensor     # [N, H, W] alpha-weighted camera depth (divide by alpha for the mean)
    means2d: torch.Tensor   # [G, 2] screen positions (autograd leaf for densification stats)
    visible: torch.Tensor   # [G] bool, survived culling in this view


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """[G, 4] wxyz (any norm) -> [G, 3, 3]. A zero quaternion gives the identity."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour from SH coefficients sh: [G, K, 3] along unit directions dirs: [G, 3].

    Same basis, signs and +0.5 offset as the reference; clamped at 0 like it.
    """
    k = sh.shape[1]
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
    basis_t = torch.stack(basis, dim=-1).to(sh.dtype)  # [G, K]
    return ((basis_t[..., None] * sh).sum(dim=1) + 0.5).clamp_min(0.0)


def project(model: GaussianModel, camera: Camera, near: float = NEAR_PLANE) -> tuple[Projected, torch.Tensor, torch.Tensor]:
    """Stage 1. Returns the visible splats, the screen means of ALL splats [G, 2]
    (for densification gradients) and the visibility mask [G]."""
    w2c = camera.world_to_camera()                     # [4, 4] float64
    rot_wc, t_wc = w2c[:3, :3], w2c[:3, 3]
    means = model.means.double()
    p_cam = means @ rot_wc.T + t_wc                    # [G, 3]
    depth = p_cam[:, 2]
    in_front = depth > near
    z = torch.where(in_front, depth, torch.ones_like(depth))  # keep culled rows finite
    means2d = torch.stack([camera.fx * p_cam[:, 0] / z + camera.cx,
                           camera.fy * p_cam[:, 1] / z + camera.cy], dim=-1)

    # EWA: Jacobian of the perspective map at the (clamped) centre, as the reference does.
    lim_x_pos = (camera.width - camera.cx) / camera.fx + 0.3 * camera.width / (2 * camera.fx)
    lim_x_neg = camera.cx / camera.fx + 0.3 * camera.width / (2 * camera.fx)
    lim_y_pos = (camera.height - camera.cy) / camera.fy + 0.3 * camera.height / (2 * camera.fy)
    lim_y_neg = camera.cy / camera.fy + 0.3 * camera.height / (2 * camera.fy)
    tx = (p_cam[:, 0] / z).clamp(-lim_x_neg, lim_x_pos) * z
    ty = (p_cam[:, 1] / z).clamp(-lim_y_neg, lim_y_pos) * z
    zeros = torch.zeros_like(z)
    jac = torch.stack([camera.fx / z, zeros, -camera.fx * tx / (z * z),
                       zeros, camera.fy / z, -camera.fy * ty / (z * z)], dim=-1).reshape(-1, 2, 3)
    rot = quaternion_to_rotation(model.quats.double())
    scales = model.log_scales.double().clamp(-30.0, 30.0).exp()
    m = rot * scales[:, None, :]                        # R S: [G, 3, 3]
    cov3d = m @ m.transpose(1, 2)
    t = jac @ rot_wc                                    # [G, 2, 3]
    cov2d = t @ cov3d @ t.transpose(1, 2)
    a = cov2d[:, 0, 0] + DILATION
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + DILATION
    det = (a * c - b * b).clamp_min(1e-30)
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    opacities = torch.sigmoid(model.opacity_logits.double())
    # The alpha >= 1/255 region is d^T cov^-1 d <= 2 ln(255 * opacity): its bounding box.
    level = 2.0 * torch.log((opacities * 255.0).clamp_min(1.0))
    extents = torch.stack([(level * a).sqrt(), (level * c).sqrt()], dim=-1)
    on_screen = ((means2d + extents > 0) & (means2d - extents < torch.tensor(
        [camera.width, camera.height], dtype=torch.float64))).all(dim=-1)
    visible = in_front & (opacities * 255.0 > 1.0) & on_screen & torch.isfinite(conics).all(-1)

    ids = visible.nonzero().squeeze(1)
    order = torch.argsort(depth[ids], stable=True)     # front to back, ties by index
    ids = ids[order]
    dirs = means[ids] - camera.center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh(model.sh[ids], dirs.to(model.sh.dtype))
    projected = Projected(ids=ids, means2d=means2d[ids], conics=conics[ids], opacities=opacities[ids],
                          colors=colors, depths=depth[ids], extents=extents[ids].detach())
    return projected, means2d, visible


@dataclass
class Pairs:
    """Stage 2 output: (tile, splat) pairs ordered by tile, then depth."""

    tile: torch.Tensor       # [M] long, tile index (row-major over the tile grid)
    splat: torch.Tensor      # [M] long, index into Projected (front-to-back order)
    tile_start: torch.Tensor  # [M] long, position of the first pair of this pair's tile
    tiles_x: int
    tiles_y: int


def intersect(proj: Projected, width: int, height: int, tile: int) -> Pairs:
    """Stage 2: list every tile each splat's alpha >= 1/255 box overlaps."""
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    centre = proj.means2d.detach() - 0.5               # pixel centres sit at integer + 0.5
    lo = ((centre - proj.extents) / tile).floor().long()
    hi = ((centre + proj.extents) / tile).floor().long()
    lo = torch.maximum(lo, torch.zeros_like(lo))
    hi = torch.minimum(hi, torch.tensor([tiles_x - 1, tiles_y - 1]))
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


def splat_alpha(proj: Projected, pairs: Pairs, tile: int) -> torch.Tensor:
    """Stage 3: alpha [M, P] of each pair at each of the P = tile^2 pixels of its tile.

    Over one tile the Gaussian's exponent is a quadratic in the pixel offset (ox, oy):
    log(opacity) - 0.5 d^T conic d with d = (base + o), so all P pixels of all pairs are
    one [M, 6] x [6, P] product followed by exp.
    """
    offsets = torch.arange(tile * tile)
    ox, oy = (offsets % tile).double(), (offsets // tile).double()
    monomials = torch.stack([torch.ones_like(ox), ox, oy, ox * ox, ox * oy, oy * oy])   # [6, P]
    corner = torch.stack([(pairs.tile % pairs.tiles_x) * tile + 0.5,
                          (pairs.tile // pairs.tiles_x) * tile + 0.5], dim=-1).double()  # [M, 2]
    base = corner - proj.means2d[pairs.splat]                  # [M, 2] offset of the tile's first pixel
    a, b, c = proj.conics[pairs.splat].unbind(-1)
    bx, by = base.unbind(-1)
    coeffs = torch.stack([
        torch.log(proj.opacities[pairs.splat]) - 0.5 * (a * bx * bx + c * by * by) - b * bx * by,
        -(a * bx + b * by), -(c * by + b * bx), -0.5 * a, -b, -0.5 * c,
    ], dim=-1).float()                                         # [M, 6]
    log_alpha = (coeffs @ monomials.float()).clamp_max(math.log(ALPHA_MAX))
    alpha = log_alpha.exp()
    return torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))


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


class PixelSums(torch.autograd.Function):
    """sums[s, n, c] = sum over the entries e of covered pixel s of weight[e, n] * values[e, c].

    Forward: one CSR (pixels x entries, holding a value channel) times dense
    (entries x masks) product per channel. Backward: each entry gathers its pixel's
    gradient, O(E * N * C). (Autograd through CSR values would densify to S x E.)
    """

    @staticmethod
    def forward(ctx, weight: torch.Tensor, values: torch.Tensor, row: torch.Tensor,
                row_ptr: torch.Tensor) -> torch.Tensor:
        # weight: [E, N], values: [E, C] -> [S, N, C]
        ctx.save_for_backward(weight, values, row)
        entries = torch.arange(len(row))
        size = (len(row_ptr) - 1, len(row))
        return torch.stack([torch.sparse_csr_tensor(row_ptr, entries, channel.contiguous(), size=size) @ weight
                            for channel in values.T], dim=-1)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        weight, values, row = ctx.saved_tensors
        per_entry = grad.index_select(0, row)                              # [E, N, C]
        grad_weight = (per_entry * values[:, None, :]).sum(-1) if ctx.needs_input_grad[0] else None
        grad_values = (per_entry * weight[:, :, None]).sum(1) if ctx.needs_input_grad[1] else None
        return grad_weight, grad_values, None, None


def composite(frags: Fragments, values: torch.Tensor, keep: torch.Tensor | None,
              num_pixels: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 4: front-to-back compositing, once per keep-mask.

    values: [E, C] per-entry quantities (colour, depth); keep: [N, E] bool or None.
    Returns (accumulated values [N, num_pixels, C], accumulated alpha [N, num_pixels]).
    Transmittance is a running sum of log(1 - alpha) in float64 along the entries,
    rebased at each pixel's first entry. Per-pixel sums go through `PixelSums`.
    """
    alpha = frags.alpha[None] if keep is None else frags.alpha[None] * keep   # [N, E]
    log_1ma = torch.log1p(-alpha).double()
    inclusive = torch.cumsum(log_1ma, dim=1)
    exclusive = inclusive - log_1ma
    base = exclusive.index_select(1, frags.start)      # log T before the pixel's first entry
    # An entry that would bring T below T_MIN ends the pixel, itself excluded.
    weight = torch.where(inclusive - base >= LOG_T_MIN, alpha * (exclusive - base).exp().float(),
                         torch.zeros_like(alpha))       # [N, E]
    channels = torch.cat([values, torch.ones_like(values[:, :1])], dim=1)     # [E, C + 1]
    sums = PixelSums.apply(weight.T.contiguous(), channels, frags.row, frags.row_ptr)  # [S, N, C + 1]
    totals = sums.new_zeros(weight.shape[0], num_pixels, sums.shape[-1])
    totals = totals.index_copy(1, frags.pixel, sums.transpose(0, 1))
    return totals[..., :-1], totals[..., -1]


def _untile(x: torch.Tensor, pairs: Pairs, tile: int, width: int, height: int) -> torch.Tensor:
    """[N, T * P, C] tile layout -> [N, H, W, C] image."""
    n, c = x.shape[0], x.shape[-1]
    x = x.reshape(n, pairs.tiles_y, pairs.tiles_x, tile, tile, c).permute(0, 1, 3, 2, 4, 5)
    return x.reshape(n, pairs.tiles_y * tile, pairs.tiles_x * tile, c)[:, :height, :width]


def rasterize(model: GaussianModel, camera: Camera, background: torch.Tensor,
              keep: torch.Tensor | None = None, *, tile: int = DEFAULT_TILE,
              near: float = NEAR_PLANE) -> RenderOutput:
    """Render `camera` once per keep-mask (keep: [N, G] bool, None = all splats).

    Differentiable with respect to the model's tensors. background: [3].
    """
    keep = check_keep(keep, model.num_splats)
    proj, means2d_all, visible = project(model, camera, near)
    pairs = intersect(proj, camera.width, camera.height, tile)
    frags = fragments(splat_alpha(proj, pairs, tile), pairs)
    splat = pairs.splat[frags.pair]                                    # [E] index into proj
    values = torch.cat([proj.colors.float(), proj.depths.float()[:, None]], dim=-1)[splat]  # [E, 4]
    num_pixels = pairs.tiles_x * pairs.tiles_y * tile * tile
    if keep is None:
        acc_v, acc_a = composite(frags, values, None, num_pixels)
    else:
        keep_frags = keep[:, proj.ids[splat]]                          # [N, E]
        chunk = max(1, CHUNK_ELEMENTS // max(1, len(splat)))
        parts = [composite(frags, values, keep_frags[i:i + chunk], num_pixels)
                 for i in range(0, keep.shape[0], chunk)]
        acc_v = torch.cat([v for v, _ in parts])
        acc_a = torch.cat([a for _, a in parts])
    acc_v = _untile(acc_v, pairs, tile, camera.width, camera.height)              # [N, H, W, 4]
    acc_a = _untile(acc_a[..., None], pairs, tile, camera.width, camera.height)[..., 0]
    rgb = acc_v[..., :3] + (1.0 - acc_a)[..., None].clamp_min(0.0) * background.to(acc_v.dtype)
    return RenderOutput(rgb=rgb, alpha=acc_a, depth=acc_v[..., 3], means2d=means2d_all, visible=visible)


class GaussianRenderer:
    """A trained 3DGS model behind the renderer protocol (`phd_core.renderers.Renderer`).

    Dropout units are the splats: keep [N, G].
    """

    kind = "3dgs"

    def __init__(self, model: GaussianModel, background: Sequence[float] = (1.0, 1.0, 1.0),
                 training_cameras: list[Camera] | None = None, *, tile: int = DEFAULT_TILE,
                 near: float = NEAR_PLANE):
        model.validate()
        self.model = model
        self.background = torch.tensor(background, dtype=torch.float32)
        self.training_cameras = training_cameras
        self.tile = tile
        self.near = near

    @property
    def num_units(self) -> int:
        return self.model.num_splats

    @torch.no_grad()
    def render_full(self, camera: Camera, keep: torch.Tensor | None = None) -> RenderOutput:
        return rasterize(self.model, camera, self.background, keep, tile=self.tile, near=self.near)

    def render(self, camera: Camera, keep: torch.Tensor | None = None) -> torch.Tensor:
        return self.render_full(camera, keep).rgb.clamp(0.0, 1.0)

    def describe(self) -> dict[str, Any]:
        lo, hi = self.model.bounds()
        return {
            "kind": self.kind,
            "num_units": self.num_units,
            "sh_degree": self.model.sh_degree,
            "bounds": {"min": lo, "max": hi},
            "background": self.background.tolist(),
            "has_training_cameras": self.training_cameras is not None,
        }
