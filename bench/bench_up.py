"""The upright frame on real captures: the up `phd_core.scene.capture_up` estimates (from the
cameras, refined on the plane the capture stands on when the SfM points show one), the same from
the cameras alone, the rule before both (the cameras' mean up) and the cameras' cue without its
robust parts (least squares on every right axis), each against two references that no up
estimate enters:

- the plane: the normal of the floor or table top, fitted to the SfM points. Four candidate
  planes by sequential RANSAC (`phd_core.scene.up.find_plane`, the product's search without its
  angle gate: REFERENCE_TRIALS seeded point triples, the most points within 1% of the points'
  extent among planes with 90% of the camera centres on one side, refitted to the points within
  0.5%, pointing to the cameras); each candidate's points within 0.5% are set aside before the
  next. The reference is the largest candidate that the photos show to be the floor or a table
  top, checked by eye on the images `--check DIR` writes (SEEN records the choice): for each
  candidate, the photo with most of its points in view, them in red (the other points cyan), and
  posts on twelve of them along its normal (green) and the estimate (magenta). Its checks: the
  normal's spread over SEEDS RANSAC seeds, and the largest angle between its normal and that of a
  third of its points (split along the plane's longest axis: is it one flat plane?).
- the lines: the scene's vertical vanishing direction from straight segments in the undistorted
  photos (bench/vanishing.py), which neither the cameras' roll nor the SfM points decide. Its
  checks: its spread over SEEDS seeds and its angle to the same fit on either half of the photos
  (even and odd), and by eye: `--check` draws the photo with most inlier segments, them green,
  the others red, with ticks along the lines' vertical (magenta) and the plane's (cyan).

The estimate refined on a support plane is that plane's normal, so against the plane reference
it is near 0 by construction: the lines judge it. A third table says what the cameras' estimate's
error comes from (`rolls`, against the lines): the cameras' roll, and the error split into a
tilt toward their mean right axis and toward their mean heading.

    PHD_CACHE_DIR=/tmp/up_cache nice -n 10 .venv/bin/python -m bench.bench_up --check /tmp/up_check \\
        --out bench/results/up.json --doc

(the bench extra: `pip install -e ".[bench]"`, OpenCV's line segment detector; `--doc`: the
tables into docs/formats.md, section "The upright frame"; PHD_CACHE_DIR: where the distorted
captures' undistorted photos go.)

`--models DIR` judges the estimate the service makes when a model is uploaded instead: from the
model's training cameras and its opaque splat centres (not the SfM points), for every DIR/NAME.ply
`phd train` wrote on a capture above, against the references that `--out` stored:

    nice -n 10 .venv/bin/python -m bench.bench_up --models DIR --doc
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from bench import _harness
from bench.vanishing import (
    Vanishing,
    interpretation_normals,
    photo_segments,
    vanishing_direction,
    vanishing_pixel,
)
from phd_core.data import Dataset, load_dataset
from phd_core.renderers import load_model
from phd_core.scene import capture_up
from phd_core.scene.up import PLANE_BAND, find_plane, point_extent
from phd_core.uq.candidates import scene_points

CAPTURES = {"cup_colmap": _harness.DATA / "cup_colmap",
            **{name: _harness.DATA / "real" / name
               for name in ("flask_desk", "imac_chair", "meeting_room_a", "drone_flight1")}}
# The plane reference: which candidate plane (1 = the largest) and what it is, checked by eye on the --check images.
SEEN = {"cup_colmap": (1, "table top"), "flask_desk": (1, "desk top"), "imac_chair": (1, "floor"),
        "meeting_room_a": (1, "floor"), "drone_flight1": (4, "floor")}
CANDIDATES = 4
REFERENCE_TRIALS = 4000
SEEDS = 5


@dataclass
class Capture:
    name: str
    data: Dataset               # every photo, undistorted onto pinhole cameras, and the SfM points
    centres: torch.Tensor       # [V, 3] float64 camera centres
    points: torch.Tensor        # [P, 3] float64 SfM points


@dataclass
class Lines:
    segments: list[np.ndarray]  # per photo [S_v, 4] pixel ends
    normals: np.ndarray         # [N, 3] their interpretation planes' world normals, photo after photo
    photo: np.ndarray           # [N] which photo each came from


def read_capture(name: str, folder: Path) -> Capture:
    data = load_dataset(folder, "all")
    assert data.points is not None, f"{name}: the COLMAP model has no points"
    return Capture(name, data, torch.stack([c.center for c in data.cameras]), data.points.to(torch.float64))


def read_lines(capture: Capture) -> Lines:
    assert capture.data.images is not None
    segments = [photo_segments(image.numpy()) for image in capture.data.images]
    normals = [interpretation_normals(c, s) for c, s in zip(capture.data.cameras, segments)]
    photo = np.concatenate([np.full(len(n), k) for k, n in enumerate(normals)])
    return Lines(segments, np.concatenate(normals), photo)


# ----------------------------------------------------------------------------- the plane reference

@dataclass
class Candidate:
    normal: np.ndarray       # [3] unit, toward the cameras
    point: np.ndarray        # [3] on the plane
    inliers: np.ndarray      # [P] bool: within half the band of it (of the points left when it was found)


def candidate_planes(capture: Capture, seed: int) -> list[Candidate]:
    """CANDIDATES planes, largest first (module docstring)."""
    points = capture.points
    band = PLANE_BAND * point_extent(points)
    left = torch.ones(len(points), dtype=torch.bool)
    planes = []
    for _ in range(CANDIDATES):
        found = find_plane(points[left], capture.centres, band, trials=REFERENCE_TRIALS, seed=seed)
        assert found is not None, f"{capture.name}: no plane has the cameras on one side"
        inliers = left & (((points - found.point) @ found.normal).abs() < band / 2)
        planes.append(Candidate(found.normal.numpy(), found.point.numpy(), inliers.numpy()))
        left &= ~inliers
    return planes


def thirds_angle(capture: Capture, plane: Candidate) -> float:
    """Degrees: the largest angle between the plane's normal and that of a third of its inliers,
    split along the inliers' longest in-plane axis."""
    inliers = capture.points.numpy()[plane.inliers]
    centred = inliers - inliers.mean(0)
    along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
    worst = 0.0
    for part in np.array_split(np.argsort(along), 3):
        chunk = inliers[part] - inliers[part].mean(0)
        worst = max(worst, degrees(np.linalg.svd(chunk, full_matrices=False)[2][2], plane.normal, signed=False))
    return worst


