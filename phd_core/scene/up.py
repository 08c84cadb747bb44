"""The capture's up direction: from its cameras, refined on the plane the capture stands on
when its points show one (docs/formats.md, "The upright frame").

Hand-held, tripod and rig photos share one thing: the camera is not rolled, so a horizontal
line in the world is horizontal in the photo and the camera's right axis is horizontal. Up is
then the direction most nearly orthogonal to every right axis: the eigenvector of the smallest
eigenvalue of sum_i w_i h_i h_i^T over the cameras' horizontal axes h_i (float64). The rule
before, the mean of the cameras' up axes, leans toward the side the cameras look down from
(22 degrees on flask_desk, a camera arcing round the front of a flask on a desk).

Sideways photos: a portrait photo whose rotation flag was dropped (COLMAP reads pixels as they
are stored) has its right axis along up and its up axis horizontal. So a camera's horizontal
axis h_i is its up axis when that lies nearer the plane than its right axis and the right axis
is tilted at least SIDEWAYS_TILT (20 degrees) out of it; else its right axis. (A camera looking
nearly along up has both axes in the plane, and its choice would be no evidence: it keeps its
right axis.)

The fit: an L1 plane fit by iteratively reweighted least squares (weights 1 / max(|h_i . up|,
sin 1 degree)) re-choosing each h_i, so a few rolled photos pull little, settled from two starts:
the best of GRID_SIZE directions spread over the hemisphere (the least mean |h_i . up|), so a
majority of sideways photos cannot trap it, and the normal of the right axes alone (every photo
upright); the fit whose axes tilt least on average is kept. (A narrow arc of cameras looking
down fits "all upright" and "all sideways" almost equally well from the grid: 88 of flask_desk's
101 cameras settled on "all sideways", 82 degrees off, from the grid's start alone.)
The fit is trusted when there are at least MIN_CAMERAS cameras and
  - the axes span a plane: the middle eigenvalue of the weighted mean (trace 1) is at least
    MIN_SPREAD = sin^2 10 degrees, i.e. the headings vary by about 10 degrees rms or more (a
    straight dolly, a forward-facing capture or a fixed-heading survey span less: roll noise
    would decide the normal);
  - they lie close to it: the smallest eigenvalue is at most RATIO_MAX = 0.05 of the middle one
    (simulated hand-held captures with 10 degrees rms of roll reach 0.048; random orientations
    of 100 cameras sit around 0.05);
  - the cameras do not look along it (their mean viewing direction within 30 degrees of it): a
    top-down survey is left to the fallback below, which says which way is up.

The sign follows the upright photos' up axes when they agree (mean of up_i . n over all
cameras, sideways photos counting 0, at least SIGN_VOTE in size); else the cameras look down
more than up (photos that are all sideways or all top-down).

Without a trusted fit: the cameras' mean up when their up axes agree (|mean| >= AGREE), else
minus their mean viewing direction when that agrees (a top-down survey, whose up axes turn with
its headings), else +z.

The support plane. A roll every photo shares (a phone held a little rolled throughout) tilts the
cameras' estimate by about that roll, 5 to 10 degrees for hand-held captures, and nothing in the
poses tells. A floor or a table top the capture stands on does, when its points are at hand (the
SfM points of a capture, or a model's opaque splat centres): of PLANE_POINTS of them at most
(evenly spaced), RANSAC over PLANE_TRIALS seeded point triples (`find_plane`) finds the plane with
the most points within PLANE_BAND of the points' extent (the diagonal of their 5th-95th
percentile box) among the planes that have CAMERAS_ON_ONE_SIDE of the camera centres on one side
and whose normal, pointing to that side, is within 15 degrees of the cameras' up (PLANE_GATE:
above the roll noise, far below a wall's 90 degrees; a ceiling's normal points down, 180
degrees), refitted to the points within half the band. Its normal is up ("support plane") when
  - it holds PLANE_SHARE (10%) of the points: a large plane (RANSAC's triples miss one that
    large with probability (1 - 0.1^3)^10000 < 1e-4);
  - it is a thin sheet, not a slab cut through clutter: of its points, PLANE_SHEET (0.75) lie
    within half the band, halfway between a slab through points of even density (0.5) and a
    perfectly flat sheet (1; Gaussian scatter of 0.45 bands rms gives 0.75);
  - its refitted normal is still within PLANE_GATE.
Else the cameras' estimate stands (`CaptureUp.plane` says what was found). The same points give
the same plane: the search is seeded, and costs at most PLANE_TRIALS x PLANE_POINTS distances.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import torch

from .camera import Camera

MIN_CAMERAS = 3                                   # two axes always span a plane: three can disagree
MIN_SPREAD = math.sin(math.radians(10)) ** 2      # the axes span a plane
RATIO_MAX = 0.05                                  # and lie close to it
ALONG_VIEW = math.cos(math.radians(30))           # a fit whose up is the viewing direction is not trusted
SIDEWAYS_TILT = math.sin(math.radians(20))        # a sideways photo's right axis leaves the plane this much
ROLL_FLOOR = math.sin(math.radians(1))            # IRLS weights stop growing at 1 degree of roll
SIGN_VOTE = 0.2                                   # the upright photos' vote that sets the sign
AGREE = 0.5                                       # a mean of unit axes this long: the cameras agree on it
GRID_SIZE = 1000                                  # start directions: about 4.5 degrees apart
GRID_CAMERAS = 512                                # cameras the start search looks at, at most (evenly spaced)
ROUNDS = 100                                      # IRLS rounds at most (it settles in tens)
SETTLED = 1e-7                                    # radians: the normal has stopped turning
DEFAULT_UP = (0.0, 0.0, 1.0)                      # Blender's (and the bundled data's) up
# The support plane:
PLANE_GATE = math.cos(math.radians(15))           # its normal within 15 degrees of the cameras' up
PLANE_SHARE = 0.10                                # it holds 10% of the points or more
PLANE_SHEET = 0.75                                # and is a thin sheet: this share of them within half the band
CAMERAS_ON_ONE_SIDE = 0.9                         # the cameras (this share of them) stand on one side of it
PLANE_BAND = 0.01                                 # a point this near it (x the points' extent) is on it
PLANE_POINTS = 5_000                              # points the search looks at, at most (evenly spaced)
MIN_PLANE_POINTS = 50                             # fewer points (finite ones): no plane is sought
PLANE_TRIALS = 10_000                             # seeded point triples: the same points give the same plane
REFITS = 10                                       # least-squares refits of the plane (it settles in a few)


@dataclass(frozen=True)
class Plane:
    """A plane found in a point cloud (`find_plane`)."""

    normal: torch.Tensor      # [3] float64 unit, toward the cameras
    point: torch.Tensor       # [3] float64, on the plane
    share: float              # of the points within the search's band of it
    sheet: float              # of those, the share within half the band (0.5 for a slab through even density)


@dataclass(frozen=True)
class CaptureUp:
    """The capture's up and how it was found."""

    vector: torch.Tensor      # [3] float64, unit
    rule: str                 # "support plane", "horizontal axes", "mean up", "mean view" or "default"
    spread: float             # the cameras' fit's middle eigenvalue (NaN without a trusted fit)
    ratio: float              # its smallest over middle eigenvalue (NaN without a trusted fit)
    sideways: int             # photos whose up axis was taken as the horizontal one
    plane: Plane | None = None  # the largest plane near the cameras' up; the up when rule is "support plane"


