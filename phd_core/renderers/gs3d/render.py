"""3D Gaussian Splatting on the CPU, built for batches of PH-Dropout keep-masks.

One entry point, `rasterize`, over four named stages:

1. `project`:    world -> camera, EWA 2D covariance (+0.3 px dilation), SH colour,
                 near-plane culling, exact screen extents. Float64, once per view.
2. `intersect`:  tile/splat pairs ordered by (tile, depth). Once per view.
3. `splat_alpha`, `fragments`: the alpha of every pair at every pixel of its tile, kept
                 where alpha >= 1/255 and grouped by pixel. Once per view.
4. `composite`:  front-to-back compositing in log space, once per keep-mask, batched, by a
                 backend from `phd_core.renderers.composite` (`reference`: pure torch).

Stages 1-3 do not depend on the keep-mask, so N masks cost one projection, one sort and
one alpha evaluation plus N cheap compositing passes. `rasterize` runs them in torch
(differentiable: training); `GaussianRenderer.prepare` runs stages 2-3 compiled
(`kernels.py`) and keeps the result as a `SplatView`, which composites any number of mask
batches with the fused kernel: calibration re-uses one view for every ratio it tries,
PH-Dropout for every chunk of masks. A render of the full model alone (`render_full` with
keep None: `phd render`, a render request) prepares a cut view instead, whose pixels
list their fragments only down to where the transmittance is spent (`cut_lengths` is the
twin of the cut). A dropped splat has opacity 0:
it contributes nothing and leaves the transmittance unchanged; survivors are untouched.

Compositing follows the reference rasteriser: alpha = min(0.99, opacity * G(x)), pairs
with alpha < 1/255 are skipped, and a pixel stops at the splat that would bring its
transmittance below 1e-4. A splat is listed in every tile its alpha >= 1/255 ellipse
touches, so the image does not depend on the tile size (the reference cuts splats at a
3-sigma square, which makes its images depend on the tiling).

Stages 2-4 and the SH colour are shared splat maths (`phd_core.renderers.splats.maths`),
the renderer's protocol side is `SplatRenderer`; this module holds what is particular to 3D
Gaussians: the EWA projection, the alpha of an ellipse and the compiled `SplatView`.
Pixel (i, j) has its centre at (i + 0.5, j + 0.5); see `phd_core.scene.camera`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ...errors import InputError
from ...scene import Camera
from ...scene.rotations import quaternion_to_rotation
from ..composite import pick_compositor
from ..composite.fused import composite_indexed, keep_columns
from ..protocol import MEMORY_PROBE_UNITS, CameraView, RenderMemory, View, check_keep
from ..signals import DEFAULT_SIGNAL, over, signal_image
from ..splats.maths import (
    ALPHA_MAX,
    ALPHA_MIN,
    DEFAULT_TILE,
    LOG_T_MIN,
    Pairs,
    box_counts,
    composite_images,
    eval_sh,
    fragments,
    intersect,
    untile,
)
from ..splats.model import GaussianModel
from ..splats.renderer import NEAR_PLANE, RenderOutput, SplatRenderer
from .kernels import CUT_MARGIN, PAIR_CHUNKS, project_splats, splat_fragments, splat_values

DILATION = 0.3          # px^2 added to the 2D covariance diagonal (anti-aliasing low-pass)


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


def front_to_back(visible: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Indices of the visible splats ([G] bool) ordered by depth [G], ties by index."""
    ids = visible.nonzero().squeeze(1)
    return ids[torch.argsort(depth[ids], stable=True)]


def splat_colors(model: GaussianModel, ids: torch.Tensor, camera: Camera) -> torch.Tensor:
    """SH colour [V, 3] of the splats `ids` seen from the camera centre."""
    dirs = model.means[ids].double() - camera.center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return eval_sh(model.sh[ids], dirs.to(model.sh.dtype))


def project(model: GaussianModel, camera: Camera,
            near: float = NEAR_PLANE) -> tuple[Projected, torch.Tensor, torch.Tensor]:
    """Stage 1. Returns the visible splats, the screen means of ALL splats [G, 2]
    (for densification gradients) and the visibility mask [G]."""
    rot_wc = camera.world_to_camera()[:3, :3]          # [3, 3] float64
    means = model.means.double()
    p_cam = camera.to_camera(means)                    # [G, 3]
    depth = p_cam[:, 2]
    in_front = depth > near
    z = torch.where(in_front, depth, torch.ones_like(depth))  # keep culled rows finite
    means2d = camera.to_pixels(p_cam, z)               # [G, 2]

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

    ids = front_to_back(visible, depth)
    colors = splat_colors(model, ids, camera)
    projected = Projected(ids=ids, means2d=means2d[ids], conics=conics[ids], opacities=opacities[ids],
                          colors=colors, depths=depth[ids], extents=extents[ids].detach())
    return projected, means2d, visible


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