def degrees(a: np.ndarray, b: np.ndarray, signed: bool = True) -> float:
    """The angle between two directions (as lines when not `signed`)."""
    cosine = float(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, abs(cosine) if not signed else max(-1.0, cosine))))


# ----------------------------------------------------------------------------- the lines reference

def segment_angles(capture: Capture, lines: Lines, fit: Vanishing, direction: np.ndarray) -> np.ndarray:
    """Degrees [I]: in each photo, the angle between each of the fit's inlier segments and the
    line from its midpoint to where lines along `direction` meet (what a reference makes of the
    vertical edges the photos show)."""
    angles = []
    for k, camera in enumerate(capture.data.cameras):
        ends = lines.segments[k][fit.inliers[lines.photo == k]]                  # [S, 4]
        meet = vanishing_pixel(camera, direction)                                # [3] homogeneous
        middle, along = (ends[:, :2] + ends[:, 2:]) / 2, ends[:, 2:] - ends[:, :2]
        toward = meet[:2] - middle * meet[2]                                     # [S, 2]
        cosine = np.abs((along * toward).sum(1)) / np.linalg.norm(along, axis=1) / np.linalg.norm(toward, axis=1)
        angles.append(np.degrees(np.arccos(np.clip(cosine, 0, 1))))
    return np.concatenate(angles)


def line_checks(lines: Lines, guess: np.ndarray, fit: Vanishing) -> dict:
    """The lines reference's spread over seeds and its angle to the fit on either half of the photos."""
    seeds = [degrees(vanishing_direction(lines.normals, guess, seed).direction, fit.direction)
             for seed in range(1, SEEDS)]
    halves = [degrees(vanishing_direction(lines.normals[lines.photo % 2 == half], guess).direction, fit.direction)
              for half in (0, 1)]
    return {"lines_seed_spread_deg": max(seeds), "lines_halves_deg": max(halves)}


# ----------------------------------------------------------------------------- the tables