@dataclass(frozen=True)
class _Fit:
    normal: torch.Tensor      # [3] unit, sign not yet chosen
    values: torch.Tensor      # [3] ascending eigenvalues of the weighted mean of h h^T
    sideways: torch.Tensor    # [V] bool: the camera's up axis is its horizontal one


def capture_up(cameras: Sequence[Camera], points: torch.Tensor | None = None) -> CaptureUp:
    """The capture's up direction (module docstring): from the cameras, refined on the plane the
    capture stands on when `points` ([P, 3]: SfM points or opaque splat centres) show one; +z
    without cameras."""
    if not cameras:
        return _without_fit(torch.tensor(DEFAULT_UP, dtype=torch.float64), "default")
    found = _camera_up(cameras)
    if points is None:
        return found
    points = points.detach().to(torch.float64).reshape(-1, 3)
    points = points[torch.isfinite(points).all(dim=1)]                              # [P, 3]
    if len(points) < MIN_PLANE_POINTS:
        return found
    points = points[torch.linspace(0, len(points) - 1, min(len(points), PLANE_POINTS)).round().long()]
    centres = torch.stack([c.center for c in cameras])                              # [V, 3]
    plane = find_plane(points, centres, PLANE_BAND * point_extent(points), near=found.vector)
    if plane is None:
        return found
    if plane.share < PLANE_SHARE or plane.sheet < PLANE_SHEET or float(plane.normal @ found.vector) < PLANE_GATE:
        return replace(found, plane=plane)
    return replace(found, vector=plane.normal, rule="support plane", plane=plane)


