"""NeRF on the CPU, behind the same renderer protocol as Gaussian Splatting.

A radiance field in the original NeRF shape, sized for two CPU cores:

    points -> encoding -> FIRST layer (the dropout units) -> trunk (with one skip) -> density
                                                                 \\-> feature + view direction -> RGB

Encodings: `pe` (positional encoding, ReLU after the first layer), `spe` (the same PE with a
sine after the first layer: sinusoidal PE, Sun et al. 2024) and `hash` (multiresolution hash
grid, InstantNGP style). `hash` is kept on purpose: hash collisions make any ensemble method,
PH-Dropout included, blind to what the model got wrong (paper, Section 3.4), and users should
be able to see that on their own scenes.

Rendering (`render_rays`): rays are clipped to the scene box and to [near, far], cut into
`samples` equal bins (a random point per bin in training, the bin centre at inference), the
samples in cells the occupancy grid marks empty are dropped, the network runs on the rest
and the compositing gives the dropped samples zero density. Transmittance is accumulated in
log space. Everything up to and including the first layer is computed once per ray chunk;
the rest of the network runs once per keep-mask, batched.

Checkpoints (`save_nerf` / `load_nerf`) are safetensors files: tensors that cannot execute
code on load, plus a JSON config in the header and the training cameras as JSON frames.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import Tensor, nn

from .cameras import Camera, cameras_from_json
from .errors import InputError, check_float, check_int
from .fileio import write_bytes_atomic
from .protocol import check_keep

ENCODINGS = ("pe", "spe", "hash")
CHECKPOINT_FORMAT = "phd-nerf"
CHECKPOINT_VERSION = "1"
CAMERAS_TENSOR = "training_cameras_json"  # uint8 JSON bytes: [frame, ...] from Camera.to_frame()
DENSITY_SHIFT = -1.0        # sigma = softplus(raw - 1): a faint medium at initialisation, not fog
HASH_PRIMES = (1, 2654435761, 805459861)   # per-axis hash multipliers (InstantNGP)
HASH_INIT = 1e-4            # hash table entries start uniform in [-1e-4, 1e-4]
# Memory bounds of one rendering step: samples per ray chunk, and elements of one
# [masks, kept samples, width] activation (2^23 float32 = 32 MB; a few are alive at once).
CHUNK_SAMPLES = 1 << 16
CHUNK_ELEMENTS = 1 << 23
MAX_HEADER_BYTES = 100 << 20


# --------------------------------------------------------------------------- configuration

@dataclass
class NeRFConfig:
    """Everything needed to rebuild a model: stored as JSON in every checkpoint.

    Defaults are sized for 100x100 training on 2 shared CPU cores (docs/nerf.md): a
    4-layer, 64-wide trunk (64 dropout units) costs about 27k multiply-adds per sample
    (128 wide: 91k, for +0.4 dB), and the occupancy grid keeps only the samples in
    occupied cells.
    """

    encoding: str = "pe"
    depth: int = 4                  # trunk layers, the first one included
    width: int = 64                 # trunk width = number of dropout units
    skip: bool = True               # re-inject the encoded position at layer depth // 2 (depth >= 3)
    color_width: int = 32           # hidden width of the view-dependent colour branch
    pos_freqs: int = 10             # PE frequencies for the position (pe, spe)
    dir_freqs: int = 4              # PE frequencies for the view direction (all encodings)
    hash_levels: int = 8
    hash_features: int = 2
    hash_log2_size: int = 15
    hash_base_resolution: int = 16
    hash_max_resolution: int = 512
    samples: int = 64               # samples per ray over [near, far] clipped to the box
    near: float = 2.0
    far: float = 6.0
    bounds: list[list[float]] = field(default_factory=lambda: [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])
    background: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    grid_resolution: int = 32
    grid_threshold: float = 0.01    # a cell is empty if a ray crossing its diagonal loses < 1% of its light
    freenerf_frequency: bool = False  # provenance: trained with FreeNeRF's frequency mask
    freenerf_occlusion: bool = False  # provenance: trained with FreeNeRF's occlusion penalty

    def validate(self) -> "NeRFConfig":
        """Raise `InputError` naming the first field out of range; return self."""
        if self.encoding not in ENCODINGS:
            raise InputError("encoding", f"must be one of {', '.join(ENCODINGS)}, got {self.encoding!r}")
        for name, lo, hi in (("depth", 1, 16), ("width", 1, 1024), ("color_width", 1, 1024),
                             ("pos_freqs", 0, 16), ("dir_freqs", 0, 8), ("hash_levels", 1, 32),
                             ("hash_features", 1, 8), ("hash_log2_size", 8, 24),
                             ("hash_base_resolution", 1, 4096), ("hash_max_resolution", 1, 8192),
                             ("samples", 1, 4096), ("grid_resolution", 1, 256)):
            check_int(getattr(self, name), name, lo, hi)
        if self.hash_max_resolution < self.hash_base_resolution:
            raise InputError("hash_max_resolution", f"must be >= hash_base_resolution ({self.hash_base_resolution}), "
                             f"got {self.hash_max_resolution}")
        for name in ("skip", "freenerf_frequency", "freenerf_occlusion"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(name, f"must be true or false, got {getattr(self, name)!r}")
        check_float(self.near, "near", 0.0)
        check_float(self.far, "far", 0.0)
        if not self.far > self.near:
            raise InputError("far", f"must exceed near ({self.near}), got {self.far}")
        check_float(self.grid_threshold, "grid_threshold", 0.0)
        if not 0 < self.grid_threshold < 1:
            raise InputError("grid_threshold", f"must lie in (0, 1), got {self.grid_threshold}")
        self.bounds = _check_bounds(self.bounds)
        self.background = parse_color("background", self.background)
        return self

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "NeRFConfig":
        """Validated config from a dict (unknown keys are an error)."""
        if not isinstance(values, dict):
            raise InputError("config", f"must be an object, got {type(values).__name__}")
        known = {f.name for f in fields(cls)}
        for key in values:
            if key not in known:
                raise InputError(str(key), "unknown NeRF setting")
        return cls(**values).validate()

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check_bounds(bounds: Any) -> list[list[float]]:
    try:
        box = torch.as_tensor(bounds, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise InputError("bounds", f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {bounds!r}") from None
    if tuple(box.shape) != (2, 3) or not torch.isfinite(box).all():
        raise InputError("bounds", f"must be two finite 3-vectors [min, max], got {bounds!r}")
    if not (box[1] > box[0]).all():
        raise InputError("bounds", f"max must exceed min on every axis, got {box.tolist()}")
    return box.tolist()


def parse_color(name: str, value: Any) -> list[float]:
    """'white', 'black' or three numbers in [0, 1] -> [r, g, b]."""
    if isinstance(value, str):
        named = {"white": [1.0, 1.0, 1.0], "black": [0.0, 0.0, 0.0]}
        if value not in named:
            raise InputError(name, f"must be 'white', 'black' or three numbers in [0, 1], got {value!r}")
        return named[value]
    try:
        color = [float(c) for c in value]
    except (TypeError, ValueError):
        raise InputError(name, f"must be three numbers in [0, 1], got {value!r}") from None
    if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
        raise InputError(name, f"must be three numbers in [0, 1], got {value!r}")
    return color


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

    def __init__(self, levels: int, features: int, log2_size: int, base: int, finest: int):
        super().__init__()
        self.bands = levels
        self.size = 1 << log2_size
        self.out_dim = levels * features
        growth = math.exp((math.log(finest) - math.log(base)) / (levels - 1)) if levels > 1 else 1.0
        res = [int(math.floor(base * growth ** l + 1e-9)) for l in range(levels)]
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

    def __init__(self, config: NeRFConfig, seed: int = 0):
        super().__init__()
        self.config = config.validate()
        c = config
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            if c.encoding == "hash":
                self.encoding: nn.Module = HashEncoding(c.hash_levels, c.hash_features, c.hash_log2_size,
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
        h1, skip_term = self.units(points, weights)
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


# --------------------------------------------------------------------------- volume rendering

def camera_rays(camera: Camera) -> tuple[Tensor, Tensor]:
    """Origins and unit directions of every pixel centre, row-major: ([H*W, 3], [H*W, 3]) float32."""
    j, i = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                          torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    # OpenGL camera: +x right, +y up, looking down -z; image rows grow downwards.
    d_cam = torch.stack([(i + 0.5 - camera.cx) / camera.fx, -(j + 0.5 - camera.cy) / camera.fy,
                         -torch.ones_like(i)], -1).reshape(-1, 3)
    dirs = d_cam @ camera.c2w[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = camera.center.expand_as(dirs)
    return origins.float().contiguous(), dirs.float().contiguous()


def ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances [R] of rays through the box [lo, hi] (entry >= exit: a miss)."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t_lo, t_hi = (lo - origins) / safe, (hi - origins) / safe
    return torch.minimum(t_lo, t_hi).amax(-1), torch.maximum(t_lo, t_hi).amin(-1)


def composite(sigma: Tensor, rgb: Tensor, delta: Tensor, t: Tensor, background: Tensor
              ) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha compositing of S segments per ray.

    sigma [..., S], rgb [..., S, 3], segment lengths delta and sample distances t [..., S]
    -> colour on `background` [..., 3], accumulated alpha [...], alpha-weighted depth [...]
    (divide by alpha for the mean depth). alpha_i = 1 - exp(-sigma_i delta_i); the
    transmittance before segment i is exp(-sum_{j<i} sigma_j delta_j), summed in log space.
    """
    tau = sigma * delta                                     # optical depth of each segment
    total = tau.cumsum(-1)
    log_t = tau - total                                     # -(sum over the previous segments)
    weights = torch.exp(log_t) * -torch.expm1(-tau)        # [..., S]
    acc = weights.sum(-1)
    color = (weights[..., None] * rgb).sum(-2) + torch.exp(-total[..., -1:]) * background
    return color, acc, (weights * t).sum(-1)


