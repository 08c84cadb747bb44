"""The upright frame on real captures: the up `phd_core.scene.capture_up` estimates from the
cameras, the rule before it (the cameras' mean up) and the cue without its robust parts (least
squares on every right axis), each against a reference up taken from the scene's points
instead of the cameras: the normal of the floor or table plane.

The reference, for each COLMAP model (read with pycolmap): four
candidate planes by sequential RANSAC over the SfM points. Each is the plane (of
REFERENCE_TRIALS seeded point triples) with the most points within 1% of the points' extent
(the diagonal of their 5th-95th percentile box) among the planes with at least 90% of the
camera centres on one side, refined by least squares on the points within 0.5% of it (twice),
its normal pointing to the cameras' side; its points are set aside before the next. The
reference is the largest candidate that the photos show to be the floor or a table top,
checked by eye on the images `--check DIR` writes (SEEN records the choice): for each
candidate, the photo that sees most of its points, them in red (the photo's other SfM points
cyan), and posts on twelve of them along the candidate's normal (green) and the estimate
(magenta). No up estimate enters the reference. Its checks in the table: the normal's spread
over five RANSAC seeds, and the largest angle between its normal and that of a third of its
points (split along the plane's longest axis: is it one flat plane?). A second table says
what the estimate's error comes from (`rolls`): the cameras' roll against the reference, and
the error split into a tilt toward their mean right axis and toward their mean heading.

    nice -n 10 .venv/bin/python -m bench.bench_up --check /tmp/up_check --out bench/results/up.json --doc

(`--doc`: the tables into docs/formats.md, section "The upright frame".)
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from bench import _harness
from phd_core.scene import Camera, capture_up

CAPTURES = {"cup_colmap": _harness.DATA / "cup_colmap",
            **{name: _harness.DATA / "real" / name
               for name in ("flask_desk", "imac_chair", "meeting_room_a", "drone_flight1")}}
# The reference: which candidate plane (1 = the largest) and what it is, checked by eye on the --check images.
SEEN = {"cup_colmap": (1, "table top"), "flask_desk": (1, "desk top"), "imac_chair": (1, "floor"),
        "meeting_room_a": (1, "floor"), "drone_flight1": (4, "floor")}
CANDIDATES = 4
REFERENCE_TRIALS = 4000
DETECT_BAND, FIT_BAND = 0.01, 0.005          # of the points' extent
CAMERAS_ON_ONE_SIDE = 0.9
SEEDS = 5
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])      # OpenCV camera axes -> OpenGL (the project's Camera)


@dataclass
class Capture:
    name: str
    cameras: list[Camera]            # OpenGL camera-to-world, pinhole intrinsics of the model's cameras
    centres: np.ndarray              # [V, 3]
    points: np.ndarray               # [P, 3] SfM points
    point_ids: np.ndarray            # [P]
    reconstruction: object           # the pycolmap.Reconstruction (photos and projection for --check)
    folder: Path


def read_capture(name: str, folder: Path) -> Capture:
    import pycolmap

    reconstruction = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    images = sorted(reconstruction.images.values(), key=lambda image: image.name)
    cameras, centres = [], []
    for image in images:
        cam_from_world = image.cam_from_world().matrix()                       # [3, 4] OpenCV
        c2w = np.eye(4)
        c2w[:3, :3] = cam_from_world[:, :3].T @ GL_FROM_CV
        c2w[:3, 3] = image.projection_center()
        camera = image.camera
        cameras.append(Camera(torch.from_numpy(c2w), camera.focal_length_x, camera.focal_length_y,
                              camera.principal_point_x, camera.principal_point_y, camera.width, camera.height))
        centres.append(c2w[:3, 3])
    ids = np.array(sorted(reconstruction.points3D))
    points = np.array([reconstruction.points3D[i].xyz for i in ids])
    return Capture(name, cameras, np.array(centres), points, ids, reconstruction, folder)


# ----------------------------------------------------------------------------- the reference plane

@dataclass
class Plane:
    normal: np.ndarray       # [3] unit, toward the cameras
    point: np.ndarray        # [3] on the plane
    inliers: np.ndarray      # [P] bool: within FIT_BAND of it (of the points left when it was found)


def candidate_planes(capture: Capture, seed: int) -> list[Plane]:
    """CANDIDATES planes, largest first (module docstring): each the RANSAC plane with the most
    of the points left within DETECT_BAND, among those with the cameras on one side, refined by
    least squares on the points left within FIT_BAND; its points are then set aside."""
    points, centres = capture.points, capture.centres
    low, high = np.percentile(points, [5, 95], axis=0)
    extent = float(np.linalg.norm(high - low))
    rng = np.random.default_rng(seed)
    left = np.ones(len(points), dtype=bool)
    planes = []
    for _ in range(CANDIDATES):
        pool = points[left]
        best, best_count = None, -1
        for _ in range(0, REFERENCE_TRIALS, 250):           # batches: [250, P] distances at a time
            triples = pool[rng.integers(0, len(pool), (250, 3))]                  # [T, 3, 3]
            normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
            lengths = np.linalg.norm(normals, axis=1)
            keep = lengths > 1e-12 * extent ** 2
            normals, anchors = normals[keep] / lengths[keep, None], triples[keep, 0]
            above = (((centres[None] - anchors[:, None]) @ normals[..., None])[..., 0] > 0).mean(1)   # [T]
            counts = (np.abs(((pool[None] - anchors[:, None]) @ normals[..., None])[..., 0])
                      < DETECT_BAND * extent).sum(1)
            counts[np.maximum(above, 1 - above) < CAMERAS_ON_ONE_SIDE] = -1
            if counts.max() > best_count:
                best_count, best = int(counts.max()), (normals[counts.argmax()], anchors[counts.argmax()])
        assert best is not None and best_count > 0, f"{capture.name}: no plane has the cameras on one side"
        normal, point = best
        for _ in range(2):
            near = left & (np.abs((points - point) @ normal) < FIT_BAND * extent)
            point = points[near].mean(0)
            normal = np.linalg.svd(points[near] - point)[2][2]
        normal = normal if ((centres - point) @ normal > 0).mean() >= 0.5 else -normal
        inliers = left & (np.abs((points - point) @ normal) < FIT_BAND * extent)
        planes.append(Plane(normal, point, inliers))
        left &= ~inliers
    return planes


def thirds_angle(capture: Capture, plane: Plane) -> float:
    """Degrees: the largest angle between the plane's normal and that of a third of its inliers,
    split along the inliers' longest in-plane axis."""
    inliers = capture.points[plane.inliers]
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


