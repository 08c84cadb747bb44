"""The radiance field: input encodings (pe, spe, hash), the occupancy grid and the network.

The first fully connected layer's hidden units are the dropout units; `mask_scale` turns a
keep-mask into the per-unit factor (0 for dropped units, 1 or the rescale for survivors)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import CHUNK_SAMPLES, NeRFConfig

DENSITY_SHIFT = -1.0        # sigma = softplus(raw - 1): a faint medium at initialisation, not fog
HASH_PRIMES = (1, 2654435761, 805459861)   # per-axis hash multipliers (InstantNGP)
HASH_INIT = 1e-4            # hash table entries start uniform in [-1e-4, 1e-4]


# --------------------------------------------------------------------------- encodings

def band_weights(bands: int, visible: float | None) -> Tensor | None:
    """FreeNeRF frequency mask: weight of each band when `visible` bands are revealed.

    Band k gets clip(visible - k, 0, 1): the first floor(visible) bands are fully on, the
    next one is partly on, the rest are off. None (no mask) when visible is None.
    """
    if visible is None:
        return None
    return (visible - torch.arange(bands, dtype=torch.float32)).clamp(0.0, 1.0)


class PositionalEncoding(nn.Module):
    """x [P, 3] in [-1, 1] -> [P, 3 + 6 L]: x, then for k < L: sin(2^k pi x), cos(2^k pi x).

    A band is one frequency (its 3 sines and 3 cosines); `weights` [L] scales each band
    (FreeNeRF's mask). The raw x is never masked.
    """

    scales: Tensor                  # a buffer registered in __init__

    def __init__(self, freqs: int):
        super().__init__()
        self.bands = freqs
        self.out_dim = 3 + 6 * freqs
        self.register_buffer("scales", math.pi * 2.0 ** torch.arange(freqs, dtype=torch.float32), persistent=False)

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        angles = x[:, None, :] * self.scales[:, None]                  # [P, L, 3]
        enc = torch.cat([torch.sin(angles), torch.cos(angles)], -1)    # [P, L, 6]
        if weights is not None:
            enc = enc * weights[:, None]
        return torch.cat([x, enc.flatten(1)], -1)


class HashEncoding(nn.Module):
    """Multiresolution hash grid: x [P, 3] in [-1, 1] -> [P, levels * features].

    Level l has a grid of resolution N_l = floor(base * b^l) cells per axis (b spaces the
    levels geometrically from base to max). Its (N_l + 1)^3 vertices index a table of
    T = 2^log2_size feature vectors: directly when they fit, else through the spatial hash
    (x * 1 XOR y * 2654435761 XOR z * 805459861) mod T, where distinct vertices collide.
    A point's features are the trilinear interpolation of its cell's 8 vertices.
    `weights` [levels] scales each level (the FreeNeRF mask, applied coarse to fine).
    """

    # buffers registered in __init__ (nn.Module's __getattr__ would type them as Tensor | Module)
    resolutions: Tensor
    dense: Tensor
    strides: Tensor
    primes: Tensor

    def __init__(self, levels: int, features: int, log2_size: int, base: int, finest: int):
        super().__init__()
        self.bands = levels
        self.size = 1 << log2_size
        self.out_dim = levels * features
        growth = math.exp((math.log(finest) - math.log(base)) / (levels - 1)) if levels > 1 else 1.0
        res = [int(math.floor(base * growth ** level + 1e-9)) for level in range(levels)]
        self.register_buffer("resolutions", torch.tensor(res, dtype=torch.int64), persistent=False)
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= self.size for r in res]), persistent=False)
        self.table = nn.Parameter(torch.empty(levels, self.size, features).uniform_(-HASH_INIT, HASH_INIT))
        res1 = self.resolutions + 1
        self.register_buffer("strides", torch.stack([torch.ones_like(res1), res1, res1 * res1], -1), persistent=False)
        self.register_buffer("primes", torch.tensor(HASH_PRIMES), persistent=False)

    def corner_rows(self, cell: Tensor) -> Tensor:
        """Table rows [P, L, 8] of the 8 vertices of integer cells [P, L, 3] (one cell per level).

        Corner c is the vertex cell + ((c >> 2) & 1, (c >> 1) & 1, c & 1); rows index the
        flattened [levels * T] table. The terms are computed per axis and combined, not per
        vertex: most of the cost of a hash grid on a CPU is this arithmetic.
        """
        both = torch.stack([cell, cell + 1], -1)                          # [P, L, 3, 2] lower/upper vertex
        dx, dy, dz = (both * self.strides[:, :, None]).unbind(2)          # dense: x + (r+1) y + (r+1)^2 z
        hx, hy, hz = (both * self.primes[:, None]).unbind(2)              # hashed: x p0 ^ y p1 ^ z p2
        dense = dx[..., :, None, None] + dy[..., None, :, None] + dz[..., None, None, :]       # [P, L, 2, 2, 2]
        hashed = (hx[..., :, None, None] ^ hy[..., None, :, None] ^ hz[..., None, None, :]) & (self.size - 1)
        rows = torch.where(self.dense[:, None, None, None], dense, hashed).flatten(2)          # [P, L, 8]
        return rows + torch.arange(len(self.resolutions))[:, None] * self.size

    def forward(self, x: Tensor, weights: Tensor | None = None) -> Tensor:
        features = self.table.shape[2]
        unit = ((x + 1) * 0.5).clamp(0.0, 1.0)                                    # [P, 3]
        pos = unit[:, None, :] * self.resolutions[:, None]                         # [P, L, 3]
        cell = pos.floor().clamp_max(self.resolutions[:, None] - 1)                # [P, L, 3]
        frac = pos - cell                                                          # [P, L, 3] in [0, 1]
        values = self.table.view(-1, features)[self.corner_rows(cell.long())]     # [P, L, 8, F]
        wx, wy, wz = torch.stack([1 - frac, frac], -1).unbind(2)                   # [P, L, 2] each
        w = (wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]).flatten(2)  # [P, L, 8]
        out = (w[..., None] * values).sum(2)                                       # [P, L, F]
        if weights is not None:
            out = out * weights[:, None]
        return out.flatten(1)


# --------------------------------------------------------------------------- occupancy grid

class OccupancyGrid(nn.Module):
    """A res^3 grid over the scene box: which cells may hold density.

    `density` [res, res, res] is a running estimate of each cell's largest density;
    `occupied` is density > threshold, where the threshold is the density at which a ray
    crossing the cell's diagonal loses `grid_threshold` of its light. Rendering evaluates the
    network only at samples inside occupied cells. A new grid is fully occupied.
    """

    # buffers registered in __init__ (nn.Module's __getattr__ would type them as Tensor | Module)
    lo: Tensor
    size: Tensor
    density: Tensor
    occupied: Tensor

    def __init__(self, resolution: int, bounds: list[list[float]], threshold: float):
        super().__init__()
        self.resolution = resolution
        box = torch.tensor(bounds, dtype=torch.float32)
        self.register_buffer("lo", box[0], persistent=False)
        self.register_buffer("size", box[1] - box[0], persistent=False)
        cell_diagonal = float((self.size / resolution).norm())
        self.density_threshold = -math.log1p(-threshold) / cell_diagonal
        self.register_buffer("density", torch.full((resolution,) * 3, math.inf))
        self.register_buffer("occupied", torch.ones((resolution,) * 3, dtype=torch.bool))

    @property
    def fraction(self) -> float:
        """Share of the box marked occupied."""
        return float(self.occupied.float().mean())

    def cells(self, points: Tensor) -> Tensor:
        """Flat cell index of points [P, 3] (clamped into the grid): [P] long."""
        ijk = ((points - self.lo) / self.size * self.resolution).floor().long().clamp(0, self.resolution - 1)
        return (ijk[:, 0] * self.resolution + ijk[:, 1]) * self.resolution + ijk[:, 2]

    def lookup(self, points: Tensor) -> Tensor:
        """[P] bool: the point lies in an occupied cell."""
        return self.occupied.flatten()[self.cells(points)]

    def cell_points(self, offsets: Tensor) -> Tensor:
        """One point per cell at fractional offset(s) inside it: offsets [C or 1, 3] -> [C, 3]."""
        r = self.resolution
        idx = torch.arange(r ** 3)
        ijk = torch.stack([idx // (r * r), (idx // r) % r, idx % r], -1).float()
        return self.lo + (ijk + offsets) / r * self.size

    def set_density(self, density: Tensor, allowed: Tensor | None = None) -> None:
        """Replace the estimate ([res^3] or [res, res, res]) and recompute `occupied`."""
        self.density.copy_(density.reshape(self.density.shape))
        occupied = self.density > self.density_threshold
        self.occupied.copy_(occupied if allowed is None else occupied & allowed.reshape(occupied.shape))


# --------------------------------------------------------------------------- the network

class RadianceField(nn.Module):
    """The MLP radiance field with its encoding and occupancy grid.

    Parameters are initialised from `seed` without touching the global random state.
    The dropout units are the `width` outputs of `first` (after its activation).
    """

    center: Tensor                  # buffers registered in __init__
    half_size: Tensor

    def __init__(self, config: NeRFConfig, seed: int = 0):
        super().__init__()
        self.config = config.validate()
        c = config
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.encoding: HashEncoding | PositionalEncoding
            if c.encoding == "hash":
                self.encoding = HashEncoding(c.hash_levels, c.hash_features, c.hash_log2_size,
                                             c.hash_base_resolution, c.hash_max_resolution)
            else:
                self.encoding = PositionalEncoding(c.pos_freqs)
            self.dir_encoding = PositionalEncoding(c.dir_freqs)
            enc_dim, w = self.encoding.out_dim, c.width
            self.first = nn.Linear(enc_dim, w)
            self.hidden = nn.ModuleList(nn.Linear(w, w) for _ in range(c.depth - 1))
            # Layer `skip_layer` (0 = first) also sees the encoded input: a concat, stored as a
            # second weight so that its input term is computed once for all keep-masks.
            self.skip_layer = c.depth // 2 if c.skip and c.depth >= 3 else 0
            self.skip = nn.Linear(enc_dim, w, bias=False) if self.skip_layer else None
            self.density_head = nn.Linear(w, 1)
            self.feature = nn.Linear(w, w)
            self.color_feature = nn.Linear(w, c.color_width)
            self.color_dir = nn.Linear(self.dir_encoding.out_dim, c.color_width, bias=False)
            self.color_out = nn.Linear(c.color_width, 3)
        self.grid = OccupancyGrid(c.grid_resolution, c.bounds, c.grid_threshold)
        box = torch.tensor(c.bounds, dtype=torch.float32)
        self.register_buffer("center", (box[0] + box[1]) / 2, persistent=False)
        self.register_buffer("half_size", (box[1] - box[0]) / 2, persistent=False)

    # The pieces, in the order a sample goes through them.
    def encode(self, points: Tensor, weights: Tensor | None = None) -> Tensor:
        """World points [P, 3] -> encoded [P, E] (positions normalised to [-1, 1] in the box)."""
        return self.encoding((points - self.center) / self.half_size, weights)

    def first_layer(self, enc: Tensor) -> Tensor:
        """[P, E] -> the dropout units [P, width]: sin for spe, ReLU otherwise."""
        pre = self.first(enc)
        return torch.sin(pre) if self.config.encoding == "spe" else F.relu(pre)

    def trunk(self, h: Tensor, skip_term: Tensor | None) -> Tensor:
        """Layers after the first: h [n, P, width] -> [n, P, width]."""
        for i, layer in enumerate(self.hidden, start=1):
            pre = layer(h)
            if i == self.skip_layer:
                pre = pre + skip_term
            h = F.relu(pre)
        return h

    def sigma(self, h: Tensor) -> Tensor:
        """Density >= 0 from trunk features: [..., width] -> [...]."""
        return F.softplus(self.density_head(h)[..., 0] + DENSITY_SHIFT)

    def color(self, h: Tensor, dir_term: Tensor) -> Tensor:
        """RGB in (0, 1) from trunk features [n, P, width] and the direction term [P, color_width]."""
        return torch.sigmoid(self.color_out(F.relu(self.color_feature(self.feature(h)) + dir_term)))

    def units(self, points: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """At world points [P, 3]: the dropout units [P, W] and the skip layer's input term [P, W]."""
        enc = self.encode(points, weights)
        return self.first_layer(enc), (self.skip(enc) if self.skip is not None else None)

    def density(self, points: Tensor, weights: Tensor | None = None) -> Tensor:
        """Density of the full model at world points [P, 3] -> [P] (no colour branch)."""
        return self.units_density(*self.units(points, weights))

    def units_density(self, h1: Tensor, skip_term: Tensor | None) -> Tensor:
        """Density of the full model from the dropout units [P, W] and the skip term: [P]."""
        return self.sigma(self.trunk(h1[None], skip_term))[0]

    def stem(self, points: Tensor, dirs: Tensor, weights: Tensor | None = None,
             dir_weights: Tensor | None = None) -> tuple[Tensor, Tensor | None, Tensor]:
        """The mask-independent part at points [P, 3] seen along unit dirs [P, 3]: the
        dropout units [P, W], the skip layer's input term [P, W] and the direction term [P, CW]."""
        return *self.units(points, weights), self.color_dir(self.dir_encoding(dirs, dir_weights))

    def heads(self, stem: tuple[Tensor, Tensor | None, Tensor], keep: Tensor | None = None,
              rescale: bool = False) -> tuple[Tensor, Tensor]:
        """The rest of the network once per keep-mask [n, W] (None: n = 1, all units kept):
        density [n, P] and RGB [n, P, 3]."""
        h1, skip_term, dir_term = stem
        h = h1[None] if keep is None else h1[None] * mask_scale(keep, rescale)[:, None, :]
        h = self.trunk(h, skip_term)                                      # [n, P, W]
        return self.sigma(h), self.color(h, dir_term)

    def forward(self, points: Tensor, dirs: Tensor, keep: Tensor | None = None, *, rescale: bool = False,
                weights: Tensor | None = None, dir_weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Density [n, P] and RGB [n, P, 3] at points [P, 3] seen along unit dirs [P, 3]."""
        return self.heads(self.stem(points, dirs, weights, dir_weights), keep, rescale)

    @torch.no_grad()
    def cell_density(self, generator: torch.Generator | None = None, subdivisions: int = 3) -> Tensor:
        """Largest density of the full model in each occupancy-grid cell: [res^3].

        With a generator: at one random point per cell (the cheap training-time probe).
        Without: the max over the centres of subdivisions^3 sub-cells (deterministic).
        """
        grid = self.grid
        if generator is not None:
            offsets = [torch.rand(grid.resolution ** 3, 3, generator=generator)]
        else:
            s = (torch.arange(subdivisions) + 0.5) / subdivisions
            offsets = list(torch.cartesian_prod(s, s, s)[:, None, :])
        best = torch.zeros(grid.resolution ** 3)
        for offset in offsets:
            points = grid.cell_points(offset)
            for start in range(0, points.shape[0], CHUNK_SAMPLES):
                chunk = slice(start, start + CHUNK_SAMPLES)
                best[chunk] = torch.maximum(best[chunk], self.density(points[chunk]))
        return best


def mask_scale(keep: Tensor, rescale: bool) -> Tensor:
    """Keep-masks [n, W] bool -> float multipliers: 0/1, or 0/(1/kept share) with rescale
    (like standard dropout; a mask that keeps nothing stays all zero)."""
    scale = keep.float()
    if rescale:
        kept = scale.mean(1, keepdim=True)
        scale = torch.where(kept > 0, scale / kept.clamp_min(1e-12), torch.zeros_like(scale))
    return scale