@dataclass
class RayOutput:
    rgb: Tensor      # [n, R, 3] composited on the background
    alpha: Tensor    # [n, R] accumulated opacity
    depth: Tensor    # [n, R] alpha-weighted distance along the ray
    sigma: Tensor | None  # [n, R, S] density of every sample (0 where skipped), if asked for
    samples: int     # samples the network evaluated


def ray_samples(model: RadianceField, origins: Tensor, dirs: Tensor, *, generator: torch.Generator | None = None,
                use_grid: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Sample rays [R, 3] in [near, far] clipped to the scene box, `samples` bins per ray.

    Returns distances t [R, S] (bin centres, or one uniform point per bin with a
    generator), bin lengths delta [R, S], points [R, S, 3] and valid [R, S]: the sample is
    on a ray that meets the box and (with use_grid) lies in an occupied cell.
    """
    c, grid = model.config, model.grid
    t_in, t_out = ray_box(origins, dirs, grid.lo, grid.lo + grid.size)
    t0, t1 = t_in.clamp_min(c.near), t_out.clamp_max(c.far)
    hit = t1 > t0                                                         # [R]
    span = torch.where(hit, t1 - t0, torch.zeros_like(t0))
    delta = (span / c.samples)[:, None].expand(-1, c.samples)             # [R, S]
    offset = (torch.rand(delta.shape, generator=generator) if generator is not None
              else torch.full(delta.shape, 0.5))
    t = t0[:, None] + (torch.arange(c.samples) + offset) * delta          # [R, S]
    points = origins[:, None] + t[..., None] * dirs[:, None]              # [R, S, 3]
    valid = hit[:, None].expand_as(t)
    if use_grid:
        valid = valid & grid.lookup(points.reshape(-1, 3)).view(t.shape)
    return t, delta, points, valid


def render_rays(model: RadianceField, origins: Tensor, dirs: Tensor, *, keep: Tensor | None = None,
                rescale: bool = False, use_grid: bool = True, generator: torch.Generator | None = None,
                weights: Tensor | None = None, dir_weights: Tensor | None = None,
                background: Tensor | None = None, with_sigma: bool = False) -> RayOutput:
    """Render rays [R, 3] once per keep-mask [n, W] (None: n = 1, the full model).

    Sampling, the grid lookup, the encoding and the first layer run once; the rest of the
    network runs over the masks in groups of at most CHUNK_ELEMENTS values per tensor.
    Deterministic unless a `generator` is given (stratified sampling, for training);
    `use_grid=False` evaluates every sample in the box. `weights`/`dir_weights` are the
    FreeNeRF band weights of the position and direction encodings. `with_sigma` also
    returns every sample's density (training's occlusion penalty needs it).
    """
    c = model.config
    bg = torch.tensor(c.background) if background is None else background
    t, delta, points, valid = ray_samples(model, origins, dirs, generator=generator, use_grid=use_grid)
    flat = valid.flatten().nonzero()[:, 0]                                # [K] evaluated samples
    stem = model.stem(points.reshape(-1, 3)[flat], dirs[flat // c.samples], weights, dir_weights)
    # Per mask: [K, width] activations and the dense [R * S, 3] colours of the compositing.
    per_mask = max(1, flat.numel() * c.width, t.numel() * 3)
    masks = [None] if keep is None else keep.split(max(1, CHUNK_ELEMENTS // per_mask))
    colors, alphas, depths, sigmas = [], [], [], []
    for sub in masks:
        sigma_k, rgb_k = model.heads(stem, sub, rescale)                  # [n, K], [n, K, 3]
        n = sigma_k.shape[0]
        sigma = sigma_k.new_zeros(n, t.numel()).index_copy(1, flat, sigma_k).view(n, *t.shape)
        rgb = rgb_k.new_zeros(n, t.numel(), 3).index_copy(1, flat, rgb_k).view(n, *t.shape, 3)
        color, acc, depth = composite(sigma, rgb, delta, t, bg)
        colors.append(color), alphas.append(acc), depths.append(depth)
        if with_sigma:
            sigmas.append(sigma)
    return RayOutput(torch.cat(colors), torch.cat(alphas), torch.cat(depths),
                     torch.cat(sigmas) if with_sigma else None, int(flat.numel()))


# --------------------------------------------------------------------------- the renderer

@dataclass
class NeRFOutput:
    rgb: Tensor     # [N, H, W, 3] composited on the background
    alpha: Tensor   # [N, H, W] accumulated opacity
    depth: Tensor   # [N, H, W] alpha-weighted distance along the ray (divide by alpha for the mean)


class NeRFRenderer:
    """A trained radiance field behind the renderer protocol (`phd_core.protocol.Renderer`).

    Dropout units are the first trunk layer's hidden units: keep [N, width]. One mask is
    one sub-network shared by every ray and sample of a render; survivors are not rescaled
    unless `rescale=True` (divide by the kept share, like the public reference code).
    """

    kind = "nerf"

    def __init__(self, model: RadianceField, training_cameras: list[Camera] | None = None, *,
                 rescale: bool = False, use_grid: bool = True):
        self.model = model.eval()
        self.training_cameras = training_cameras
        self.rescale = rescale
        self.use_grid = use_grid

    @property
    def num_units(self) -> int:
        return self.model.config.width

    @property
    def config(self) -> NeRFConfig:
        return self.model.config

    @torch.no_grad()
    def render_full(self, camera: Camera, keep: Tensor | None = None) -> NeRFOutput:
        keep = check_keep(keep, self.num_units)
        n = 1 if keep is None else keep.shape[0]
        origins, dirs = camera_rays(camera)
        rays_per_chunk = max(1, CHUNK_SAMPLES // self.config.samples)
        parts = [render_rays(self.model, origins[i:i + rays_per_chunk], dirs[i:i + rays_per_chunk], keep=keep,
                             rescale=self.rescale, use_grid=self.use_grid)
                 for i in range(0, origins.shape[0], rays_per_chunk)]
        h, w = camera.height, camera.width
        return NeRFOutput(torch.cat([p.rgb for p in parts], 1).view(n, h, w, 3),
                          torch.cat([p.alpha for p in parts], 1).view(n, h, w),
                          torch.cat([p.depth for p in parts], 1).view(n, h, w))

    def render(self, camera: Camera, keep: Tensor | None = None) -> Tensor:
        return self.render_full(camera, keep).rgb.clamp(0.0, 1.0)

    def describe(self) -> dict[str, Any]:
        c = self.config
        return {
            "kind": self.kind,
            "num_units": self.num_units,
            "encoding": c.encoding,
            "depth": c.depth,
            "width": c.width,
            "parameters": sum(p.numel() for p in self.model.parameters()),
            "samples_per_ray": c.samples,
            "near": c.near,
            "far": c.far,
            "bounds": {"min": c.bounds[0], "max": c.bounds[1]},
            "background": c.background,
            "occupancy_grid": {"resolution": c.grid_resolution, "occupied_fraction": self.model.grid.fraction,
                               "in_use": self.use_grid},
            "freenerf": {"frequency_mask": c.freenerf_frequency, "occlusion": c.freenerf_occlusion},
            "rescale": self.rescale,
            "has_training_cameras": self.training_cameras is not None,
        }


# --------------------------------------------------------------------------- checkpoints

def save_nerf(renderer_or_model: NeRFRenderer | RadianceField, path: str | Path,
              training_cameras: list[Camera] | None = None) -> None:
    """Write a checkpoint atomically (temp file + os.replace).

    Training cameras come from the renderer unless given.
    """
    write_bytes_atomic(path, nerf_bytes(renderer_or_model, training_cameras))


def nerf_bytes(renderer_or_model: NeRFRenderer | RadianceField, training_cameras: list[Camera] | None = None) -> bytes:
    """The checkpoint as bytes: safetensors with our metadata in the header."""
    if isinstance(renderer_or_model, NeRFRenderer):
        model = renderer_or_model.model
        training_cameras = training_cameras if training_cameras is not None else renderer_or_model.training_cameras
    else:
        model = renderer_or_model
    tensors = {name: t.detach().contiguous() for name, t in model.state_dict().items()}
    if training_cameras is not None:
        frames = json.dumps([camera.to_frame() for camera in training_cameras]).encode()
        tensors[CAMERAS_TENSOR] = torch.frombuffer(bytearray(frames), dtype=torch.uint8)
    metadata = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
                "config": json.dumps(model.config.to_dict())}
    return st_save(tensors, metadata=metadata)


def _header(data: bytes) -> dict | None:
    """The parsed safetensors header if `data` holds all of it, else None."""
    if len(data) < 8:
        return None
    (size,) = struct.unpack("<Q", data[:8])
    if size > MAX_HEADER_BYTES or len(data) < 8 + size:
        return None
    try:
        header = json.loads(data[8:8 + size])
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    return header if isinstance(header, dict) else None


def is_nerf_checkpoint(head: bytes) -> bool:
    """True if `head` (the first bytes of a file; 4 KiB is plenty) starts like our checkpoint:
    a safetensors header whose metadata says format "phd-nerf".

    The config and the tensor list are small, so the header of a default model is about
    2 KB. When `head` cuts the header short, the format marker is looked up in what it holds.
    """
    if len(head) < 9 or head[8:9] != b"{":
        return False
    (size,) = struct.unpack("<Q", head[:8])
    if size > MAX_HEADER_BYTES:
        return False
    header = _header(head)
    if header is None:
        return b'"format":"phd-nerf"' in head[8:8 + size]
    meta = header.get("__metadata__")
    return isinstance(meta, dict) and meta.get("format") == CHECKPOINT_FORMAT


def load_nerf(path: str | Path, **renderer_options: Any) -> NeRFRenderer:
    """Load a checkpoint file (see `load_nerf_bytes`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError("model", f"cannot read {path}: {exc.strerror or exc}") from None
    return load_nerf_bytes(data, path.name, **renderer_options)


def load_nerf_bytes(data: bytes, name: str = "model", **renderer_options: Any) -> NeRFRenderer:
    """Validate and load a checkpoint held in memory; no code runs on load.

    Every failure is an `InputError(field="model")` saying what is wrong: not a
    safetensors file, not ours, truncated or tampered (tensor missing, wrong shape or
    dtype, non-finite values), a config out of range, or unreadable training cameras.
    """
    def bad(reason: str) -> InputError:
        return InputError("model", f"{name}: {reason}")

    data = bytes(data)
    header = _header(data)
    if header is None and len(data) > 8 and data[8:9] == b"{" and b'"format":"phd-nerf"' in data:
        raise bad("truncated or corrupt safetensors header")
    if header is None or not is_nerf_checkpoint(data):
        raise bad("not a phd-nerf checkpoint (expected a safetensors file with format 'phd-nerf')")
    meta = header["__metadata__"]
    if meta.get("version") != CHECKPOINT_VERSION:
        raise bad(f"unsupported checkpoint version {meta.get('version')!r} (expected {CHECKPOINT_VERSION})")
    try:
        values = json.loads(meta.get("config", ""))
    except json.JSONDecodeError as exc:
        raise bad(f"config is not valid JSON ({exc.msg})") from None
    try:
        config = NeRFConfig.from_dict(values)
    except (InputError, TypeError) as exc:
        raise bad(f"config: {exc}") from None
    try:
        tensors = st_load(data)
    except Exception as exc:  # safetensors raises its own error types for every malformed file
        raise bad(f"truncated or corrupt tensor data ({str(exc).splitlines()[0]})") from None

    model = RadianceField(config)
    expected = model.state_dict()
    for key, ref in expected.items():
        if key not in tensors:
            raise bad(f"tensor {key!r} is missing")
        got = tensors[key]
        if got.shape != ref.shape or got.dtype != ref.dtype:
            raise bad(f"tensor {key!r} has shape {list(got.shape)} {got.dtype}, expected {list(ref.shape)} {ref.dtype}")
        if got.dtype.is_floating_point and key != "grid.density" and not torch.isfinite(got).all():
            raise bad(f"tensor {key!r} holds NaN or infinite values")
    if torch.isnan(tensors["grid.density"]).any():
        raise bad("tensor 'grid.density' holds NaN values")
    unexpected = sorted(set(tensors) - set(expected) - {CAMERAS_TENSOR})
    if unexpected:
        raise bad(f"unexpected tensors {unexpected}")
    model.load_state_dict({k: tensors[k] for k in expected})

    cameras = None
    if CAMERAS_TENSOR in tensors:
        raw = tensors[CAMERAS_TENSOR]
        try:
            frames = json.loads(bytes(raw.numpy().tobytes()).decode())
            cameras = cameras_from_json(frames)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise bad(f"training cameras are not valid JSON ({exc})") from None
        except InputError as exc:
            raise bad(f"training cameras: {exc}") from None
    return NeRFRenderer(model, cameras, **renderer_options)