# ----------------------------------------------------------------------------- the table

def measure(capture: Capture, candidates: list[Plane]) -> dict:
    """The estimate and the rule before it against the reference (candidates: seed 0's planes),
    with what explains the estimate's error (`rolls`)."""
    estimate = capture_up(capture.cameras)
    mean_up = np.mean([c.c2w[:3, 1].numpy() for c in capture.cameras], axis=0)
    # The cue without its robust parts: least squares on every right axis, signed by the mean up.
    right = np.stack([c.c2w[:3, 0].numpy() for c in capture.cameras])
    plain = np.linalg.eigh(right.T @ right)[1][:, 0]
    plain = plain if plain @ mean_up >= 0 else -plain
    rank, _ = SEEN[capture.name]
    reference = candidates[rank - 1]
    # The same plane found with other seeds: their candidate nearest to it.
    others = [min(degrees(p.normal, reference.normal) for p in candidate_planes(capture, seed))
              for seed in range(1, SEEDS)]
    return {"capture": capture.name, "photos": len(capture.cameras), "rule": estimate.rule,
            "spread": estimate.spread, "ratio": estimate.ratio, "sideways": estimate.sideways,
            "estimate": estimate.vector.tolist(), "reference": reference.normal.tolist(),
            "estimate_deg": degrees(estimate.vector.numpy(), reference.normal),
            "mean_up_deg": degrees(mean_up, reference.normal), "plain_deg": degrees(plain, reference.normal),
            "plane": SEEN[capture.name][1], "candidate": rank, "inliers": int(reference.inliers.sum()),
            "points": len(capture.points), "seed_spread_deg": max(others),
            "thirds_deg": thirds_angle(capture, reference), **rolls(capture, reference.normal, estimate.vector.numpy())}