def point_extent(points: torch.Tensor) -> float:
    """The size of a point cloud [P, 3]: the diagonal of its 5th-95th percentile box (a few far
    points move it little)."""
    low, high = torch.quantile(points, torch.tensor([0.05, 0.95], dtype=points.dtype), dim=0)
    return float((high - low).norm())


def find_plane(points: torch.Tensor, centres: torch.Tensor, band: float, *, near: torch.Tensor | None = None,
               trials: int = PLANE_TRIALS, seed: int = 0) -> Plane | None:
    """RANSAC: of the planes through `trials` seeded triples of `points` [P, 3] (float64) that
    have at least CAMERAS_ON_ONE_SIDE of the camera centres [V, 3] on one side (and, given `near`
    [3], whose normal toward the cameras is within PLANE_GATE of it), the one with the most
    points within `band`; refitted REFITS times to the points within band / 2 of it: the normal
    by least squares, the offset by their median distance (so what stands on a floor does not
    lift it). None when no triple qualifies. Cost: at most `trials` x P point-plane distances."""
    generator = torch.Generator().manual_seed(seed)
    triples = points[torch.randint(len(points), (trials, 3), generator=generator)]    # [T, 3, 3]
    normals = torch.linalg.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])   # [T, 3]
    lengths = normals.norm(dim=1)
    normals, anchors = normals[lengths > 0] / lengths[lengths > 0, None], triples[lengths > 0, 0]
    above = (((centres[None] - anchors[:, None]) * normals[:, None]).sum(-1) > 0).double().mean(1)   # [T]
    normals = torch.where((above >= 0.5)[:, None], normals, -normals)                   # toward the cameras
    keep = above.maximum(1 - above) >= CAMERAS_ON_ONE_SIDE
    if near is not None:
        keep &= normals @ near >= PLANE_GATE
    normals, anchors = normals[keep], anchors[keep]
    if len(normals) == 0:
        return None
    offsets = (normals * anchors).sum(1)                                                 # [T']
    counts = torch.cat([(points @ n.T - o).abs().lt(band).sum(0)                            # [256] at a time
                        for n, o in zip(normals.split(256), offsets.split(256))])         # [T']
    best = int(counts.argmax())
    normal, point = normals[best], anchors[best]
    for _ in range(REFITS):
        on = ((points - point) @ normal).abs() < band / 2
        if int(on.sum()) < 3:
            break
        centre = points[on].mean(0)
        fitted = torch.linalg.svd(points[on] - centre, full_matrices=False).Vh[-1]
        normal = fitted if float(fitted @ normal) >= 0 else -fitted
        point = centre + ((points[on] - centre) @ normal).median() * normal
    distances = ((points - point) @ normal).abs()                                       # [P]
    within = int((distances < band).sum())
    return Plane(normal, point, within / len(points), int((distances < band / 2).sum()) / max(within, 1))