def measure(capture: Capture, candidates: list[Candidate], lines: Lines) -> tuple[dict, Vanishing]:
    """Every estimate against both references (candidates: seed 0's planes), the references'
    checks, and what explains the cameras' estimate's error (`rolls`)."""
    cameras = capture.data.cameras
    refined, alone = capture_up(cameras, capture.points), capture_up(cameras)
    mean_up = np.mean([c.c2w[:3, 1].numpy() for c in cameras], axis=0)
    # The cue without its robust parts: least squares on every right axis, signed by the mean up.
    right = np.stack([c.c2w[:3, 0].numpy() for c in cameras])
    plain = np.linalg.eigh(right.T @ right)[1][:, 0]
    plain = plain if plain @ mean_up >= 0 else -plain
    rank, _ = SEEN[capture.name]
    plane = candidates[rank - 1]
    fit = vanishing_direction(lines.normals, alone.vector.numpy())
    estimates = {"estimate": refined.vector.numpy(), "cameras": alone.vector.numpy(), "mean_up": mean_up,
                 "plain": plain}
    found = refined.plane
    row = {"capture": capture.name, "photos": len(cameras), "rule": refined.rule, "camera_rule": alone.rule,
           "spread": alone.spread, "ratio": alone.ratio, "sideways": alone.sideways,
           "support_share": found.share if found else math.nan, "support_sheet": found.sheet if found else math.nan,
           "support_to_cameras_deg": degrees(found.normal.numpy(), alone.vector.numpy()) if found else math.nan,
           **{name: vector.tolist() for name, vector in estimates.items()},
           **{f"{name}_vs_plane_deg": degrees(vector, plane.normal) for name, vector in estimates.items()},
           **{f"{name}_vs_lines_deg": degrees(vector, fit.direction) for name, vector in estimates.items()},
           "plane_reference": plane.normal.tolist(), "plane": SEEN[capture.name][1], "candidate": rank,
           "plane_points": int(plane.inliers.sum()), "points": len(capture.points),
           "plane_seed_spread_deg": max(min(degrees(p.normal, plane.normal) for p in candidate_planes(capture, seed))
                                        for seed in range(1, SEEDS)),
           "thirds_deg": thirds_angle(capture, plane),
           "lines_reference": fit.direction.tolist(), "segments": len(lines.normals),
           "line_inliers": int(fit.inliers.sum()), "line_photos": len(set(lines.photo[fit.inliers].tolist())),
           **line_checks(lines, alone.vector.numpy(), fit),
           "references_deg": degrees(plane.normal, fit.direction),
           "edges_to_lines_deg": float(np.median(segment_angles(capture, lines, fit, fit.direction))),
           "edges_to_plane_deg": float(np.median(segment_angles(capture, lines, fit, plane.normal))),
           **rolls(capture, fit.direction, alone.vector.numpy())}
    return row, fit


def rolls(capture: Capture, up: np.ndarray, estimate: np.ndarray) -> dict:
    """The cameras against the reference `up`: each camera's roll (degrees: the tilt of its level
    right axis out of the reference's horizontal plane; for a sideways photo, whose right axis
    points along up, that is its up axis turned back a quarter) and heading (of that axis, about
    up, from the mean); their mean, spread and correlation; and the estimate's error split into
    its tilt toward the cameras' mean right axis (what a roll they share does) and toward their
    mean heading (what a roll that turns with the heading does)."""
    axes = np.stack([c.c2w[:3, :3].numpy() for c in capture.data.cameras])      # [V, 3, 3]
    right, image_up = axes[:, :, 0], axes[:, :, 1]
    sideways = np.abs(image_up @ up) < np.abs(right @ up)
    level_right = np.where(sideways[:, None], -np.sign(right @ up)[:, None] * image_up, right)     # [V, 3]
    mean_right = level_right.mean(0) - (level_right.mean(0) @ up) * up
    mean_right /= np.linalg.norm(mean_right)
    ahead = np.cross(up, mean_right)
    roll = np.degrees(np.arcsin(np.clip(level_right @ up, -1, 1)))
    heading = np.degrees(np.arctan2(level_right @ ahead, level_right @ mean_right))
    return {"roll_mean_deg": float(roll.mean()), "roll_std_deg": float(roll.std()),
            "heading_std_deg": float(heading.std()), "roll_heading_corr": float(np.corrcoef(roll, heading)[0, 1]),
            "error_toward_right_deg": math.degrees(math.asin(float(estimate @ mean_right))),
            "error_toward_heading_deg": math.degrees(math.asin(float(estimate @ ahead)))}


