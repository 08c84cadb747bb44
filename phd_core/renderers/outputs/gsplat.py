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
   negated if that would be a reflection); z is the direction of least spread.
3. newer gsplat only: a half turn about x when the points' median z exceeds their mean z.

Versions differ (step 3 is recent; without points only step 1 runs), so each candidate
(1+2+3, 1+2, 1; or none when cfg.yml turns normalisation off) maps the SfM points into the
model frame, and the one whose points lie nearest the splats is used; that residual (the
median distance from a point to the nearest splat centre, relative to the median camera
distance) is reported. The splats are moved into the capture's frame on loading. Training
cameras: the capture's images but every `test_every`-th (cfg.yml, default 8) by name; the
background is black (the trainer's).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from ...data.colmap import find_model, load_colmap
from ...errors import InputError
from ...io.foreign import read_checkpoint, read_yaml, yaml_path
from ...scene import IDENTITY, Camera, Similarity
from ..gs3d import GaussianModel
from .base import OUTPUTS, OutputFormat, TrainerOutput, data_candidates, nearest_distances, sh_from_parts

_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
CHECKPOINT = re.compile(r"ckpt_(\d+)_rank(\d+)\.pt")
SPLAT_KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
FIT_WARNING = 0.1          # residual (x the median camera distance) above which no candidate frame fits
RESIDUAL_POINTS = 2000     # SfM points the residual is measured on (every n-th)
RESIDUAL_SPLATS = 50_000   # splat centres they are compared with (every n-th)
HALF_TURN_X = Similarity.make(1.0, torch.diag(torch.tensor([1.0, -1.0, -1.0])), torch.zeros(3))


def detect(path: Path) -> bool:
    return path.is_dir() and any(CHECKPOINT.fullmatch(p.name) for p in (path / "ckpts").glob("ckpt_*.pt"))


def read(folder: Path) -> TrainerOutput:
    checkpoints = {(int(m.group(1)), -int(m.group(2))): p for p in (folder / "ckpts").glob("ckpt_*.pt")
                   if (m := CHECKPOINT.fullmatch(p.name))}
    source = checkpoints[max(checkpoints)]                       # the latest step, rank 0 first
    model = checkpoint_model(source)
    config = read_yaml(folder / "cfg.yml") if (folder / "cfg.yml").is_file() else {}
    if not isinstance(config, dict):
        raise InputError("cfg.yml", "must be a mapping (the trainer's Config)")
    if config.get("data_type", "colmap") != "colmap":
        raise InputError("cfg.yml.data_type", f"only COLMAP captures are read, got {config['data_type']!r}")
    capture = _find_capture(folder, yaml_path(config.get("data_dir")))
    background = (0.0, 0.0, 0.0)
    if capture is None:
        return TrainerOutput(model, [], background, source, warnings=[
            f"the COLMAP capture of this run was not found (cfg.yml data_dir: {config.get('data_dir')!r}, looked from "
            f"the working directory and every folder above {folder}): no training cameras, and poses are in gsplat's "
            "normalised frame"])
    dataset = load_colmap(capture, "all", with_images=False)
    cameras = dataset.cameras                                                          # sorted by name
    points = None if dataset.points is None else dataset.points.numpy()               # [P, 3] float64
    test_every = config.get("test_every", 8)
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 1:
        raise InputError("cfg.yml.test_every", f"must be a positive integer, got {test_every!r}")
    trained = [i for i in range(len(cameras)) if i % test_every] or list(range(len(cameras)))
    training = [cameras[i] for i in trained]
    if config.get("normalize_world_space", True) is False:
        candidates = {"none (normalize_world_space is off)": IDENTITY}
    else:
        candidates = normalisations(cameras, points)
    name, frame, residual = best_frame(model, candidates, cameras, points)
    notes = [f"gsplat checkpoint {source.name}: world frame recomputed from {capture} ({name})"
             + ("" if residual is None else f"; residual {residual:.3g} (median distance from an SfM point to the "
                "nearest splat, x the median camera distance)")]
    warnings = []
    if residual is not None and residual > FIT_WARNING:
        warnings.append(f"no normalisation of gsplat's fits this checkpoint to {capture}: the SfM points lie "
                        f"{residual:.3g} camera distances from the nearest splat (wrong capture, or another trainer "
                        "version)")
    splits = {"train": trained, "test": sorted(set(range(len(cameras))) - set(trained))}
    return TrainerOutput(model.transformed(frame.inverse()), training, background, source, frame=frame,
                         notes=notes, warnings=warnings, camera_format="colmap", capture=capture, splits=splits)


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
    """gsplat's normalisations of a capture (all its images, sorted by name), newest version first."""
    c2w = np.stack([(c.c2w @ _GL_TO_CV).numpy() for c in cameras])                 # [N, 4, 4] OpenCV
    from_cameras = cameras_similarity(c2w)
    if points is None or len(points) < 3:
        return {"similarity from the cameras (the capture has no SfM points)": from_cameras}
    cloud = torch.from_numpy(np.asarray(points, dtype=np.float32).astype(np.float64))    # [P, 3] as gsplat holds them
    axes = from_cameras.then(principal_axes(from_cameras.points(cloud).numpy()))
    moved = axes.points(cloud).numpy()
    found = {}
    if np.median(moved[:, 2]) > np.mean(moved[:, 2]):
        found["cameras, principal axes of the points, upside-down turn"] = axes.then(HALF_TURN_X)
    found["cameras and principal axes of the points"] = axes
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
    """Step 2 from the points after step 1 ([P, 3] float64)."""
    centre = np.median(points, axis=0)
    values, vectors = np.linalg.eigh(np.cov(points - centre, rowvar=False))
    vectors = vectors[:, np.argsort(values)[::-1]]
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] *= -1
    rotation = vectors.T
    return Similarity.make(1.0, torch.from_numpy(rotation), torch.from_numpy(-rotation @ centre))