def _camera_up(cameras: Sequence[Camera]) -> CaptureUp:
    """The up the cameras' axes alone give (module docstring)."""
    axes = torch.stack([c.c2w[:3, :3] for c in cameras]).to(torch.float64)     # [V, 3, 3] columns: right, up, back
    right, up, view = axes[:, :, 0], axes[:, :, 1], -axes[:, :, 2]            # [V, 3] each
    if len(cameras) >= MIN_CAMERAS:
        fit = _plane_fit(right, up)
        small, middle = float(fit.values[0]), float(fit.values[1])
        if middle >= MIN_SPREAD and small <= RATIO_MAX * middle and abs(float(view.mean(0) @ fit.normal)) < ALONG_VIEW:
            return CaptureUp(_signed(fit, up, view), "horizontal axes", middle, small / middle,
                             int(fit.sideways.sum()))
    mean_up, mean_view = up.mean(0), view.mean(0)
    if mean_up.norm() >= AGREE:
        return _without_fit(mean_up / mean_up.norm(), "mean up")
    if mean_view.norm() >= AGREE:
        return _without_fit(-mean_view / mean_view.norm(), "mean view")
    return _without_fit(torch.tensor(DEFAULT_UP, dtype=torch.float64), "default")


def _horizontal(right: torch.Tensor, up: torch.Tensor, normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For cameras' right and up axes [V, 3] and candidate normals [N, 3]: which cameras are
    sideways [V, N] bool, and the sine of their horizontal axis' tilt out of each plane [V, N]."""
    tilt_right, tilt_up = (right @ normals.T).abs(), (up @ normals.T).abs()
    sideways = (tilt_right >= SIDEWAYS_TILT) & (tilt_up < tilt_right)
    return sideways, torch.where(sideways, tilt_up, tilt_right)


def _plane_fit(right: torch.Tensor, up: torch.Tensor) -> _Fit:
    """The L1 plane through the origin of the cameras' horizontal axes (module docstring): settled
    from the best grid direction and from the plane of the right axes alone (every photo upright),
    the one whose horizontal axes tilt least out of it on average."""
    every = torch.linspace(0, len(right) - 1, min(len(right), GRID_CAMERAS)).round().long()
    _, tilts = _horizontal(right[every], up[every], _GRID)                           # [V', G]
    upright = torch.linalg.eigh(right.T @ right)[1][:, 0]                              # [3]
    fits = [_settle(right, up, start) for start in (_GRID[tilts.mean(0).argmin()], upright)]
    return min(fits, key=lambda fit: float(_horizontal(right, up, fit.normal[None])[1].mean()))


def _settle(right: torch.Tensor, up: torch.Tensor, normal: torch.Tensor) -> _Fit:
    """IRLS from the start `normal` [3] until the normal and the sideways photos settle."""
    sideways, tilt = (t[:, 0] for t in _horizontal(right, up, normal[None]))
    for _ in range(ROUNDS):
        h = torch.where(sideways[:, None], up, right)                                # [V, 3]
        weights = 1 / tilt.clamp_min(ROLL_FLOOR)                                      # [V]
        values, vectors = torch.linalg.eigh((weights[:, None] * h).T @ h / weights.sum())
        moved = float(torch.linalg.cross(vectors[:, 0], normal).norm())               # sine of the turn
        normal = vectors[:, 0]
        turned, tilt = (t[:, 0] for t in _horizontal(right, up, normal[None]))
        if torch.equal(turned, sideways) and moved < SETTLED:
            break
        sideways = turned
    return _Fit(normal, values, sideways)


def _signed(fit: _Fit, up: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
    """The fit's normal, pointing the way the upright photos' up axes agree on, else against the
    cameras' mean viewing direction."""
    vote = float(((up @ fit.normal) * ~fit.sideways).mean())
    if abs(vote) < SIGN_VOTE:
        vote = -float((view @ fit.normal).mean())
    return fit.normal if vote >= 0 else -fit.normal


def _without_fit(vector: torch.Tensor, rule: str) -> CaptureUp:
    return CaptureUp(vector, rule, math.nan, math.nan, 0)


def _fibonacci_hemisphere(count: int) -> torch.Tensor:
    """[count, 3] unit directions spread evenly over the upper hemisphere (a normal and its
    negative are one plane)."""
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = k / count
    azimuth = k * math.pi * (3 - math.sqrt(5))
    ring = (1 - z * z).sqrt()
    return torch.stack([ring * azimuth.cos(), ring * azimuth.sin(), z], dim=1)


_GRID = _fibonacci_hemisphere(GRID_SIZE)                                              # [G, 3]
