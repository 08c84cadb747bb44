"""Held-out scenes for the next-best-view benchmark: random layouts of our own splat models.

Four scenes are too few to choose a default by (issue 37). This script makes a family of
scenes no strategy was tuned on, in the Blender layout `bench.bench_nbv` reads:

1. Assets: a 3DGS model trained (SH degree 0, seeded, one thread) on each named scene, lego_200,
   donut_200, chain_200 and cup_colmap (the cup cropped out of its table: the splats within
   CUP_CROP of the point the cameras look at), turned so its up is +z, centred and scaled to a
   unit radius (0.9 quantile of its opaque splats' distance from their median).
2. Scenes: scene i draws (seeded by FAMILY_SEED and i) 1 + i % 4 objects, each an asset at a
   random scale, turn about +z and colour (channels permuted, tinted), placed close together
   on the ground plane so they hide each other, the whole scaled to radius SCENE_RADIUS.
3. Cameras (radius about 4, lego's field of view, looking at the scene): the train split (the
   candidates) is one of CANDIDATE_SHAPES and the test split one of TEST_SHAPES, every pair once
   over 12 scenes; the val split (target views for `+targets` runs) is drawn from the test
   split's shape with other poses, so targets and test views never coincide (a one-sided test
   split's val stands on the same side). Twelve walk scenes more (`capture_plan`) are captures
   along one hand-held walk of uneven speed, held out as cup_colmap is: every 8th frame a test
   view, the rest the candidates and the target views (their own layouts, their own seeds); and
   twelve room scenes, the same inside a textured room (`room`), written as COLMAP captures with
   SfM points, so the views also see surroundings as a real capture's do.
4. Images: the composed model rendered at SIZE px, RGBA (colour un-premultiplied, alpha the
   accumulated opacity), as donut_200 was made.

    .venv/bin/python -m bench.nbv_scenes       # assets (once), held_00 .. 11, walk_00 .. 11, room_00 .. 11

Written under bench/results/nbv_scenes/ (not in git; `layouts.json` there and in
bench/results/nbv_scenes.json records every draw). The same seeds give the same scenes.
"""

from __future__ import annotations

import argparse
import json
import math
import random
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch

from bench._harness import DATA, RESULTS, write_result
from phd_core.data import load_dataset
from phd_core.data.colmap import write_colmap_text
from phd_core.data.frames import HOLDOUT
from phd_core.io import png_bytes, write_bytes_atomic, write_json_atomic
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer, read_ply, write_ply
from phd_core.renderers.splats import SH_C0
from phd_core.scene import Camera, look_at
from phd_core.scene.rotations import quaternion_multiply, rotation_to_quaternion
from phd_core.train.gs3d import TrainConfig, fit
from phd_core.uq.candidates.frame import scene_frame

OUT = RESULTS / "nbv_scenes"
ASSETS = {"lego": "lego_200", "donut": "donut_200", "chain": "chain_200", "cup": "cup_colmap"}
ASSET_SIZE = 80               # training width of an asset (cup_colmap: 80x60)
ASSET_ITERATIONS = 1500
CUP_CROP = 0.22               # of the median camera distance: the cup without its table
FAMILY_SEED = 37
SCENES = 12
SIZE = 64                     # rendered image size (the benchmark downscales to its --resolution)
FOV_X = 0.6911112070083618    # lego's camera_angle_x
RADIUS = 4.03                 # camera distance of the Blender scenes
SCENE_RADIUS = 1.4            # the layout is scaled to this radius around the origin (lego's scene fits in 1.5)
COUNTS = {"train": 60, "val": 20, "test": 40}
WALKS = 12                    # walk_00 .. walk_11: every split from one hand-held walk, as cup_colmap's
CAPTURES = {"walk": 500, "room": 700}   # the seed offsets of the scenes split as a capture is
WALK_FRAMES = 96              # frames of a walk: every HOLDOUT-th a test view, the rest candidates and targets
LINGER = 0.7                  # a walk's speed varies from 0.3 to 1.7 times its mean
ROOMS = 12                    # room_00 .. room_11: walks in a textured room, written as COLMAP captures
ROOM_RADIUS = 7.0             # the room's wall, around the cameras (at about RADIUS)
ROOM_HEIGHT = 5.0
ROOM_SPACING = 0.1            # between the room's splats (a pixel at the far wall spans about 0.1 at SIZE)
ROOM_POINTS = 4000            # SfM points of a room capture: splat centres, as COLMAP triangulates surfaces


