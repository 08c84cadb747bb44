"""2D Gaussian Splatting on the CPU (Huang et al. 2024), built for batches of keep-masks.

The same four stages as the 3DGS rasteriser (`phd_core.renderers.gs3d.render`), sharing
stages 2 and 4 with it (`phd_core.renderers.splats.maths`, `phd_core.renderers.composite`)
and the renderer (`SplatRenderer`); only what a surfel is differs:

1. `project`:   per surfel the 3x3 map T from its local (u, v, 1) to homogeneous pixels,
                T = K [s_u R t_u, s_v R t_v, p_cam] (K the intrinsics, R, p_cam the surfel's
                axes and centre in the camera frame), the camera-facing normal, SH colour,
                near-plane culling and the exact screen box of its alpha >= 1/255 region.
2. `intersect`: tile/surfel pairs ordered by (tile, centre depth).
3. `splat_alpha`: per pair and pixel, the ray-surfel intersection in (u, v): a pixel x
                defines the planes h_x = T_1 - x T_3 and h_y = T_2 - y T_3 (rows of T) in
                (u, v, 1) space; the ray meets the surfel at q ~ h_x cross h_y, so
                (u, v) = (q_1, q_2) / q_3 and the intersection's depth is T_3 . (u, v, 1)
                (= det T / q_3; q is affine in the pixel position).
                The surfel's Gaussian there is exp(-(u^2 + v^2) / 2). Seen edge-on that
                Gaussian degenerates to a line, so the screen-space low-pass
                exp(-|x - c|^2 / (2 sigma^2)) with sigma = sqrt(2) / 2 px around the projected
                centre c is taken where it is larger:
                    alpha = min(0.99, opacity * max(G(u, v), G_lowpass(x))).
                Intersections nearer than the near plane do not count. The per-pixel depth is
                the intersection's where the surfel's Gaussian wins, the centre's otherwise.
4. `composite`: front-to-back in log space, once per keep-mask (a backend by name).

Stages 1-3 and each fragment's values do not depend on the keep-mask: `surfel_view` runs
them once and keeps the result as a `SurfelView`, which composites any number of mask batches
(`SurfelRenderer.prepare`: PH-Dropout's chunks of masks, calibration's ratios) and whose
fragment lists the visibility pass walks in place. `rasterize_surfels` is a view built and
composited once, differentiable (training).

Outputs: RGB, alpha, depth (alpha-weighted), and with `geometry=True` the alpha-weighted
camera-frame normal (OpenCV axes, facing the camera) and the depth distortion
sum_ij w_i w_j (d_i - d_j)^2 / 2 per pixel, which the 2DGS trainer regularises.
Compositing rules and constants are the 3DGS ones (`splats.maths`). Float64 up to alpha.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ...scene import Camera
from ...scene.rotations import quaternion_to_rotation
from ..composite import Compositor, pick_compositor
from ..protocol import MEMORY_PROBE_UNITS, RenderMemory, View, check_keep
from ..signals import DEFAULT_SIGNAL, signal_image
from ..splats.maths import (
    ALPHA_MAX,
    ALPHA_MIN,
    DEFAULT_TILE,
    Fragments,
    Pairs,
    box_counts,
    composite_images,
    eval_sh,
    fragments,
    intersect,
)
from ..splats.renderer import NEAR_PLANE, RenderOutput, SplatRenderer
from .model import SurfelModel

LOWPASS_INV_VAR = 2.0   # 1 / sigma^2 of the screen-space low-pass, sigma = sqrt(2)/2 px
RHO_MAX = 1e6           # (u^2 + v^2) beyond this is no intersection (alpha < 1e-300 anyway)


@dataclass
class Projected:
    """Per-view, mask-independent state of the visible surfels (V of the model's G)."""

    ids: torch.Tensor         # [V] long, index into the model's surfels, sorted front to back
    means2d: torch.Tensor     # [V, 2] pixel coordinates of the centres
    transforms: torch.Tensor  # [V, 3, 3] T: (u, v, 1) -> (x w, y w, w), float64
    opacities: torch.Tensor   # [V]
    colors: torch.Tensor      # [V, 3]
    normals: torch.Tensor     # [V, 3] camera frame, facing the camera
    depths: torch.Tensor      # [V] camera-space z of the centres
    box_centres: torch.Tensor  # [V, 2] centre of the screen box of the alpha >= 1/255 region, px
    extents: torch.Tensor     # [V, 2] half-width/height of that box, px


@dataclass
class SurfelOutput(RenderOutput):
    normal: torch.Tensor | None = None      # [N, H, W, 3] alpha-weighted camera-frame normal
    distortion: torch.Tensor | None = None  # [N, H, W] sum_ij w_i w_j (d_i - d_j)^2 / 2


def screen_boxes(transforms: torch.Tensor, means2d: torch.Tensor, level: torch.Tensor, near: float,
                 width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre and half-size [G, 2] of a box holding every pixel where alpha >= 1/255.

    The surfel's part is the disk u^2 + v^2 <= level (level = 2 ln(255 opacity)); its image
    is the conic whose dual is C* = T diag(level, level, -1) T^T, and the tangent lines
    x = const of that conic solve C*_33 x^2 - 2 C*_13 x + C*_11 = 0 (same for y). This
    holds while the whole disk lies beyond the near plane; otherwise the box is the
    screen. The low-pass part is the circle |x - c|^2 <= level / LOWPASS_INV_VAR.
    """
    t = transforms.detach()
    dual = t @ torch.diag_embed(torch.stack([level, level, -torch.ones_like(level)], -1)) @ t.transpose(1, 2)
    c33 = dual[:, 2, 2]
    # Nearest depth on the disk: w_centre - sqrt(level) * |(T_31, T_32)|.
    in_front = t[:, 2, 2] - level.sqrt() * t[:, 2, :2].norm(dim=-1) > near
    safe = torch.where(in_front, c33, -torch.ones_like(c33))
    centre = dual[:, :2, 2] / safe[:, None]                                    # [G, 2]
    half = (dual[:, :2, 2].square() - dual[:, [0, 1], [0, 1]] * c33[:, None]).clamp_min(0).sqrt() / safe.abs()[:, None]
    screen = torch.tensor([width, height], dtype=t.dtype)
    lo = torch.where(in_front[:, None], centre - half, torch.zeros_like(centre) - 1)
    hi = torch.where(in_front[:, None], centre + half, screen + 1)
    radius = (level / LOWPASS_INV_VAR).sqrt()[:, None]
    c = means2d.detach()
    lo, hi = torch.minimum(lo, c - radius), torch.maximum(hi, c + radius)
    return (lo + hi) / 2, (hi - lo) / 2


def project(model: SurfelModel, camera: Camera,
            near: float = NEAR_PLANE) -> tuple[Projected, torch.Tensor, torch.Tensor]:
    """Stage 1. Returns the visible surfels, the screen means of ALL surfels [G, 2] (for
    densification gradients) and the visibility mask [G]."""
    rot_wc = camera.world_to_camera()[:3, :3]            # [3, 3] float64
    intrinsics = torch.tensor([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
                              dtype=torch.float64)
    means = model.means.double()
    p_cam = camera.to_camera(means)                      # [G, 3]
    depth = p_cam[:, 2]
    in_front = depth > near
    z = torch.where(in_front, depth, torch.ones_like(depth))
    means2d = camera.to_pixels(p_cam, z)                 # [G, 2]
    axes = rot_wc @ quaternion_to_rotation(model.quats.double())        # [G, 3, 3] t_u, t_v, normal in camera frame
    scales = model.log_scales.double().clamp(-30.0, 30.0).exp()         # [G, 2]
    tangents = intrinsics @ (axes[:, :, :2] * scales[:, None, :])       # [G, 3, 2]
    # K p_cam written through means2d, so the screen-space gradient reaches the means2d leaf.
    centre = torch.cat([means2d, torch.ones_like(z)[:, None]], dim=-1) * z[:, None]   # [G, 3]
    transforms = torch.cat([tangents, centre[:, :, None]], dim=-1)      # [G, 3, 3]
    normals = axes[:, :, 2]
    normals = torch.where(((normals * p_cam).sum(-1) > 0)[:, None], -normals, normals)

    opacities = torch.sigmoid(model.opacity_logits.double())
    level = 2.0 * torch.log((opacities * 255.0).clamp_min(1.0)).detach()
    box_centres, extents = screen_boxes(transforms, means2d, level, near, camera.width, camera.height)
    on_screen = ((box_centres + extents > 0) & (box_centres - extents < torch.tensor(
        [camera.width, camera.height], dtype=torch.float64))).all(dim=-1)
    finite = torch.isfinite(transforms.detach()).flatten(1).all(-1) & torch.isfinite(extents).all(-1)
    visible = in_front & (opacities * 255.0 > 1.0) & on_screen & finite

    ids = visible.nonzero().squeeze(1)
    ids = ids[torch.argsort(depth[ids], stable=True)]   # front to back, ties by index
    dirs = means[ids] - camera.center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    colors = eval_sh(model.sh[ids], dirs.to(model.sh.dtype))
    projected = Projected(ids=ids, means2d=means2d[ids], transforms=transforms[ids], opacities=opacities[ids],
                          colors=colors, normals=normals[ids], depths=depth[ids], box_centres=box_centres[ids],
                          extents=extents[ids])
    return projected, means2d, visible


def splat_alpha(proj: Projected, pairs: Pairs, tile: int, width: int, height: int,
                near: float = NEAR_PLANE) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 3: alpha [M, P] and depth [M, P] of each pair at each of the P = tile^2 pixels
    of its tile (alpha zero below 1/255, and at the pixels of the last tile row and column
    that lie past the image's width x height: no fragment there, so a visibility pass counts
    only what the image shows).

    With T's rows a, b, c the intersection q = (a - x c) x (b - y c) = a x b + x (b x c) +
    y (c x a) is affine in the pixel (x, y), so over a tile it is one [M, 3, 3] x [3, P]
    product; and c . q = det T for every pixel, so the depth is det T / q_3.
    """
    offsets = torch.arange(tile * tile)
    ox, oy = (offsets % tile).double(), (offsets // tile).double()
    monomials = torch.stack([torch.ones_like(ox), ox, oy])                              # [3, P]
    corner = torch.stack([(pairs.tile % pairs.tiles_x) * tile + 0.5,
                          (pairs.tile // pairs.tiles_x) * tile + 0.5], dim=-1).double()  # [M, 2] first pixel
    a, b, c = proj.transforms[pairs.splat].unbind(1)                                     # [M, 3] each
    along_x, along_y = torch.linalg.cross(b, c), torch.linalg.cross(c, a)
    at_corner = torch.linalg.cross(a, b) + corner[:, :1] * along_x + corner[:, 1:] * along_y
    q = torch.stack([at_corner, along_x, along_y], dim=-1) @ monomials                  # [M, 3, P] ~ (u, v, 1)
    det = q[:, 2]
    numer = q[:, 0].square() + q[:, 1].square()
    det_t = (c * torch.linalg.cross(a, b)).sum(-1)[:, None]                             # depth * det, [M, 1]
    hit = (numer < RHO_MAX * det.square()) & ((det_t - near * det) * det > 0)
    safe_det = torch.where(hit, det, torch.ones_like(det))
    rho_surfel = torch.where(hit, numer / safe_det.square(), torch.full_like(det, RHO_MAX))
    d = corner - proj.means2d[pairs.splat]                                              # [M, 2]
    rho_lowpass = LOWPASS_INV_VAR * ((d[:, :1] + ox).square() + (d[:, 1:] + oy).square())
    surfel_wins = rho_surfel <= rho_lowpass
    rho = torch.where(surfel_wins, rho_surfel, rho_lowpass)
    log_alpha = (torch.log(proj.opacities[pairs.splat])[:, None] - 0.5 * rho).clamp_max(math.log(ALPHA_MAX))
    alpha = log_alpha.float().exp()
    in_image = ((corner[:, :1] + ox < width) & (corner[:, 1:] + oy < height))                # [M, P]
    alpha = torch.where((alpha >= ALPHA_MIN) & in_image, alpha, torch.zeros_like(alpha))
    depth = torch.where(surfel_wins, det_t / safe_det, proj.depths[pairs.splat][:, None])
    return alpha, depth.float()


def surfel_fragments(model: SurfelModel, camera: Camera, tile: int, near: float
                     ) -> tuple[Projected, torch.Tensor, torch.Tensor, Pairs, torch.Tensor, Fragments]:
    """Stages 1-3: the projection, screen means of all surfels [G, 2] and their visibility [G],
    the tile pairs, each pair's depth at each pixel of its tile [M, P], and the fragments."""
    proj, means2d_all, visible = project(model, camera, near)
    pairs = intersect(proj.box_centres, proj.extents, camera.width, camera.height, tile)
    alpha, depth = splat_alpha(proj, pairs, tile, camera.width, camera.height, near)
    return proj, means2d_all, visible, pairs, depth, fragments(alpha, pairs)


@dataclass
class SurfelView:
    """One camera's mask-independent state (stages 1-3 and each fragment's values), composited
    per batch of keep-masks. Built by `surfel_view`; a `phd_core.renderers.View`."""

    camera: Camera
    background: torch.Tensor  # [3]
    num_units: int            # G, the width of a keep-mask
    frags: Fragments          # E fragments grouped by covered pixel, front to back
    values: torch.Tensor      # [E, C] colour and depth of each fragment (and normal, depth^2 with geometry)
    pair_units: torch.Tensor  # [M] long, the model surfel of each tile pair: fragment e is of pair_units[frags.pair[e]]
    pairs: Pairs              # the tile grid only (tiles_x, tiles_y), for untile
    tile: int
    compositor: Compositor
    means2d: torch.Tensor     # [G, 2] screen positions of all surfels (densification gradients)
    visible: torch.Tensor     # [G] bool, survived culling

    @property
    def nbytes(self) -> int:
        f = self.frags
        return sum(t.numel() * t.element_size() for t in (f.alpha, f.pair, f.start, f.row, f.row_ptr, f.pixel,
                                                         self.values, self.pair_units, self.means2d, self.visible))

    def accumulate(self, keep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Stage 4 once per keep-mask (keep: [N, G] bool, None = all surfels): accumulated values
        [N, H, W, C], alpha [N, H, W] and RGB over the background [N, H, W, 3]."""
        keep = check_keep(keep, self.num_units)
        cam = self.camera
        return composite_images(self.compositor, self.frags, self.values, keep,
                                self.pair_units.index_select(0, self.frags.pair), self.pairs, self.tile, cam.width,
                                cam.height, self.background)

    def render(self, keep: torch.Tensor | None = None, signal: str = DEFAULT_SIGNAL) -> torch.Tensor:
        acc_v, acc_a, _ = self.accumulate(keep)
        return signal_image(signal, acc_v[..., :3], acc_a, self.background)


def surfel_view(model: SurfelModel, camera: Camera, background: torch.Tensor, *, tile: int = DEFAULT_TILE,
                near: float = NEAR_PLANE, compositor: str | None = None, geometry: bool = False) -> SurfelView:
    """Stages 1-3 for `camera` and the values each fragment composites: colour and the depth of
    its intersection (geometry: also the normal and the squared depth). Differentiable."""
    proj, means2d_all, visible, pairs, depth, frags = surfel_fragments(model, camera, tile, near)
    per_tile = tile * tile
    splat = pairs.splat[frags.pair]                                     # [E] index into proj
    in_tile = frags.pixel.index_select(0, frags.row) % per_tile
    entry_depth = depth.reshape(-1).index_select(0, frags.pair * per_tile + in_tile)[:, None]   # [E, 1]
    columns = [proj.colors.float()[splat], entry_depth]
    if geometry:
        columns += [proj.normals.float()[splat], entry_depth.square()]
    empty = torch.empty(0, dtype=torch.long)
    grid = Pairs(tile=empty, splat=empty, tile_start=empty, tiles_x=pairs.tiles_x, tiles_y=pairs.tiles_y)
    return SurfelView(camera=camera, background=background, num_units=model.num_splats, frags=frags,
                      values=torch.cat(columns, dim=-1), pair_units=proj.ids[pairs.splat], pairs=grid, tile=tile,
                      compositor=pick_compositor(compositor), means2d=means2d_all, visible=visible)


def rasterize_surfels(model: SurfelModel, camera: Camera, background: torch.Tensor,
                      keep: torch.Tensor | None = None, *, tile: int = DEFAULT_TILE, near: float = NEAR_PLANE,
                      compositor: str | None = None, geometry: bool = False) -> SurfelOutput:
    """Render `camera` once per keep-mask (keep: [N, G] bool, None = all surfels).

    Differentiable with respect to the model's tensors with either compositor (None: the
    default, `pick_compositor`).
    geometry: also composite normals and the depth distortion (for training and normal maps).
    """
    keep = check_keep(keep, model.num_splats)
    view = surfel_view(model, camera, background, tile=tile, near=near, compositor=compositor, geometry=geometry)
    acc_v, acc_a, rgb = view.accumulate(keep)
    out = SurfelOutput(rgb=rgb, color=acc_v[..., :3], alpha=acc_a, depth=acc_v[..., 3], means2d=view.means2d,
                       visible=view.visible)
    if geometry:
        out.normal = acc_v[..., 4:7]
        out.distortion = (acc_a * acc_v[..., 7] - acc_v[..., 3].square()).clamp_min(0.0)
    return out


# What one `rasterize_surfels` call holds, in bytes per item (upper envelopes of the peaks
# bench/bench_memory.py measures): per surfel of the model (stage 1's [G, 3, 3] float64 maps and
# screen boxes), per visible surfel and per SH coefficient of one, per tile/surfel pair (the
# int64 pair lists and their sort), per pair and pixel of its tile (stage 3's [M, 3, P] float64
# intersections and [M, P] temporaries), per fragment (their int64 bookkeeping and values), per
# pixel of the tile grid; and per keep-mask: its flag for each fragment and the images it composites.
# The live peak is about 2/3 of these: the rest is the heap that phd_core.allocator keeps between
# renders of different views (measured over 4 views at 200x200: 1.52 GB resident for 1.07 GB at
# the first render).
SURFEL_BYTES = 1024
VISIBLE_BYTES, SH_COEFF_BYTES = 96, 48
PAIR_BYTES, PAIR_PIXEL_BYTES = 24, 168
FRAGMENT_BYTES = 72
GRID_PIXEL_BYTES = 48
MASK_FRAGMENT_BYTES, MASK_GRID_PIXEL_BYTES = 1, 96


@torch.no_grad()
def surfel_counts(renderer: "SurfelRenderer", camera: Camera) -> tuple[int, int, int]:
    """(visible surfels, tile/surfel pairs, a bound on fragments) of `camera`, from stage 1 run
    MEMORY_PROBE_UNITS surfels at a time (so this costs little memory whatever the model)."""
    model, counts = renderer.model, [0, 0, 0]
    for start in range(0, model.num_splats, MEMORY_PROBE_UNITS):
        proj, _, _ = project(model.subset(slice(start, start + MEMORY_PROBE_UNITS)), camera, renderer.near)
        pairs, pixels = box_counts(proj.box_centres, proj.extents, camera.width, camera.height, renderer.tile)
        for i, n in enumerate((len(proj.ids), pairs, pixels)):
            counts[i] += n
    return counts[0], counts[1], counts[2]


# What a SurfelView keeps (its nbytes), in bytes per item: per fragment its alpha, pair, start and
# row (4 + 8 x 3) and its colour and depth (16); per covered pixel (at most the tile grid's) its row
# offset and tile-layout position (8 + 8); per tile pair its surfel (8); per surfel its screen
# position (float64) and culling flag.
VIEW_FRAGMENT_BYTES, VIEW_GRID_PIXEL_BYTES, VIEW_PAIR_BYTES, VIEW_SURFEL_BYTES = 44, 16, 8, 17


def surfel_memory(renderer: "SurfelRenderer", camera: Camera) -> RenderMemory:
    """Bounds of `prepare(camera)` and its renders (the family's `memory`): `fixed` is what
    projecting, listing and rasterising hold at their peak, `kept` what the view keeps."""
    visible, pairs, fragments_ = surfel_counts(renderer, camera)
    model, tile = renderer.model, renderer.tile
    grid = math.ceil(camera.width / tile) * math.ceil(camera.height / tile) * tile * tile
    fixed = (SURFEL_BYTES * model.num_splats + (VISIBLE_BYTES + SH_COEFF_BYTES * model.sh.shape[1]) * visible
             + pairs * (PAIR_BYTES + PAIR_PIXEL_BYTES * tile * tile) + FRAGMENT_BYTES * fragments_
             + GRID_PIXEL_BYTES * grid)
    kept = (VIEW_FRAGMENT_BYTES * fragments_ + VIEW_GRID_PIXEL_BYTES * grid + VIEW_PAIR_BYTES * pairs
            + VIEW_SURFEL_BYTES * model.num_splats)
    return RenderMemory(fixed=fixed, kept=kept,
                        per_mask=MASK_FRAGMENT_BYTES * fragments_ + MASK_GRID_PIXEL_BYTES * grid,
                        fragments=fragments_)


class SurfelRenderer(SplatRenderer):
    """A trained 2DGS model behind the renderer protocol; dropout units are the surfels.

    `prepare` returns a `SurfelView`: one projection, tile list, depth order and set of
    fragments per camera, composited per batch of keep-masks with the renderer's compositor,
    and walked in place by the visibility pass."""

    kind = "2dgs"
    model_type = SurfelModel
    model: SurfelModel          # __init__ refuses any other model (model_type)
    rasterizer = staticmethod(rasterize_surfels)

    @torch.no_grad()
    def prepare(self, camera: Camera) -> SurfelView:
        return surfel_view(self.model, camera, self.background, tile=self.tile, near=self.near,
                           compositor=self.compositor)

    def fragment_rows(self, view: View) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                                 torch.Tensor, Pairs]:
        if not isinstance(view, SurfelView):
            view = self.prepare(view.camera)
        f = view.frags
        return f.row_ptr, f.alpha, f.pair, view.pair_units, f.pixel, view.pairs

    @torch.no_grad()
    def render_full(self, camera: Camera, keep: torch.Tensor | None = None, *,
                    geometry: bool = False) -> SurfelOutput:
        return rasterize_surfels(self.model, camera, self.background, keep, tile=self.tile, near=self.near,
                                 compositor=self.compositor, geometry=geometry)