def table(rows: list[dict]) -> str:
    lines = ["| capture | photos | plane reference (candidate): SfM points on it, spread over 5 seeds, thirds | "
             "lines reference: inlier segments of all (photos), spread over 5 seeds, halves | plane vs lines | "
             "vertical edges' median angle in the photos to the lines' / the plane's vertical |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['photos']} | {r['plane']} ({r['candidate']}): {r['plane_points']} of "
                     f"{r['points']}, {r['plane_seed_spread_deg']:.2f}°, {r['thirds_deg']:.1f}° | "
                     f"{r['line_inliers']} of {r['segments']} ({r['line_photos']}), {r['lines_seed_spread_deg']:.2f}°, "
                     f"{r['lines_halves_deg']:.2f}° | **{r['references_deg']:.1f}°** | "
                     f"{r['edges_to_lines_deg']:.2f}° / {r['edges_to_plane_deg']:.2f}° |")
    lines += ["", "| capture | rule | estimate vs plane / lines | cameras alone vs plane / lines | mean up (before) vs "
              "plane / lines | plain least squares vs plane / lines | largest plane near the cameras' up: share, "
              "sheet, angle to their up | cameras' fit: spread, ratio, sideways photos |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = [f"{r[f'{k}_vs_plane_deg']:.1f}° / {r[f'{k}_vs_lines_deg']:.1f}°"
                 for k in ("estimate", "cameras", "mean_up", "plain")]
        cells[0] = f"{r['estimate_vs_plane_deg']:.1f}° / **{r['estimate_vs_lines_deg']:.1f}°**"
        lines.append(f"| {r['capture']} | {r['rule']} | {' | '.join(cells)} | {r['support_share']:.2f}, "
                     f"{r['support_sheet']:.2f}, {r['support_to_cameras_deg']:.1f}° | "
                     f"{r['camera_rule']}: {r['spread']:.3f}, {r['ratio']:.4f}, {r['sideways']} |")
    lines += ["", "| capture | cameras' roll against the lines: mean, std | heading std | roll-heading correlation | "
              "cameras' error toward the mean right axis | toward the mean heading |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['roll_mean_deg']:+.1f}°, {r['roll_std_deg']:.1f}° | "
                     f"{r['heading_std_deg']:.0f}° | {r['roll_heading_corr']:+.2f} | "
                     f"{r['error_toward_right_deg']:+.1f}° | {r['error_toward_heading_deg']:+.1f}° |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the check images

def enlarged(capture: Capture, k: int) -> tuple[Image.Image, int]:
    """Photo k as a PIL image about 720 pixels across its longer side, and the scale."""
    assert capture.data.images is not None
    camera = capture.data.cameras[k]
    scale = max(1, round(720 / max(camera.width, camera.height)))
    pixels = (capture.data.images[k].numpy() * 255).round().astype(np.uint8)
    return Image.fromarray(pixels).resize((camera.width * scale, camera.height * scale), Image.LANCZOS), scale


def plane_image(capture: Capture, plane: Candidate, estimate: np.ndarray, path: Path) -> None:
    """The photo with most of the plane's points in view: those points red, the other points
    cyan, posts on twelve of the plane's points along its normal (green) and the estimate (magenta)."""
    cameras = capture.data.cameras
    projected = [camera.project(capture.points) for camera in cameras]          # per photo ([P, 2], [P])
    seen = [((depth > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] < c.width) & (pixels[:, 1] >= 0)
             & (pixels[:, 1] < c.height)).numpy() for c, (pixels, depth) in zip(cameras, projected)]
    k = int(np.argmax([(s & plane.inliers).sum() for s in seen]))
    photo, scale = enlarged(capture, k)
    draw = ImageDraw.Draw(photo)
    pixels = projected[k][0].numpy() * scale
    for i in np.flatnonzero(seen[k]):
        r, colour = (4, (255, 0, 0)) if plane.inliers[i] else (2, (0, 255, 255))
        draw.ellipse([pixels[i, 0] - r, pixels[i, 1] - r, pixels[i, 0] + r, pixels[i, 1] + r], fill=colour)
    height = 0.1 * point_extent(capture.points)
    for base in np.random.default_rng(0).permutation(np.flatnonzero(seen[k] & plane.inliers))[:12]:
        foot = capture.points[int(base)].numpy()
        for direction, colour in ((plane.normal, (0, 255, 0)), (estimate, (255, 0, 255))):
            ends, depth = cameras[k].project(torch.from_numpy(np.stack([foot, foot + height * direction])))
            if (depth > 0).all():
                a, b = ends.numpy() * scale
                draw.line([tuple(a), tuple(b)], fill=colour, width=3)
    save(photo, path)