def rolls(capture: Capture, up: np.ndarray, estimate: np.ndarray) -> dict:
    """The cameras against the reference `up`: each camera's roll (degrees: the tilt of its level
    right axis out of the reference's horizontal plane; for a sideways photo, whose right axis
    points along up, that is its up axis turned back a quarter) and heading (of that axis, about
    up, from the mean); their mean, spread and correlation; and the estimate's error split into
    its tilt toward the cameras' mean right axis (what a roll they share does) and toward their
    mean heading (what a roll that turns with the heading does)."""
    axes = np.stack([c.c2w[:3, :3].numpy() for c in capture.cameras])             # [V, 3, 3]
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
    lines = ["| capture | photos | estimate vs reference | mean up (before) vs reference | plain least squares "
             "vs reference | fit: spread, ratio, sideways photos | reference plane (candidate): SfM points on it | its "
             "spread over 5 seeds | thirds |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['photos']} | **{r['estimate_deg']:.1f}°** | {r['mean_up_deg']:.1f}° | "
                     f"{r['plain_deg']:.1f}° | "
                     f"{r['rule']}: {r['spread']:.3f}, {r['ratio']:.4f}, {r['sideways']} | {r['plane']} "
                     f"({r['candidate']}): {r['inliers']} of {r['points']} | {r['seed_spread_deg']:.2f}° | "
                     f"{r['thirds_deg']:.1f}° |")
    lines += ["", "| capture | cameras' roll: mean, std | heading std | roll-heading correlation | error toward the "
              "mean right axis | toward the mean heading |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['roll_mean_deg']:+.1f}°, {r['roll_std_deg']:.1f}° | "
                     f"{r['heading_std_deg']:.0f}° | {r['roll_heading_corr']:+.2f} | "
                     f"{r['error_toward_right_deg']:+.1f}° | {r['error_toward_heading_deg']:+.1f}° |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the check images

def check_image(capture: Capture, plane: Plane, estimate: np.ndarray, path: Path) -> None:
    """The photo that sees most of the plane's points, 3x: those points red, its other SfM points
    cyan, posts on twelve of the plane's points along its normal (green) and the estimate (magenta)."""
    from PIL import Image, ImageDraw

    reconstruction = capture.reconstruction
    on_plane = set(capture.point_ids[plane.inliers].tolist())
    images = sorted(reconstruction.images.values(), key=lambda image: image.name)
    seen = [[p.point3D_id for p in image.points2D if p.has_point3D()] for image in images]
    image = images[int(np.argmax([sum(i in on_plane for i in ids) for ids in seen]))]
    photo = Image.open(capture.folder / "images" / image.name).convert("RGB")
    scale = 3 * photo.width / image.camera.width
    photo = photo.resize((photo.width * 3, photo.height * 3))
    draw = ImageDraw.Draw(photo)
    for observation in image.points2D:
        if observation.has_point3D():
            u, v = observation.xy * scale
            r, colour = (4, (255, 0, 0)) if observation.point3D_id in on_plane else (2, (0, 255, 255))
            draw.ellipse([u - r, v - r, u + r, v + r], fill=colour)
    low, high = np.percentile(capture.points, [5, 95], axis=0)
    height = 0.1 * float(np.linalg.norm(high - low))
    cam_from_world = image.cam_from_world().matrix()
    bases = [i for i in (p.point3D_id for p in image.points2D if p.has_point3D()) if i in on_plane]
    for base in np.random.default_rng(0).permutation(sorted(set(bases)))[:12]:
        foot = reconstruction.points3D[int(base)].xyz
        for direction, colour in ((plane.normal, (0, 255, 0)), (estimate, (255, 0, 255))):
            ends = np.stack([foot, foot + height * direction]) @ cam_from_world[:, :3].T + cam_from_world[:, 3]
            if (ends[:, 2] > 0).all():
                a, b = image.camera.img_from_cam(ends) * scale
                draw.line([tuple(a), tuple(b)], fill=colour, width=3)
    path.parent.mkdir(parents=True, exist_ok=True)
    photo.save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", type=Path, help="write the check images here (CAPTURE_K.png: candidate K)")
    parser.add_argument("--out", type=Path, help="the results as JSON")
    parser.add_argument("--doc", action="store_true", help="write the tables into docs/formats.md")
    args = parser.parse_args()
    rows = []
    for name, folder in CAPTURES.items():
        capture = read_capture(name, folder)
        candidates = candidate_planes(capture, 0)
        rows.append(measure(capture, candidates))
        for k, plane in enumerate(candidates if args.check else [], start=1):
            check_image(capture, plane, np.array(rows[-1]["estimate"]), args.check / f"{name}_{k}.png")
    print(table(rows))
    if args.doc:
        run = f"    nice -n 10 .venv/bin/{_harness.command()}"
        _harness.write_doc(_harness.DOCS / "formats.md", f"{table(rows)}\n\n{run}", "up")
    if args.out:
        _harness.write_result(args.out, {"command": _harness.command(), "machine": _harness.machine(), "rows": rows})


if __name__ == "__main__":
    main()