# ----------------------------------------------------------------------------- assets

def look_point(cameras: list[Camera]) -> torch.Tensor:
    """[3] float64 the point nearest every camera's optical axis (least squares)."""
    lhs, rhs = torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    for camera in cameras:
        axis = -camera.c2w[:3, 2].double()
        project = torch.eye(3, dtype=torch.float64) - torch.outer(axis, axis)
        lhs += project
        rhs += project @ camera.center
    return torch.linalg.solve(lhs, rhs)


def rotation_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[3, 3] float64 the rotation taking unit a to unit b about their common normal."""
    a, b = a / a.norm(), b / b.norm()
    v, c = torch.linalg.cross(a, b), float(a @ b)
    if v.norm() < 1e-9:
        return torch.eye(3, dtype=torch.float64) if c > 0 else torch.diag(torch.tensor([1.0, -1.0, -1.0],
                                                                                      dtype=torch.float64))
    vx = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + vx + vx @ vx / (1 + c)


def transformed(model: GaussianModel, rotation: torch.Tensor, scale: float, shift: torch.Tensor,
                keep: torch.Tensor | None = None) -> GaussianModel:
    """The model turned by `rotation` [3, 3], scaled about the origin and moved by `shift` [3]
    (splats `keep` only); SH degree 0 (the DC colour) so a turn needs no SH rotation."""
    keep = torch.ones(model.num_splats, dtype=torch.bool) if keep is None else keep
    q = rotation_to_quaternion(rotation).float().expand(int(keep.sum()), 4)
    return GaussianModel(means=((model.means[keep].double() @ rotation.T) * scale + shift).float(),
                         log_scales=model.log_scales[keep] + math.log(scale),
                         quats=quaternion_multiply(q, model.quats[keep]).contiguous(),
                         opacity_logits=model.opacity_logits[keep], sh=model.sh[keep, :1].contiguous())


def train_asset(name: str, seed: int = 0) -> GaussianModel:
    """One named scene's model, turned +z up, centred and scaled to a unit radius."""
    source = DATA / ASSETS[name]
    width = load_dataset(source, "train", with_images=False).cameras[0].width
    data = load_dataset(source, "train", downscale=width / ASSET_SIZE)
    model, _ = fit(data, TrainConfig(iterations=ASSET_ITERATIONS, sh_degree=0, seed=seed), progress=False)
    frame = scene_frame(data.cameras)
    turn = rotation_between(frame.up, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    keep = torch.sigmoid(model.opacity_logits) > 0.02
    if name == "cup":     # a real capture: keep the object the cameras look at, not the room
        centre = look_point(data.cameras)
        reach = float((torch.stack([c.center for c in data.cameras]) - centre).norm(dim=1).median())
        keep &= (model.means.double() - centre).norm(dim=1) < CUP_CROP * reach
    model = transformed(model, turn, 1.0, torch.zeros(3, dtype=torch.float64), keep)
    solid = model.means[torch.sigmoid(model.opacity_logits) > 0.5].double()
    centre = solid.median(dim=0).values
    radius = float(torch.quantile((solid - centre).norm(dim=1), 0.9))
    return transformed(model, torch.eye(3, dtype=torch.float64), 1.0 / radius, -centre / radius)


def assets(out: Path) -> dict[str, GaussianModel]:
    """The four assets, trained once and kept as PLY under `out`/assets."""
    models = {}
    for name in ASSETS:
        path = out / "assets" / f"{name}.ply"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            write_ply(train_asset(name), path)
            print(f"asset {name}: trained", flush=True)
        models[name] = read_ply(path)
    return models


# ----------------------------------------------------------------------------- layouts

def recoloured(model: GaussianModel, permutation: list[int], tint: list[float]) -> GaussianModel:
    """The model's colours with their channels permuted and scaled by `tint`."""
    colour = (model.sh[:, 0] * SH_C0 + 0.5)[:, permutation] * torch.tensor(tint)
    return replace(model, sh=((colour.clamp(0, 1) - 0.5) / SH_C0)[:, None, :].contiguous())


def draw_layout(rng: random.Random, objects: int) -> list[dict]:
    """`objects` placements: asset, scale, turn, colour and a ground-plane centre close enough to
    the others' that they hide each other from many directions."""
    placed: list[dict] = []
    while len(placed) < objects:
        scale = rng.uniform(0.45, 0.8)
        if placed:
            anchor = rng.choice(placed)
            angle, gap = rng.uniform(0, 2 * math.pi), (scale + anchor["scale"]) * rng.uniform(0.75, 1.0)
            centre = [anchor["centre"][0] + gap * math.cos(angle), anchor["centre"][1] + gap * math.sin(angle)]
            if any(math.dist(centre, p["centre"]) < 0.7 * (scale + p["scale"]) for p in placed):
                continue
        else:
            centre = [0.0, 0.0]
        placed.append({"asset": rng.choice(sorted(ASSETS)), "scale": scale, "centre": centre,
                       "turn": rng.uniform(0, 2 * math.pi), "permutation": rng.sample(range(3), 3),
                       "tint": [rng.uniform(0.6, 1.15) for _ in range(3)]})
    return placed


def compose(layout: list[dict], models: dict[str, GaussianModel]) -> GaussianModel:
    """One model of every placed object, centred on the origin and scaled to fill SCENE_RADIUS (one
    object as much of the image as four)."""
    parts = []
    for p in layout:
        c, s = math.cos(p["turn"]), math.sin(p["turn"])
        turn = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
        shift = torch.tensor([p["centre"][0], p["centre"][1], 0.0], dtype=torch.float64)
        parts.append(transformed(recoloured(models[p["asset"]], p["permutation"], p["tint"]), turn, p["scale"],
                                 shift))
    means = torch.cat([m.means for m in parts]).double()
    centre = (means.amax(0) + means.amin(0)) / 2
    reach = float(max((torch.cat([m.means[torch.sigmoid(m.opacity_logits) > 0.5] for m in parts]).double()
                       - centre).norm(dim=1).quantile(0.98), 1e-6))
    factor = SCENE_RADIUS / reach
    return merged([transformed(m, torch.eye(3, dtype=torch.float64), factor, -centre * factor) for m in parts])


def texture(rng: random.Random, uv: torch.Tensor) -> torch.Tensor:
    """[P, 3] colours in [0.08, 0.92] at surface coordinates uv [P, 2]: a base colour and eight random
    gratings (0.3 to 2 cycles a unit, any orientation): detail at the scales a view at the benchmark's
    32 px resolves (a pixel spans about 0.1 at the scene, 0.2 at the far wall)."""
    colour = torch.tensor([rng.uniform(0.3, 0.7) for _ in range(3)], dtype=torch.float64).expand(len(uv), 3).clone()
    for _ in range(8):
        angle, frequency, phase = rng.uniform(0, math.pi), rng.uniform(0.3, 2.0), rng.uniform(0, 2 * math.pi)
        wave = torch.sin(2 * math.pi * frequency * (uv[:, 0] * math.cos(angle) + uv[:, 1] * math.sin(angle)) + phase)
        colour += wave[:, None] * torch.tensor([rng.uniform(-0.12, 0.12) for _ in range(3)], dtype=torch.float64)
    return colour.clamp(0.08, 0.92)


def room(rng: random.Random, floor: float) -> GaussianModel:
    """A textured floor (a disc at height `floor`) and wall (a cylinder ROOM_HEIGHT tall) of ROOM_RADIUS,
    flat opaque splats ROOM_SPACING apart, each surface with its own texture: the surroundings a real
    capture sees behind the object, which only views from nearby directions reconstruct."""
    d = ROOM_SPACING
    grid = torch.arange(-ROOM_RADIUS, ROOM_RADIUS, d, dtype=torch.float64) + d / 2
    xy = torch.cartesian_prod(grid, grid)
    xy = xy[xy.norm(dim=1) < ROOM_RADIUS]                                               # [F, 2]
    turns, heights = round(2 * math.pi * ROOM_RADIUS / d), round(ROOM_HEIGHT / d)
    angle = torch.arange(turns, dtype=torch.float64) * (2 * math.pi / turns)
    th = torch.cartesian_prod(angle, torch.arange(heights, dtype=torch.float64) * d + d / 2)    # [W, 2]
    wall = torch.stack([ROOM_RADIUS * th[:, 0].cos(), ROOM_RADIUS * th[:, 0].sin(), floor + th[:, 1]], 1)
    means = torch.cat([torch.cat([xy, torch.full((len(xy), 1), floor, dtype=torch.float64)], 1), wall])
    colours = torch.cat([texture(rng, xy), texture(rng, torch.stack([th[:, 0] * ROOM_RADIUS, th[:, 1]], 1))])
    # A splat's thin axis (its local z) along the surface normal: +z on the floor, the radius on the wall.
    half = th[:, 0] / 2
    to_x = torch.tensor([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0], dtype=torch.float64)  # z -> x
    about_z = torch.stack([half.cos(), torch.zeros_like(half), torch.zeros_like(half), half.sin()], 1)
    quats = torch.cat([torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(len(xy), 4),
                       quaternion_multiply(about_z, to_x.expand(len(th), 4))])
    scales = torch.tensor([0.7 * d, 0.7 * d, 0.05 * d], dtype=torch.float64).log().expand(len(means), 3)
    return GaussianModel(means=means.float(), log_scales=scales.float().contiguous(), quats=quats.float().contiguous(),
                         opacity_logits=torch.full((len(means),), 4.0),
                         sh=((colours.float() - 0.5) / SH_C0)[:, None, :].contiguous())


def merged(models: list[GaussianModel]) -> GaussianModel:
    return GaussianModel(*(torch.cat([getattr(m, f) for m in models]).contiguous()
                           for f in ("means", "log_scales", "quats", "opacity_logits", "sh")))


# ----------------------------------------------------------------------------- camera shapes

Pose = tuple[list[float], list[float]]        # eye, target


def _eye(azimuth: float, elevation: float, radius: float = RADIUS) -> list[float]:
    return [radius * math.cos(elevation) * math.cos(azimuth), radius * math.cos(elevation) * math.sin(azimuth),
            radius * math.sin(elevation)]


def hemisphere(rng: random.Random, count: int) -> list[Pose]:
    """Random poses over the upper hemisphere (uniform in area, elevation 5 to 75 degrees)."""
    lo, hi = math.sin(math.radians(5)), math.sin(math.radians(75))
    return [(_eye(rng.uniform(0, 2 * math.pi), math.asin(rng.uniform(lo, hi))), [0.0, 0.0, 0.0])
            for _ in range(count)]


def rings(rng: random.Random, count: int) -> list[Pose]:
    """Three turntable rings (elevation 15, 35 and 60 degrees), each at its own phase."""
    poses: list[Pose] = []
    for r, elevation in enumerate((15, 35, 60)):
        n, phase = count // 3 + (r < count % 3), rng.uniform(0, 2 * math.pi)
        poses += [(_eye(phase + 2 * math.pi * k / n, math.radians(elevation)), [0.0, 0.0, 0.0]) for k in range(n)]
    return poses


def path(rng: random.Random, count: int, linger: float = 0.0) -> list[Pose]:
    """A hand-held walk: a 240-degree arc whose height and distance wander, looking about the centre.
    `linger` in [0, 1) makes the walker's speed uneven (1 - linger to 1 + linger of the mean, twice
    over the walk), so frames taken at a steady rate crowd where the walker lingers."""
    start, height, phase = rng.uniform(0, 2 * math.pi), rng.uniform(20, 35), rng.uniform(0, 2 * math.pi)
    poses: list[Pose] = []
    for k in range(count):
        clock = k / max(count - 1, 1)
        t = clock + linger * (math.sin(4 * math.pi * clock + phase) - math.sin(phase)) / (4 * math.pi)  # walked
        azimuth = start + math.radians(240) * t
        elevation = math.radians(height + 15 * math.sin(phase + 3 * math.pi * t))
        radius = RADIUS * (1 + 0.12 * math.sin(phase + 5 * math.pi * t))
        target = [rng.gauss(0, 0.15), rng.gauss(0, 0.15), rng.gauss(0, 0.1)]
        poses.append((_eye(azimuth, elevation, radius), target))
    return poses


def ring_sweep(rng: random.Random, count: int) -> list[Pose]:
    """A ring whose elevation rises from 0 to 50 degrees (as donut_200's test split), at a random phase."""
    phase = rng.uniform(0, 2 * math.pi)
    return [(_eye(phase + 2 * math.pi * k / count, math.radians(50 * k / max(count - 1, 1))), [0.0, 0.0, 0.0])
            for k in range(count)]


def cap(rng: random.Random, count: int) -> list[Pose]:
    """Random poses from above (elevation 50 to 85 degrees)."""
    lo, hi = math.sin(math.radians(50)), math.sin(math.radians(85))
    return [(_eye(rng.uniform(0, 2 * math.pi), math.asin(rng.uniform(lo, hi))), [0.0, 0.0, 0.0])
            for _ in range(count)]


def side(rng: random.Random, count: int, place: random.Random | None = None) -> list[Pose]:
    """One side only: random poses within 70 degrees of azimuth of a random direction, low to middle
    height, nearer than the candidates (where a viewer stands in front of the scene). The direction is
    drawn from `place` (default rng): the val split passes the test split's seed, so the target views
    stand on the test views' side, at other poses."""
    facing = (place or rng).uniform(0, 2 * math.pi)
    return [(_eye(facing + rng.uniform(-1.2, 1.2), math.radians(rng.uniform(5, 40)), RADIUS * rng.uniform(0.8, 1.0)),
             [0.0, 0.0, 0.0]) for _ in range(count)]


CANDIDATE_SHAPES: dict[str, Callable[[random.Random, int], list[Pose]]] = {
    "hemisphere": hemisphere, "rings": rings, "path": path}
TEST_SHAPES: dict[str, Callable[[random.Random, int], list[Pose]]] = {
    "ring_sweep": ring_sweep, "cap": cap, "side": side, "hemisphere": hemisphere}


# ----------------------------------------------------------------------------- writing a scene

def write_split(root: Path, split: str, poses: list[Pose], renderer: GaussianRenderer) -> None:
    """transforms_<split>.json and its RGBA PNGs."""
    frames = []
    (root / split).mkdir(parents=True, exist_ok=True)
    for k, (eye, target) in enumerate(poses):
        camera = look_at(eye, target, width=SIZE, height=SIZE, fov_x=FOV_X)
        out = renderer.render_full(camera)
        alpha = out.alpha[0, ..., None]
        colour = torch.where(alpha > 0, out.color[0] / alpha.clamp_min(1e-12), torch.zeros_like(out.color[0]))
        write_bytes_atomic(root / split / f"r_{k}.png", png_bytes(torch.cat([colour, alpha], -1)))
        frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": camera.c2w.tolist()})
    write_json_atomic(root / f"transforms_{split}.json", {"camera_angle_x": FOV_X, "frames": frames})


def scene_plan(index: int) -> dict:
    """Scene `index`'s draws (seeded): its layout and its camera shapes."""
    rng = random.Random(FAMILY_SEED * 1000 + index)
    candidates = list(CANDIDATE_SHAPES)[index % len(CANDIDATE_SHAPES)]
    test = list(TEST_SHAPES)[(index // len(CANDIDATE_SHAPES)) % len(TEST_SHAPES)]
    return {"name": f"held_{index:02d}", "layout": draw_layout(rng, 1 + index % 4), "train": candidates,
            "test": test, "val": test, "seeds": {split: rng.randrange(1 << 30) for split in COUNTS}}


def capture_plan(kind: str, index: int) -> dict:
    """Walk or room scene `index`'s draws (seeded apart from the other kinds'): its layout, its walk's
    seed and a room's."""
    rng = random.Random(FAMILY_SEED * 1000 + CAPTURES[kind] + index)
    plan = {"name": f"{kind}_{index:02d}", "layout": draw_layout(rng, 1 + index % 4), "train": kind, "test": kind,
            "val": kind, "seeds": {"walk": rng.randrange(1 << 30)}}
    if kind == "room":
        plan["seeds"]["room"] = rng.randrange(1 << 30)
    return plan


def walk(plan: dict) -> list[Pose]:
    """The frames of a walk or room scene's capture: one uneven walk (`path` with LINGER)."""
    return path(random.Random(plan["seeds"]["walk"]), WALK_FRAMES, LINGER)


def split_poses(plan: dict) -> dict[str, list[Pose]]:
    """Each split's poses. A walk scene is a capture along one uneven walk (`path` with LINGER) held out
    as cup_colmap is: every HOLDOUT-th frame a test view, the rest both the candidates and the target
    views (a capture is looked at from where it was walked, as cup_colmap's `+targets` runs are told)."""
    if plan["train"] == "walk":
        frames = walk(plan)
        rest = [pose for k, pose in enumerate(frames) if k % HOLDOUT]
        return {"train": rest, "val": rest, "test": frames[::HOLDOUT]}
    shapes = {**CANDIDATE_SHAPES, **TEST_SHAPES}
    poses = {}
    for split, count in COUNTS.items():
        rng = random.Random(plan["seeds"][split])
        if split == "val" and plan["val"] == "side":     # where the model will be looked at: the test views' side
            poses[split] = side(rng, count, place=random.Random(plan["seeds"]["test"]))
        else:
            poses[split] = shapes[plan[split]](rng, count)
    return poses


def write_capture(root: Path, poses: list[Pose], model: GaussianModel, seed: int) -> None:
    """A COLMAP capture of `model` from `poses`: opaque PNGs in images/, sparse/0 with the cameras
    and ROOM_POINTS of the opaque splats' centres as its SfM points (drawn by `seed`)."""
    renderer = GaussianRenderer(model, (1.0, 1.0, 1.0))
    cameras = [look_at(eye, target, width=SIZE, height=SIZE, fov_x=FOV_X) for eye, target in poses]
    names = [f"r_{k:03d}.png" for k in range(len(cameras))]
    (root / "images").mkdir(parents=True, exist_ok=True)
    for camera, name in zip(cameras, names):
        write_bytes_atomic(root / "images" / name, png_bytes(renderer.render(camera)[0]))
    write_colmap_text(root / "sparse" / "0", cameras, names)
    opaque = torch.nonzero(torch.sigmoid(model.opacity_logits) > 0.5).flatten()
    chosen = opaque[torch.randperm(len(opaque), generator=torch.Generator().manual_seed(seed))[:ROOM_POINTS]]
    rgb = ((model.sh[chosen, 0] * SH_C0 + 0.5).clamp(0, 1) * 255).round().int().tolist()
    lines = ["# POINT3D_ID X Y Z R G B ERROR TRACK[]"] + [
        f"{k + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0.5" for k, ((x, y, z), (r, g, b))
        in enumerate(zip(model.means[chosen].double().tolist(), rgb))]
    write_bytes_atomic(root / "sparse" / "0" / "points3D.txt", ("\n".join(lines) + "\n").encode())


def write_scene(plan: dict, models: dict[str, GaussianModel], out: Path) -> None:
    model = compose(plan["layout"], models)
    if plan["train"] == "room":     # the layout in its room, captured along a walk
        opaque = model.means[torch.sigmoid(model.opacity_logits) > 0.5, 2].double()
        model = merged([model, room(random.Random(plan["seeds"]["room"]), float(opaque.quantile(0.02)))])
        write_capture(out / plan["name"], walk(plan), model, plan["seeds"]["room"])
    else:
        renderer = GaussianRenderer(model, (1.0, 1.0, 1.0))
        for split, poses in split_poses(plan).items():
            write_split(out / plan["name"], split, poses, renderer)
    print(f"{plan['name']}: {len(plan['layout'])} objects "
          f"({', '.join(p['asset'] for p in plan['layout'])}), {model.num_splats} splats, "
          f"candidates {plan['train']}, test {plan['test']}", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--scenes", type=int, default=SCENES)
    p.add_argument("--walks", type=int, default=WALKS)
    p.add_argument("--rooms", type=int, default=ROOMS)
    args = p.parse_args()
    torch.set_num_threads(1)
    models = assets(args.out)
    plans = ([scene_plan(i) for i in range(args.scenes)] + [capture_plan("walk", i) for i in range(args.walks)]
             + [capture_plan("room", i) for i in range(args.rooms)])
    for plan in plans:
        write_scene(plan, models, args.out)
    record = {"family_seed": FAMILY_SEED, "size": SIZE, "counts": COUNTS, "walk_frames": WALK_FRAMES,
              "linger": LINGER, "room": {"radius": ROOM_RADIUS, "height": ROOM_HEIGHT, "spacing": ROOM_SPACING,
                                         "points": ROOM_POINTS}, "scenes": plans}
    write_result(args.out / "layouts.json", record)
    write_result(RESULTS / "nbv_scenes.json", record)
    print(json.dumps({"scenes": len(plans), "out": str(args.out)}))


if __name__ == "__main__":
    main()