def lines_image(capture: Capture, lines: Lines, fit: Vanishing, plane: np.ndarray, path: Path) -> None:
    """The photo with most inlier segments: them green, its other segments red, and a grid of
    ticks along the lines' vertical (magenta) and the plane reference's (cyan, shorter)."""
    k = int(np.argmax(np.bincount(lines.photo[fit.inliers], minlength=len(capture.data.cameras))))
    camera = capture.data.cameras[k]
    photo, scale = enlarged(capture, k)
    draw = ImageDraw.Draw(photo)
    for (x1, y1, x2, y2), inlier in zip(lines.segments[k], fit.inliers[lines.photo == k]):
        draw.line([(x1 * scale, y1 * scale), (x2 * scale, y2 * scale)], fill=(0, 255, 0) if inlier else (255, 60, 60),
                  width=3 if inlier else 1)
    reach = 0.06 * max(camera.width, camera.height)
    for direction, colour, length in ((fit.direction, (255, 0, 255), reach), (plane, (0, 255, 255), 0.6 * reach)):
        meet = vanishing_pixel(camera, direction if direction @ fit.direction > 0 else -direction)
        for x in np.linspace(0.1, 0.9, 6) * camera.width:
            for y in np.linspace(0.15, 0.85, 4) * camera.height:
                toward = meet[:2] - np.array([x, y]) * meet[2]
                toward *= length / np.linalg.norm(toward)
                draw.line([((x - toward[0]) * scale, (y - toward[1]) * scale),
                           ((x + toward[0]) * scale, (y + toward[1]) * scale)], fill=colour, width=2)
    save(photo, path)


def save(photo: Image.Image, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    photo.save(path)


# ----------------------------------------------------------------------------- trained models

def splat_rows(models: Path, references: Path) -> list[dict]:
    """For every capture with a model in `models`: the up the service finds at upload (its
    training cameras, refined on the plane its opaque splats show) against the references of the
    SfM points' run (`references`: that run's --out)."""
    rows = []
    for reference in json.loads(references.read_text())["rows"]:
        path = models / f"{reference['capture']}.ply"
        if not path.exists():
            continue
        renderer = load_model(path)
        found = capture_up(renderer.training_cameras or [], scene_points(renderer))
        estimate = found.vector.numpy()
        rows.append({"capture": reference["capture"], "splats": renderer.num_units, "rule": found.rule,
                     "estimate": estimate.tolist(),
                     "vs_lines_deg": degrees(estimate, np.array(reference["lines_reference"])),
                     "vs_plane_deg": degrees(estimate, np.array(reference["plane_reference"])),
                     "vs_points_estimate_deg": degrees(estimate, np.array(reference["estimate"])),
                     "points_vs_lines_deg": reference["estimate_vs_lines_deg"]})
    return rows


def splat_table(rows: list[dict]) -> str:
    lines = ["| capture | splats | rule | estimate from the splats vs lines / plane | the SfM points' estimate vs "
             "lines | the two estimates apart |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['splats']:,} | {r['rule']} | **{r['vs_lines_deg']:.1f}°** / "
                     f"{r['vs_plane_deg']:.1f}° | {r['points_vs_lines_deg']:.1f}° | "
                     f"{r['vs_points_estimate_deg']:.1f}° |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", type=Path, help="write the check images here (CAPTURE_K.png: plane candidate "
                        "K; CAPTURE_lines.png: the lines)")
    parser.add_argument("--out", type=Path, help="the results as JSON")
    parser.add_argument("--doc", action="store_true", help="write the tables into docs/formats.md")
    parser.add_argument("--models", type=Path, help="judge the service's estimate on the models NAME.ply here "
                        "instead, against the references of --references")
    parser.add_argument("--references", type=Path, default=_harness.RESULTS / "up.json")
    args = parser.parse_args()
    if args.models:
        text = splat_table(splat_rows(args.models, args.references))
        print(text)
        if args.doc:
            run = f"    nice -n 10 .venv/bin/{_harness.command()}"
            _harness.write_doc(_harness.DOCS / "formats.md", f"{text}\n\n{run}", "up_splats")
        return
    rows = []
    for name, folder in CAPTURES.items():
        capture = read_capture(name, folder)
        candidates, lines = candidate_planes(capture, 0), read_lines(capture)
        row, fit = measure(capture, candidates, lines)
        rows.append(row)
        print(f"{name}: estimate {row['estimate_vs_plane_deg']:.1f}° from the plane, "
              f"{row['estimate_vs_lines_deg']:.1f}° from the lines", flush=True)
        if args.check:
            for k, plane in enumerate(candidates, start=1):
                plane_image(capture, plane, np.array(row["estimate"]), args.check / f"{name}_{k}.png")
            lines_image(capture, lines, fit, np.array(row["plane_reference"]), args.check / f"{name}_lines.png")
    print(table(rows))
    if args.doc:
        run = f"    PHD_CACHE_DIR=/tmp/up_cache nice -n 10 .venv/bin/{_harness.command()}"
        _harness.write_doc(_harness.DOCS / "formats.md", f"{table(rows)}\n\n{run}", "up")
    if args.out:
        _harness.write_result(args.out, {"command": _harness.command(), "machine": _harness.machine(), "rows": rows})


if __name__ == "__main__":
    main()