def best_frame(model: GaussianModel, candidates: dict[str, Similarity], cameras: list[Camera],
               points: np.ndarray | None) -> tuple[str, Similarity, float | None]:
    """The candidate that maps the SfM points nearest the splats, and its residual (None without points)."""
    if points is None or len(points) == 0 or len(candidates) == 1:
        name = next(iter(candidates))
        return name, candidates[name], residual(model, candidates[name], cameras, points)
    scored = [(residual(model, frame, cameras, points), name) for name, frame in candidates.items()]
    best, name = min(scored)
    return name, candidates[name], best


def residual(model: GaussianModel, frame: Similarity, cameras: list[Camera], points: np.ndarray | None) -> float | None:
    """Median distance from the SfM points (mapped by `frame`) to the nearest splat centre,
    divided by the median camera distance from the cameras' median centre (model frame)."""
    if points is None or len(points) == 0 or model.num_splats == 0:
        return None
    pts = frame.points(torch.from_numpy(np.asarray(points, dtype=np.float64))[::max(1, len(points) // RESIDUAL_POINTS)])
    splats = model.means[::max(1, model.num_splats // RESIDUAL_SPLATS)]
    centres = frame.points(torch.stack([c.center for c in cameras]))                  # [N, 3]
    spread = float((centres - centres.median(dim=0).values).norm(dim=-1).median()) or 1.0
    return float(nearest_distances(pts, splats).median()) / spread


def _find_capture(folder: Path, data: Path | None) -> Path | None:
    for candidate in [] if data is None else data_candidates(folder, data):
        model_dir = find_model(candidate) if candidate.is_dir() else None
        if model_dir is not None:
            return model_dir
    return None


OUTPUTS.register(OutputFormat("gsplat", "a gsplat result folder (ckpts/ckpt_*_rank*.pt, with cfg.yml naming its "
                              "COLMAP capture)", detect, read, order=30))