def rasterize(model: GaussianModel, camera: Camera, background: torch.Tensor,
              keep: torch.Tensor | None = None, *, tile: int = DEFAULT_TILE,
              near: float = NEAR_PLANE, compositor: str | None = None) -> RenderOutput:
    """Render `camera` once per keep-mask (keep: [N, G] bool, None = all splats).

    Differentiable with respect to the model's tensors with either compositor. background:
    [3]; compositor: a name in `phd_core.renderers.composite.COMPOSITORS` (None: the default).
    """
    keep = check_keep(keep, model.num_splats)
    composite = pick_compositor(compositor)
    proj, means2d_all, visible = project(model, camera, near)
    pairs = intersect(proj.means2d, proj.extents, camera.width, camera.height, tile)
    frags = fragments(splat_alpha(proj, pairs, tile), pairs)
    splat = pairs.splat[frags.pair]                                    # [E] index into proj
    values = torch.cat([proj.colors.float(), proj.depths.float()[:, None]], dim=-1)[splat]  # [E, 4]
    acc_v, acc_a, rgb = composite_images(composite, frags, values, keep, proj.ids[splat], pairs, tile,
                                         camera.width, camera.height, background)
    return RenderOutput(rgb=rgb, color=acc_v[..., :3], alpha=acc_a, depth=acc_v[..., 3], means2d=means2d_all,
                        visible=visible)


def cut_lengths(row_ptr: torch.Tensor, alpha: torch.Tensor, units: torch.Tensor,
                keep: torch.Tensor | None) -> torch.Tensor:
    """[S] how many fragments of each pixel's complete list (row_ptr [S + 1], alpha [E], units [E]:
    the model splat of each fragment) a view cut for `keep` ([N, G] bool, None: the full model)
    lists: up to and including the first fragment after which every mask's transmittance lies
    CUT_MARGIN below T_MIN. The pure-torch twin of `kernels._cut_log_alpha` (float64 log sums)."""
    counts = row_ptr[1:] - row_ptr[:-1]                                       # [S]
    row = torch.repeat_interleave(torch.arange(len(counts)), counts)         # [E]
    kept = torch.ones(1, len(alpha), dtype=torch.bool) if keep is None else keep[:, units]   # [N, E]
    steps = torch.where(kept, torch.log1p(-alpha.double()), 0.0)
    inclusive = torch.cumsum(steps, 1)
    first = row_ptr[:-1].clamp_max(max(len(alpha) - 1, 0))
    base = (inclusive - steps)[:, first][:, row]                             # log T before each row's first fragment
    spent = (inclusive - base < LOG_T_MIN - CUT_MARGIN).all(0)               # [E] every mask spent here
    position = torch.arange(len(alpha)) - row_ptr[:-1][row]                  # [E] place in its row
    last = torch.where(spent, position + 1, counts[row])                     # the length a cut at e gives
    return counts.clone().scatter_reduce_(0, row, last, "amin")


