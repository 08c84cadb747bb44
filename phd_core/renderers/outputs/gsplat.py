"""gsplat's example trainer (examples/simple_trainer.py) result folder, with the COLMAP
capture it was trained on:

    results/<scene>/
      cfg.yml                        the run's Config (YAML; data_dir, normalize_world_space, test_every)
      ckpts/ckpt_29999_rank0.pt      torch.save({"step": ..., "splats": {...}}), the latest step is used

`splats` holds means [N, 3], quats [N, 4] (wxyz), scales [N, 3] (log), opacities [N]
(logit), sh0 [N, 1, 3] and shN [N, K-1, 3]; loaded with weights_only (tensors only). Runs
with appearance optimisation (`features`, `colors`: a network colours the splats) are refused.

Frame. With normalize_world_space (the default) the trainer's COLMAP parser normalises the
world and saves the transform nowhere. It is deterministic, so it is recomputed here from the
capture (every registered image sorted by name, OpenCV camera-to-world; every SfM point, as
float32), in three steps, each a similarity:

1. from the cameras: the mean of the cameras' up axes (-y) is turned onto -y (the rotation
   about their cross product); the origin moves to the per-axis median of the points of each
   optical axis nearest the old origin; the scale makes the median camera distance 1.
2. principal axes of the points after step 1: centred on their per-axis median and turned so
   that x, y, z follow the covariance's eigenvectors by decreasing eigenvalue (the first one
   negated if that would be a reflection); z is the direction of least spread. Each
   eigenvector's sign is the numerical library's choice, so four frames are possible: the
   axes as computed here (largest component of each positive) or turned half about x, y or z.
3. gsplat >= 1.5.2 only: a half turn about x when the points' median z exceeds their mean z
   (one of the four frames again).

So the candidates are the four sign patterns and the cameras' similarity alone (or none when
cfg.yml turns normalisation off). Each maps the SfM points into the model frame; its residual
is the median distance from a point to the nearest splat centre, in units of the median camera
distance. The best is kept when every other residual is at least RESIDUAL_MARGIN times
larger (and RESIDUAL_GAP more); otherwise two of the capture's views are rendered under each
close candidate and compared with the photos (PSNR; alpha coverage when the photos cannot be
read). A best residual above FIT_WARNING, or above SPACING_WARNING times the SfM points' own
spacing, is warned about (wrong capture, or a trainer version this does not know). The note
names the frame, the residuals and, when renders decided, their scores. The splats are moved
into the capture's frame on loading. Training cameras: the capture's images but every
`test_every`-th (cfg.yml, default 8) by name; the background is black (the trainer's).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ...data.colmap import find_model, load_colmap
from ...errors import InputError
from ...eval.image import psnr
from ...io.configs import GsplatConfig, parse_config
from ...io.foreign import read_checkpoint, read_yaml
from ...scene import IDENTITY, Camera, Similarity
from ..gs3d import GaussianModel, GaussianRenderer
from ..gs3d.render import view_memory
from .base import OUTPUTS, OutputFormat, TrainerOutput, data_candidates, nearest_distances, sh_from_parts

_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
CHECKPOINT = re.compile(r"ckpt_(\d+)_rank(\d+)\.pt")
SPLAT_KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
# Residuals are in units of the capture's median camera distance (the camera spread).
FIT_WARNING = 0.1          # above this no candidate frame fits
SPACING_WARNING = 4.0      # ... nor above this many times the SfM points' own spacing (a normalised
                           # scene of any capture lies about 0.07 from any other: the spacing tells)
RESIDUAL_MARGIN = 2.0      # a best frame is clear when every other residual is at least this many times its own
RESIDUAL_GAP = 0.005       # ... and at least this much larger
RESIDUAL_POINTS = 2000     # SfM points the residual is measured on (every n-th)
RESIDUAL_SPLATS = 50_000   # splat centres they are compared with (every n-th)
RENDERED_VIEWS = 2         # views rendered per candidate when the residuals are too close
RENDERED_SIZE = 64         # at most this many pixels a side
RENDER_SHARE = 2           # those renders may hold this many times the model's bytes (or RENDER_FLOOR): a reader
RENDER_FLOOR = 64 << 20    # takes memory in proportion to its model, as the service reserves it (20 M splats of
                           # scale 1 at one point asked for 29.8 GiB here)
# The principal axes' sign patterns that are rotations (eigh picks each eigenvector's sign,
# the determinant check flips the first when they form a mirror): the same axes, or them
# turned half about one axis. gsplat >= 1.5.2's upside-down fix is the half turn about x.
SIGN_PATTERNS = {(1.0, 1.0, 1.0): "as computed", (-1.0, -1.0, 1.0): "turned half about z",
                 (-1.0, 1.0, -1.0): "turned half about y", (1.0, -1.0, -1.0): "turned half about x"}


def detect(path: Path) -> bool:
    return path.is_dir() and any(CHECKPOINT.fullmatch(p.name) for p in (path / "ckpts").glob("ckpt_*.pt"))


def read(folder: Path, within: Path | None = None) -> TrainerOutput:
    checkpoints = {(int(m.group(1)), -int(m.group(2))): p for p in (folder / "ckpts").glob("ckpt_*.pt")
                   if (m := CHECKPOINT.fullmatch(p.name))}
    source = checkpoints[max(checkpoints)]                       # the latest step, rank 0 first
    config = parse_config(GsplatConfig, read_yaml(folder / "cfg.yml") if (folder / "cfg.yml").is_file() else {},
                          "cfg.yml")
    model = checkpoint_model(source)
    capture = _find_capture(folder, config.data_dir, within)
    background = (0.0, 0.0, 0.0)
    if capture is None:
        return TrainerOutput(model, [], background, source, warnings=[
            f"the COLMAP capture of this run was not found (cfg.yml data_dir: {config.data_dir}, looked from the "
            f"working directory and every folder above {folder}): no training cameras, and poses are in gsplat's "
            "normalised frame"], name=f"{folder.resolve().name}/gsplat")
    dataset = load_colmap(capture, "all", with_images=False)
    cameras = dataset.cameras                                                          # sorted by name
    points = None if dataset.points is None else dataset.points.numpy()               # [P, 3] float64
    trained = [i for i in range(len(cameras)) if i % config.test_every] or list(range(len(cameras)))
    training = [cameras[i] for i in trained]
    if not config.normalize_world_space:
        candidates = {"none (normalize_world_space is off)": IDENTITY}
    else:
        candidates = normalisations(cameras, points)
    choice = best_frame(model, candidates, cameras, points, capture)
    spacing = None if points is None or len(points) < 2 else point_spacing(cameras, points)
    notes = [f"gsplat checkpoint {source.name}: world frame recomputed from {capture}: {describe(choice)}"
             + ("" if spacing is None else f"; the SfM points' own spacing: {spacing:.3g}")]
    warnings = []
    if choice.residual is not None and (choice.residual > FIT_WARNING
                                        or (spacing and choice.residual > SPACING_WARNING * spacing)):
        warnings.append(f"no normalisation of gsplat's fits this checkpoint to {capture}: the SfM points lie "
                        f"{choice.residual:.3g} camera distances from the nearest splat"
                        + (f", {choice.residual / spacing:.1f} times their own spacing" if spacing else "")
                        + " (wrong capture, or another trainer version)")
    if choice.unrendered is not None:
        warnings.append(f"the closest frames of this gsplat checkpoint were not rendered to tell them apart: their "
                        f"renders would hold {choice.unrendered[0] >> 20} MiB, more than the "
                        f"{choice.unrendered[1] >> 20} MiB allowed beside a model of its size, so the frame with the "
                        "lowest residual was taken; render a training view to check")
    if choice.renders is not None and choice.judged_by == "alpha coverage":
        warnings.append(f"the frame of this gsplat checkpoint was chosen by how much of {RENDERED_VIEWS} views its "
                        f"splats cover ({capture}'s photos could not be read), which tells frames apart poorly (a "
                        "cluttered scene covers a view in a wrong frame too): render a training view to check")
    splits = {"train": trained, "test": sorted(set(range(len(cameras))) - set(trained))}
    return TrainerOutput(model.transformed(choice.frame.inverse()), training, background, source, frame=choice.frame,
                         notes=notes, warnings=warnings, camera_format="colmap", capture=capture, splits=splits,
                         name=f"{folder.resolve().name}/gsplat")


def checkpoint_model(path: Path) -> GaussianModel:
    data = read_checkpoint(path)
    splats = data.get("splats") if isinstance(data, dict) else None
    if not isinstance(splats, dict):
        raise InputError(f"{path.name}.splats", "missing: a gsplat checkpoint is a dict whose 'splats' holds the "
                                                "splat tensors")
    if "features" in splats or "colors" in splats:
        raise InputError(f"{path.name}.splats.features", "appearance-optimised runs (app_opt) colour splats with a "
                                                         "network: not supported, train without --app_opt")
    for key in SPLAT_KEYS:
        value = splats.get(key)
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            raise InputError(f"{path.name}.splats.{key}", "missing or not a floating-point tensor")
    model = GaussianModel(splats["means"].float(), splats["scales"].float(), splats["quats"].float(),
                          splats["opacities"].float(),
                          sh_from_parts(splats["sh0"].float(), splats["shN"].float(), f"{path.name}.splats.shN"))
    try:
        model.validate()
    except InputError as exc:
        raise InputError(f"{path.name}.splats.{exc.field}", exc.reason) from None
    return model


# ----------------------------------------------------------------------------- the normalisation

def normalisations(cameras: list[Camera], points: np.ndarray | None) -> dict[str, Similarity]:
    """Every world frame gsplat's parser can give a capture (all its images, sorted by name):
    the four sign patterns of the principal axes (their eigenvectors' signs are the numerical
    library's choice, and the upside-down turn of gsplat >= 1.5.2 is one of them), then the
    cameras' similarity alone (no points)."""
    c2w = np.stack([(c.c2w @ _GL_TO_CV).numpy() for c in cameras])                 # [N, 4, 4] OpenCV
    from_cameras = cameras_similarity(c2w)
    if points is None or len(points) < 3:
        return {"similarity from the cameras (the capture has no SfM points)": from_cameras}
    cloud = torch.from_numpy(np.asarray(points, dtype=np.float32).astype(np.float64))    # [P, 3] as gsplat holds them
    axes = from_cameras.then(principal_axes(from_cameras.points(cloud).numpy()))
    found = {}
    for signs, turn in SIGN_PATTERNS.items():
        frame = axes.then(Similarity.make(1.0, torch.diag(torch.tensor(signs)), torch.zeros(3)))
        z = frame.points(cloud)[:, 2]
        versions = "every gsplat" if z.median() <= z.mean() else "gsplat <= 1.5.1; 1.5.2 on turns it over"
        found[f"principal axes {turn} [{versions}]"] = frame
    found["similarity from the cameras only"] = from_cameras
    return found


def cameras_similarity(c2w: np.ndarray) -> Similarity:
    """Step 1 from OpenCV camera-to-world matrices [N, 4, 4]."""
    rotations, centres = c2w[:, :3, :3], c2w[:, :3, 3]                             # [N, 3, 3], [N, 3]
    up = -rotations[:, :, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    target = np.array([0.0, -1.0, 0.0])
    cos = float(up @ target)
    if cos > -1:
        v = np.cross(up, target)
        skew = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
        align = np.eye(3) + skew + skew @ skew / (1 + cos)
    else:
        # Up is exactly +y (gsplat negates x there, a mirror): a half turn about z, a rotation.
        align = np.diag([-1.0, -1.0, 1.0])
    forward = (align @ rotations)[:, :, 2]                                         # [N, 3]
    centres = centres @ align.T
    nearest = centres + np.sum(forward * -centres, axis=-1, keepdims=True) * forward
    translate = -np.median(nearest, axis=0)
    scale = 1.0 / np.median(np.linalg.norm(centres + translate, axis=-1))
    return Similarity.make(scale, torch.from_numpy(align), torch.from_numpy(scale * translate))


def principal_axes(points: np.ndarray) -> Similarity:
    """Step 2 from the points after step 1 ([P, 3] float64), with each eigenvector's largest
    component made positive (so the sign patterns are named the same on every machine)."""
    centre = np.median(points, axis=0)
    values, vectors = np.linalg.eigh(np.cov(points - centre, rowvar=False))
    vectors = vectors[:, np.argsort(values)[::-1]]
    vectors *= np.sign(vectors[np.abs(vectors).argmax(axis=0), range(3)])
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] *= -1
    rotation = vectors.T
    return Similarity.make(1.0, torch.from_numpy(rotation), torch.from_numpy(-rotation @ centre))


@dataclass
class FrameChoice:
    """The frame a checkpoint was found in, and how it was told from the others."""

    name: str
    frame: Similarity                     # user frame -> gsplat's frame
    residual: float | None                # None: no SfM points to measure with
    runner_up: tuple[str, float] | None   # the second-best candidate and its residual
    renders: dict[str, float] | None      # when the residuals were too close: each close frame's render score
    judged_by: str = ""                   # what the render score is ("PSNR against the photos", "alpha coverage")
    unrendered: tuple[int, int] | None = None   # (bytes the renders would hold, bytes allowed) when too many


def best_frame(model: GaussianModel, candidates: dict[str, Similarity], cameras: list[Camera],
               points: np.ndarray | None, capture: Path | None = None) -> FrameChoice:
    """The candidate that maps the SfM points nearest the splats. The residuals are in units of
    the capture's camera distance; when another candidate is not clearly worse (under
    RESIDUAL_MARGIN times the best, or within RESIDUAL_GAP of it), RENDERED_VIEWS of the
    capture's views are rendered under each close candidate and the one that looks most like
    the photos wins (without the photos: the one whose alpha covers more of the views), unless
    the renders would hold more than RENDER_SHARE times the model (the best residual wins then)."""
    if points is None or len(points) == 0 or len(candidates) == 1:
        name = next(iter(candidates))
        return FrameChoice(name, candidates[name], residual(model, candidates[name], cameras, points), None, None)
    scored = sorted((residual(model, frame, cameras, points) or 0.0, name) for name, frame in candidates.items())
    (best, name), (second, second_name) = scored[0], scored[1]
    close = [n for r, n in scored if r < max(RESIDUAL_MARGIN * best, best + RESIDUAL_GAP)]
    if len(close) == 1:
        return FrameChoice(name, candidates[name], best, (second_name, second), None)
    need = render_bytes(model, {n: candidates[n] for n in close}, cameras)
    allowed = max(RENDER_SHARE * sum(t.numel() * t.element_size() for t in model.tensors()), RENDER_FLOOR)
    if need > allowed:
        return FrameChoice(name, candidates[name], best, (second_name, second), None, unrendered=(need, allowed))
    judged_by, renders = render_scores(model, {n: candidates[n] for n in close}, cameras, capture)
    chosen, runner_up = sorted(close, key=lambda n: -renders[n])[:2]
    by_residual = {n: r for r, n in scored}
    return FrameChoice(chosen, candidates[chosen], by_residual[chosen], (runner_up, by_residual[runner_up]), renders,
                       judged_by)


def rendered_views(cameras: list[Camera]) -> tuple[list[int], float]:
    """(the RENDERED_VIEWS views spread over the capture, the downscale to RENDERED_SIZE)."""
    views = np.linspace(0, len(cameras) - 1, RENDERED_VIEWS + 2, dtype=int)[1:-1].tolist()
    return views, max(1.0, max(cameras[0].width, cameras[0].height) / RENDERED_SIZE)


def render_bytes(model: GaussianModel, frames: dict[str, Similarity], cameras: list[Camera]) -> int:
    """The most any of `render_scores`' renders holds: the family's bound (`view_memory`, which
    projects the splats a chunk at a time), before anything renders."""
    renderer, (views, factor) = GaussianRenderer(model, (0.0, 0.0, 0.0)), rendered_views(cameras)
    bounds = [view_memory(renderer, frame.camera(cameras[i].scaled(factor)))
              for frame in frames.values() for i in views]
    return max(bound.fixed + bound.per_mask for bound in bounds)


def render_scores(model: GaussianModel, frames: dict[str, Similarity], cameras: list[Camera],
                  capture: Path | None) -> tuple[str, dict[str, float]]:
    """(what was measured, a score per frame, higher is better): `rendered_views` rendered with
    the cameras moved into gsplat's frame, scored by their PSNR against the capture's photos,
    or, when the photos cannot be read, by the mean alpha (how much of the views the splats
    cover)."""
    views, factor = rendered_views(cameras)
    photos = None
    if capture is not None:
        try:
            photos = load_colmap(capture, "all", views=views, downscale=factor, background=(0.0, 0.0, 0.0))
        except InputError:
            photos = None
    small = photos.cameras if photos is not None else [cameras[i].scaled(factor) for i in views]
    renderer = GaussianRenderer(model, (0.0, 0.0, 0.0))
    scores = {}
    for name, frame in frames.items():
        out = [renderer.render_full(frame.camera(camera)) for camera in small]
        if photos is not None and photos.images is not None:
            scores[name] = sum(psnr(o.rgb[0], image) for o, image in zip(out, photos.images)) / len(out)
        else:
            scores[name] = sum(float(o.alpha.mean()) for o in out) / len(out)
    return ("PSNR against the photos" if photos is not None else "alpha coverage"), scores


def describe(choice: FrameChoice) -> str:
    """The note on the chosen frame: its name, residual, the runner-up and, when renders decided, their scores."""
    text = choice.name
    if choice.residual is not None:
        text += (f"; residual {choice.residual:.3g} (median distance from an SfM point to the nearest splat, x the "
                 "median camera distance)")
    if choice.runner_up is not None:
        text += f"; next best: {choice.runner_up[0]}, residual {choice.runner_up[1]:.3g}"
    if choice.renders is not None:
        shown = (lambda v: f"{v:.1f} dB") if choice.judged_by.startswith("PSNR") else (lambda v: f"{v:.0%}")
        text += (f"; the residuals were too close to tell, so {RENDERED_VIEWS} views were rendered in each close "
                 f"frame and judged by {choice.judged_by}: {shown(choice.renders[choice.name])} in the chosen one, "
                 + ", ".join(f"{shown(v)} in {n}" for n, v in choice.renders.items() if n != choice.name))
    return text


def residual(model: GaussianModel, frame: Similarity, cameras: list[Camera], points: np.ndarray | None) -> float | None:
    """Median distance from the SfM points (mapped by `frame`) to the nearest splat centre,
    divided by the median camera distance from the cameras' median centre (model frame)."""
    if points is None or len(points) == 0 or model.num_splats == 0:
        return None
    pts = frame.points(torch.from_numpy(np.asarray(points, dtype=np.float64))[::max(1, len(points) // RESIDUAL_POINTS)])
    splats = model.means[::max(1, model.num_splats // RESIDUAL_SPLATS)]
    return float(nearest_distances(pts, splats).median()) / camera_spread(frame.cameras(cameras))


def point_spacing(cameras: list[Camera], points: np.ndarray) -> float:
    """The capture's own resolution: the median distance from an SfM point to the nearest other
    one, in the residual's unit (the median camera distance)."""
    cloud = torch.from_numpy(np.asarray(points, dtype=np.float64))
    sample = cloud[::max(1, len(cloud) // RESIDUAL_POINTS)]
    return float(nearest_distances(sample, cloud, k=2).median()) / camera_spread(cameras)


def camera_spread(cameras: list[Camera]) -> float:
    """The median distance of the camera centres from their per-axis median (1 when they coincide)."""
    centres = torch.stack([c.center for c in cameras])                                  # [N, 3]
    return float((centres - centres.median(dim=0).values).norm(dim=-1).median()) or 1.0


def _find_capture(folder: Path, data: Path | None, within: Path | None) -> Path | None:
    for candidate in [] if data is None else data_candidates(folder, data, within):
        model_dir = find_model(candidate) if candidate.is_dir() else None
        if model_dir is not None:
            return model_dir
    return None


OUTPUTS.register(OutputFormat("gsplat", "a gsplat result folder (ckpts/ckpt_*_rank*.pt, with cfg.yml naming its "
                              "COLMAP capture)", detect, read, order=30))