@dataclass
class SplatView:
    """One camera's mask-independent state (stages 1-3), composited per batch of keep-masks
    by the fused kernel. Built by `GaussianRenderer.prepare`; a `phd_core.renderers.View`."""

    camera: Camera
    background: torch.Tensor  # [3]
    num_units: int          # G, the width of a keep-mask
    units: torch.Tensor     # [V] long, the model splat of each visible splat (front to back; cut: the listed ones)
    values: torch.Tensor    # [V, 4] float32 colour and camera depth of each of them
    row_ptr: torch.Tensor   # [T * P + 1] long, fragments of pixel q (tile layout): row_ptr[q]:row_ptr[q + 1]
    alpha: torch.Tensor     # [E] float32
    log_1ma: torch.Tensor   # [E] float32, log1p(-alpha): mask-independent, so computed once
    index: torch.Tensor     # [E] int32, the visible splat of each fragment
    pairs: Pairs            # grid only (tiles_x, tiles_y), for untile
    tile: int
    means2d: torch.Tensor   # [G, 2] screen positions of all splats
    visible: torch.Tensor   # [G] bool, survived culling
    complete: bool = True   # the lists hold every fragment; False: cut for `cut_for` (`prepare_view`)
    cut_for: torch.Tensor | None = None     # the only keep a cut view renders (None: the full model)

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.units, self.values, self.row_ptr, self.alpha,
                                                         self.log_1ma, self.index, self.means2d, self.visible))

    def accumulate(self, keep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour over black and camera depth [N, H, W, 4], alpha [N, H, W]: one per keep-mask."""
        if not self.complete and keep is not self.cut_for:
            raise ValueError("a view cut for its keep-masks renders those only; prepare a complete view for others")
        keep = check_keep(keep, self.num_units)
        acc_v, acc_a = composite_indexed(self.row_ptr, self.alpha, self.index, self.units, keep, self.values,
                                         self.log_1ma)
        cam = self.camera
        acc_v = untile(acc_v, self.pairs, self.tile, cam.width, cam.height)                     # [N, H, W, 4]
        acc_a = untile(acc_a[..., None], self.pairs, self.tile, cam.width, cam.height)[..., 0]  # [N, H, W]
        return acc_v, acc_a

    def render_full(self, keep: torch.Tensor | None = None) -> RenderOutput:
        acc_v, acc_a = self.accumulate(keep)
        return RenderOutput(rgb=over(acc_v[..., :3], acc_a, self.background), color=acc_v[..., :3], alpha=acc_a,
                            depth=acc_v[..., 3], means2d=self.means2d, visible=self.visible)

    def render(self, keep: torch.Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        acc_v, acc_a = self.accumulate(keep)
        return signal_image(signal, acc_v[..., :3], acc_a, self.background)


@torch.no_grad()
def prepare_view(model: GaussianModel, camera: Camera, background: torch.Tensor, *, tile: int = DEFAULT_TILE,
                 near: float = NEAR_PLANE, cut: bool = False, keep: torch.Tensor | None = None) -> SplatView:
    """Stages 1-3 for `camera`, compiled (`kernels.py`); SH colours of the visible splats only.

    cut=False: every fragment is listed, and the view renders any keep-masks and reports
    visibility. cut=True: the view renders `keep` only ([N, G] bool; None: the full model),
    and each pixel's list ends where all of its masks' transmittance is spent: the fragments
    behind are never evaluated, and the images are the same bit for bit (a render that knows
    its masks: `GaussianRenderer.render_full`)."""
    if cut:
        keep = check_keep(keep, model.num_splats)
    means2d, conics, opacities, extents, depths, visible = project_splats(
        model.means, model.quats, model.log_scales, model.opacity_logits, camera, near, DILATION)
    ids = front_to_back(visible, depths)
    row_ptr, alpha, index, tiles_x, tiles_y = splat_fragments(means2d[ids], conics[ids], opacities[ids],
                                                              extents[ids], camera.width, camera.height, tile,
                                                              keep_columns(keep, ids) if cut else None)
    if cut:                         # the splats a cut list still names: often a small share of the visible ones
        used = torch.zeros(len(ids), dtype=torch.bool)
        used[index] = True
        rows = torch.cumsum(used, 0, dtype=torch.int32) - 1        # [V] new row of each used splat
        index, ids = rows[index], ids[used]
    empty = torch.empty(0, dtype=torch.long)
    grid = Pairs(tile=empty, splat=empty, tile_start=empty, tiles_x=tiles_x, tiles_y=tiles_y)
    values = splat_values(model.means, model.sh, ids, camera, depths)
    return SplatView(camera=camera, background=background.float(), num_units=model.num_splats, units=ids,
                     values=values, row_ptr=row_ptr, alpha=alpha, log_1ma=torch.log1p(-alpha),
                     index=index, pairs=grid, tile=tile,
                     means2d=means2d.float(), visible=visible, complete=not cut, cut_for=keep if cut else None)


# What `prepare_view` and a SplatView render hold, in bytes per item (upper envelopes of the peaks
# bench/bench_memory.py measures): per splat of the model (stage 1 in float64, what the view keeps of
# every splat), per visible splat (depth order, gathered projection) and per SH coefficient of a
# visible splat (its colour), per tile/splat pair and per pixel of its tile (the pair list, stage 3's
# [M, P] log alphas), per fragment (alpha, index, log(1 - alpha)), per tile (the pair counts and
# cursors of each run of splats, `kernels._tile_lists`), per pixel of the tile grid (fragment
# offsets); and per keep-mask: its flags by splat (the kernel's [G, m] copy, 1 byte each) and, per grid
# pixel, what `SplatView.render` holds at its worst moment: the tiled values and alpha [m, S, 4 + 1] float32
# (20 bytes) while the values are untiled (16), or the untiled ones (20) with the background weight (4) and
# the image it starts (12; the values are added and the image clamped in place): 36; the premultiplied
# signal holds the untiled ones (20) with its [m, H, W, 4] image (16): 36 as well.
SPLAT_BYTES = 128
VISIBLE_BYTES, SH_COEFF_BYTES = 64, 32
PAIR_BYTES, PAIR_PIXEL_BYTES = 4, 4
FRAGMENT_BYTES = 16
TILE_BYTES = 16 * PAIR_CHUNKS
GRID_PIXEL_BYTES = 24
MASK_GRID_PIXEL_BYTES = 36


def splat_counts(renderer: "GaussianRenderer", camera: Camera) -> tuple[int, int, int]:
    """(visible splats, tile/splat pairs, a bound on fragments) of `camera`, from stage 1 run
    MEMORY_PROBE_UNITS splats at a time (so this costs little memory whatever the model)."""
    model, counts = renderer.model, [0, 0, 0]
    for start in range(0, model.num_splats, MEMORY_PROBE_UNITS):
        part = model.subset(slice(start, start + MEMORY_PROBE_UNITS))
        means2d, _, _, extents, _, seen = project_splats(part.means, part.quats, part.log_scales,
                                                        part.opacity_logits, camera, renderer.near, DILATION)
        pairs, pixels = box_counts(means2d[seen], extents[seen], camera.width, camera.height, renderer.tile)
        for i, n in enumerate((int(seen.sum()), pairs, pixels)):
            counts[i] += n
    return counts[0], counts[1], counts[2]


def view_memory(renderer: "GaussianRenderer", camera: Camera) -> RenderMemory:
    """Bounds of `prepare(camera)` and its renders (the family's `memory`; fused compositing)."""
    if renderer.compositor != "fused":
        raise InputError("compositor",
                         f"memory bounds are measured for the fused compositor, not {renderer.compositor!r}")
    visible, pairs, fragments_ = splat_counts(renderer, camera)
    units, tile = renderer.num_units, renderer.tile
    tiles = math.ceil(camera.width / tile) * math.ceil(camera.height / tile)
    grid = tiles * tile * tile
    kept = 9 * units + 24 * visible + 8 * grid + 12 * fragments_          # SplatView.nbytes at most
    fixed = (SPLAT_BYTES * units + (VISIBLE_BYTES + SH_COEFF_BYTES * renderer.model.sh.shape[1]) * visible
             + pairs * (PAIR_BYTES + PAIR_PIXEL_BYTES * tile * tile) + FRAGMENT_BYTES * fragments_
             + TILE_BYTES * tiles + GRID_PIXEL_BYTES * grid)
    return RenderMemory(fixed=fixed, kept=kept, per_mask=units + MASK_GRID_PIXEL_BYTES * grid, fragments=fragments_)


class GaussianRenderer(SplatRenderer):
    """A trained 3DGS model behind the renderer protocol (the shared parts: `SplatRenderer`).

    With the fused compositor (the default) `prepare` returns a `SplatView` that renders many
    mask batches from one projection; any other compositor renders through `rasterize`
    (pure torch for `reference`).
    """

    kind = "3dgs"
    model_type = GaussianModel
    rasterizer = staticmethod(rasterize)

    def prepare(self, camera: Camera) -> View:
        if self.compositor == "fused":
            return prepare_view(self.model, camera, self.background, tile=self.tile, near=self.near)
        return CameraView(self, camera)

    @torch.no_grad()
    def render_full(self, camera: Camera, keep: torch.Tensor | None = None) -> RenderOutput:
        """With the fused compositor, the full model (keep None) from a cut view (`prepare_view`):
        no fragment behind the depth where a pixel's transmittance is spent is evaluated or
        listed. Masked renders list every fragment: tracking N masks' transmittance while
        listing costs about what compositing them does, and measured slower
        (docs/performance.md, "A view of the full model charged for its visible fragments")."""
        if self.compositor == "fused":
            view = prepare_view(self.model, camera, self.background, tile=self.tile, near=self.near,
                                cut=keep is None)
            return view.render_full(keep)
        return rasterize(self.model, camera, self.background, keep, tile=self.tile, near=self.near,
                         compositor=self.compositor)

    def fragment_rows(self, view: View) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                                 torch.Tensor, Pairs]:
        if not isinstance(view, SplatView) or not view.complete:       # visibility counts hidden fragments too
            view = prepare_view(self.model, view.camera, self.background, tile=self.tile, near=self.near)
        rows = torch.arange(len(view.row_ptr) - 1)
        return view.row_ptr, view.alpha, view.index, view.units, rows, view.pairs
