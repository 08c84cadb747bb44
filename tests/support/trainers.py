"""Output folders written the way nerfstudio's splatfacto and gsplat's simple_trainer write
them, from a scene in the user's frame: a YAML config with Python tags, a JSON
dataparser_transforms, a binary PLY with nerfstudio's header, checkpoints written with
torch.save of plain tensors and dicts.

The trainers' world normalisations are written here from their descriptions, as 4x4 numpy
matrices (not with the library's `Similarity`), so a loader that got a frame wrong
disagrees with them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from phd_core.renderers.gs3d import GaussianModel
from phd_core.scene import Camera, look_at

from .captures import rotation_to_quaternion, write_colmap

# The applied_transform the nerfstudio dataparser assumes for COLMAP data written before the key
# existed: swap x and y, negate z.
APPLIED_TRANSFORM = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0, 0, 0, 1]])
# The one ns-process-data (colmap_to_json, nerfstudio 1.1.5) writes: y and z swapped, then the new z negated.
APPLIED_TRANSFORM_1_1_5 = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0, 0, 0, 1]])
CV = np.diag([1.0, -1.0, -1.0, 1.0])
SH_C0 = 0.28209479177387814     # the degree-0 SH basis constant: colour = 0.5 + SH_C0 * coefficient


def scene_cameras(count: int, *, size: int = 20, centre=(2.0, -1.0, 0.5), radius: float = 3.0) -> list[Camera]:
    """Cameras on a wobbly ring around `centre`, looking at it, up +z: a capture not centred at the origin."""
    cameras = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = (centre[0] + radius * math.cos(a), centre[1] + radius * math.sin(a),
               centre[2] + 0.8 + 0.3 * math.sin(3 * a))
        cameras.append(look_at(eye, centre, (0, 0, 1), width=size, height=size, fov_x=0.8))
    return cameras


def scene_splats(count: int, *, sh_coeffs: int = 1, centre=(2.0, -1.0, 0.5), seed: int = 0) -> GaussianModel:
    """Splats in a flattened box around `centre` (wider than tall, like a table top scene)."""
    g = torch.Generator().manual_seed(seed)
    spread = torch.tensor([1.2, 0.9, 0.4])
    return GaussianModel(means=(torch.rand(count, 3, generator=g) - 0.5) * spread + torch.tensor(centre),
                         log_scales=torch.log(0.03 + 0.07 * torch.rand(count, 3, generator=g)),
                         quats=torch.randn(count, 4, generator=g),
                         opacity_logits=torch.rand(count, generator=g) * 4 - 1,
                         sh=torch.randn(count, sh_coeffs, 3, generator=g) * 0.5)


# ----------------------------------------------------------------------------- moving things between frames

def move_model(model: GaussianModel, m: np.ndarray) -> GaussianModel:
    """Splats moved by m = [[s R, t], [0, 1]]; only for SH degree 0 (a colour that does not turn)."""
    assert model.sh.shape[1] == 1
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    turn = torch.tensor(rotation_to_quaternion(m[:3, :3] / s), dtype=torch.float64)
    q = model.quats.double()
    w1, x1, y1, z1 = turn
    w2, x2, y2, z2 = q.unbind(-1)
    quats = torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], dim=-1)
    means = model.means.double().numpy() @ m[:3, :3].T + m[:3, 3]
    return GaussianModel(torch.from_numpy(means).float(), model.log_scales + math.log(s), quats.float(),
                         model.opacity_logits.clone(), model.sh.clone())


def move_camera(camera: Camera, m: np.ndarray) -> Camera:
    """The camera moved by m: centre mapped, axes turned by m's rotation."""
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    c2w = camera.c2w.numpy()
    moved = np.eye(4)
    moved[:3, :3] = m[:3, :3] / s @ c2w[:3, :3]
    moved[:3, 3] = m[:3, :3] @ c2w[:3, 3] + m[:3, 3]
    return Camera(torch.from_numpy(moved), camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)


# ----------------------------------------------------------------------------- nerfstudio splatfacto

def dataparser_transform(cameras: Sequence[Camera]) -> tuple[np.ndarray, float]:
    """(T [4, 4], scale) as the nerfstudio dataparser's defaults make them: orientation "up" (the
    mean camera up turned onto +z), centre "poses" (the mean camera centre to the origin), then
    the largest |coordinate| of a centre scaled to 1."""
    c2w = np.stack([c.c2w.numpy() for c in cameras])
    up = c2w[:, :3, 1].mean(axis=0)
    up /= np.linalg.norm(up)
    axis = np.cross(up, [0.0, 0.0, 1.0])
    angle = math.atan2(np.linalg.norm(axis), up[2])
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = -rotation @ c2w[:, :3, 3].mean(axis=0)
    centres = c2w[:, :3, 3] @ t[:3, :3].T + t[:3, 3]
    return t, 1.0 / float(np.abs(centres).max())


def frame_names(count: int) -> list[str]:
    """Image names written to transforms.json out of name order (the dataparser sorts them)."""
    names = [f"images/frame_{i + 1:05d}.png" for i in range(count)]
    return names[1::2] + names[0::2]


def write_transforms(data: Path, cameras: Sequence[Camera], names: Sequence[str], applied: bool) -> Path:
    """data/transforms.json in the user's frame (+ the applied_transform ns-process-data records)."""
    data.mkdir(parents=True, exist_ok=True)
    frames = [{"file_path": name, "transform_matrix": c.c2w.tolist(), "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx,
               "cy": c.cy, "w": c.width, "h": c.height} for c, name in zip(cameras, names)]
    meta = {"camera_model": "OPENCV", "k1": 0, "k2": 0, "p1": 0, "p2": 0, "frames": frames}
    if applied:
        meta["applied_transform"] = APPLIED_TRANSFORM[:3].tolist()
    (data / "transforms.json").write_text(json.dumps(meta, indent=2))
    return data / "transforms.json"


SPLATFACTO_CONFIG = """!!python/object:nerfstudio.engine.trainer.TrainerConfig
_target: !!python/name:nerfstudio.engine.trainer.Trainer ''
data: !!python/object/apply:pathlib.PosixPath
- data
- {scene}
experiment_name: {scene}
machine: !!python/object:nerfstudio.configs.base_config.MachineConfig
  device_type: cuda
  num_devices: 1
  seed: 42
max_num_iterations: 30000
method_name: {method}
optimizers:
  means:
    optimizer: !!python/object:nerfstudio.engine.optimizers.AdamOptimizerConfig
      _target: &id001 !!python/name:torch.optim.adam.Adam ''
      eps: 1.0e-15
      lr: 0.00016
  quats:
    optimizer: !!python/object:nerfstudio.engine.optimizers.AdamOptimizerConfig
      _target: *id001
      lr: 0.001
output_dir: !!python/object/apply:pathlib.PosixPath
- outputs
pipeline: !!python/object:nerfstudio.pipelines.base_pipeline.VanillaPipelineConfig
  _target: !!python/name:nerfstudio.pipelines.base_pipeline.VanillaPipeline ''
  datamanager: !!python/object:nerfstudio.data.datamanagers.full_images_datamanager.FullImageDatamanagerConfig
    _target: !!python/name:nerfstudio.data.datamanagers.full_images_datamanager.FullImageDatamanager ''
    cache_images: cpu
    data: null
    dataparser: !!python/object:nerfstudio.data.dataparsers.nerfstudio_dataparser.NerfstudioDataParserConfig
      _target: !!python/name:nerfstudio.data.dataparsers.nerfstudio_dataparser.Nerfstudio ''
      auto_scale_poses: true
      center_method: poses
      data: !!python/object/apply:pathlib.PosixPath
      - data
      - {scene}
      eval_interval: 8
      eval_mode: fraction
      load_3D_points: true
      orientation_method: up
      scale_factor: 1.0
      train_split_fraction: 0.9
    eval_image_indices: !!python/tuple
    - 0
  model: !!python/object:nerfstudio.models.splatfacto.SplatfactoModelConfig
    _target: !!python/name:nerfstudio.models.splatfacto.SplatfactoModel ''
    background_color: {background}
    camera_optimizer: !!python/object:nerfstudio.cameras.camera_optimizers.CameraOptimizerConfig
      mode: 'off'
    sh_degree: {sh_degree}
timestamp: 2026-11-25_101500
vis: viewer
"""


def write_splatfacto(root: Path, scene: str, model: GaussianModel, transform: np.ndarray, scale: float, *,
                     export_ply: bool, background: str = "random", method: str = "splatfacto") -> Path:
    """root/outputs/<scene>/splatfacto/<timestamp>/ with `model` (already in the dataparser's
    frame) as exports/splat/splat.ply or as nerfstudio_models/step-000029999.ckpt."""
    folder = root / "outputs" / scene / "splatfacto" / "2026-11-25_101500"
    folder.mkdir(parents=True, exist_ok=True)
    degree = math.isqrt(model.sh.shape[1]) - 1
    (folder / "config.yml").write_text(SPLATFACTO_CONFIG.format(scene=scene, method=method, background=background,
                                                                sh_degree=degree))
    (folder / "dataparser_transforms.json").write_text(json.dumps(
        {"transform": transform[:3].tolist(), "scale": scale}, indent=4))
    if export_ply:
        write_nerfstudio_ply(folder / "exports" / "splat" / "splat.ply", model)
    else:
        write_splatfacto_checkpoint(folder / "nerfstudio_models" / "step-000029999.ckpt", model)
    return folder


def write_nerfstudio_ply(path: Path, model: GaussianModel) -> None:
    """`ns-export gaussian-splat`: comments, then x y z nx ny nz f_dc_* f_rest_* (channel-major)
    opacity scale_* rot_*, one float per property, binary little endian."""
    count, k = model.num_splats, model.sh.shape[1]
    rest = model.sh[:, 1:, :].transpose(1, 2).reshape(count, 3 * (k - 1))
    columns = {"x": model.means[:, 0], "y": model.means[:, 1], "z": model.means[:, 2],
               "nx": torch.zeros(count), "ny": torch.zeros(count), "nz": torch.zeros(count),
               **{f"f_dc_{i}": model.sh[:, 0, i] for i in range(3)},
               **{f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])},
               "opacity": model.opacity_logits,
               **{f"scale_{i}": model.log_scales[:, i] for i in range(3)},
               **{f"rot_{i}": model.quats[:, i] for i in range(4)}}
    header = ("ply\nformat binary_little_endian 1.0\ncomment Generated by Nerstudio 1.1.5\n"
              "comment Vertical Axis: z\n" + f"element vertex {count}\n"
              + "".join(f"property float {name}\n" for name in columns) + "end_header\n")
    body = torch.stack(list(columns.values()), dim=1).numpy().astype("<f4").tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode() + body)


def write_splatfacto_checkpoint(path: Path, model: GaussianModel) -> None:
    """What the nerfstudio trainer saves: step, the pipeline's state dict, optimizer and scaler
    states. With SH degree 0 splatfacto keeps RGB logits in features_dc, not an SH coefficient."""
    prefix = "_model.gauss_params."
    dc = model.sh[:, 0, :] if model.sh.shape[1] > 1 else torch.logit(0.5 + SH_C0 * model.sh[:, 0, :])
    pipeline = {prefix + "means": model.means, prefix + "scales": model.log_scales, prefix + "quats": model.quats,
                prefix + "features_dc": dc, prefix + "features_rest": model.sh[:, 1:, :],
                prefix + "opacities": model.opacity_logits[:, None],
                "datamanager.train_dataset.cameras.camera_to_worlds": torch.zeros(2, 3, 4)}
    optimizers = {"means": {"state": {0: {"step": torch.tensor(29999.0), "exp_avg": torch.zeros_like(model.means)}},
                            "param_groups": [{"lr": 1.6e-6, "betas": (0.9, 0.999), "eps": 1e-15, "params": [0]}]}}
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"step": 29999, "pipeline": pipeline, "optimizers": optimizers, "schedulers": {},
                "scalers": {"scale": 65536.0, "growth_factor": 2.0}}, path)


# ----------------------------------------------------------------------------- gsplat

def gsplat_normalisation(cameras: Sequence[Camera], points: np.ndarray, *, upside_down_fix: bool = True,
                         eigh_signs: Sequence[float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """[4, 4] the world normalisation of gsplat's COLMAP parser (cameras sorted by name, OpenCV).
    Each eigenvector's sign is the numerical library's choice: here each is first made to have
    a positive largest component, then multiplied by `eigh_signs`, so every pattern an eigh
    build can return is reached the same way on every machine."""
    c2w = np.stack([c.c2w.numpy() @ CV for c in cameras])
    r, t = c2w[:, :3, :3], c2w[:, :3, 3]
    up = (r @ np.array([0.0, -1.0, 0.0])).mean(axis=0)
    up /= np.linalg.norm(up)
    down = np.array([0.0, -1.0, 0.0])
    c, v = up @ down, np.cross(up, down)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    align = np.eye(3) + k + k @ k / (1 + c)
    forwards = (align @ r) @ np.array([0.0, 0.0, 1.0])
    t = t @ align.T
    nearest = t + (forwards * -t).sum(-1)[:, None] * forwards
    t1 = np.eye(4)
    t1[:3, :3], t1[:3, 3] = align, -np.median(nearest, axis=0)
    t1[:3, :] /= np.median(np.linalg.norm(t + t1[:3, 3], axis=-1))
    p = points.astype(np.float32) @ t1[:3, :3].T + t1[:3, 3]
    centroid = np.median(p, axis=0)
    values, vectors = np.linalg.eigh(np.cov(p - centroid, rowvar=False))
    vectors = vectors[:, values.argsort()[::-1]]
    vectors = vectors * np.sign(vectors[np.abs(vectors).argmax(axis=0), range(3)]) * np.asarray(eigh_signs)
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] *= -1
    t2 = np.eye(4)
    t2[:3, :3], t2[:3, 3] = vectors.T, -vectors.T @ centroid
    full = t2 @ t1
    p = p @ t2[:3, :3].T + t2[:3, 3]
    if upside_down_fix and np.median(p[:, 2]) > np.mean(p[:, 2]):
        full = np.diag([1.0, -1.0, -1.0, 1.0]) @ full
    return full


GSPLAT_CONFIG = """absgrad: false
antialiased: false
batch_size: 1
data_dir: {data_dir}
data_factor: 4
disable_viewer: true
global_scale: 1.0
init_type: sfm
max_steps: 7000
normalize_world_space: {normalize}
random_bkgd: false
result_dir: {result_dir}
sh_degree: {sh_degree}
strategy: !!python/object:gsplat.strategy.default.DefaultStrategy
  absgrad: false
  grow_grad2d: 0.0002
  prune_opa: 0.005
  refine_every: 100
test_every: 8
"""


def write_gsplat(root: Path, scene: str, model: GaussianModel, *, data_dir: str, normalize: bool = True,
                 app_opt: bool = False) -> Path:
    """root/results/<scene>/ with cfg.yml and ckpts/ckpt_6999_rank0.pt (plus an earlier step,
    one splat, so loading the wrong one shows); `model` is in the trainer's frame."""
    folder = root / "results" / scene
    (folder / "ckpts").mkdir(parents=True, exist_ok=True)
    degree = math.isqrt(model.sh.shape[1]) - 1
    (folder / "cfg.yml").write_text(GSPLAT_CONFIG.format(data_dir=data_dir, normalize=str(normalize).lower(),
                                                         result_dir=f"results/{scene}", sh_degree=degree))
    for step, part in ((999, model.subset(torch.arange(model.num_splats) < 1)), (6999, model)):
        splats = {"means": part.means, "quats": part.quats, "scales": part.log_scales,
                  "opacities": part.opacity_logits, "sh0": part.sh[:, :1], "shN": part.sh[:, 1:]}
        if app_opt:
            splats["features"] = torch.zeros(part.num_splats, 32)
        torch.save({"step": step, "splats": splats}, folder / "ckpts" / f"ckpt_{step}_rank0.pt")
    return folder


def write_capture(root: Path, cameras: Sequence[Camera], points: np.ndarray) -> Path:
    """A COLMAP capture (binary, with SfM points) under root, images named out of capture order."""
    names = [f"IMG_{(7 * i) % len(cameras):04d}.png" for i in range(len(cameras))]
    write_colmap(root, cameras, binary=True, points=points, names=names)
    return root


# ----------------------------------------------------------------------------- whole scenes

def splatfacto_scene(root: Path, *, export_ply: bool = True, sh_coeffs: int = 1, background: str = "random",
                     applied: bool = True, count: int = 10) -> dict:
    """A capture in the user's frame (data/desk/transforms.json) and a splatfacto run on it.
    Returns the folder, the user-frame model (SH degree 0) or the dataparser-frame one (higher
    degrees: their colours are defined in that frame), the frame matrix and the training cameras."""
    cameras, names = scene_cameras(count), frame_names(count)
    write_transforms(root / "data" / "desk", cameras, names, applied=applied)
    t, scale = dataparser_transform(cameras)
    to_model = np.diag([scale, scale, scale, 1.0]) @ t                    # user frame -> dataparser frame
    user = scene_splats(300, seed=1)
    trained = move_model(user, to_model)
    if sh_coeffs > 1:
        g = torch.Generator().manual_seed(2)
        trained.sh = torch.cat([trained.sh, torch.randn(trained.num_splats, sh_coeffs - 1, 3, generator=g) * 0.4], 1)
    stored = t @ APPLIED_TRANSFORM if applied else t                      # from nerfstudio's "original" frame
    folder = write_splatfacto(root, "desk", trained, stored, scale, export_ply=export_ply, background=background)
    order = sorted(range(count), key=lambda i: names[i])
    chosen = np.linspace(0, count - 1, math.ceil(count * 0.9), dtype=int)    # eval_mode fraction, 0.9
    return {"folder": folder, "user_model": user if sh_coeffs == 1 else None, "trained": trained,
            "to_model": to_model, "cameras": cameras, "training": [cameras[order[k]] for k in chosen]}


def gsplat_scene(root: Path, *, upside_down_fix: bool = True, normalize: bool = True, shift: float = 0.0,
                 app_opt: bool = False) -> dict:
    """A COLMAP capture (data/garden) in the user's frame and a gsplat run on it (SH degree 0);
    `shift` moves the trained splats away from where the capture puts them (a mismatched model)."""
    cameras = scene_cameras(10)
    user = scene_splats(300, seed=3)
    points = user.means[:200].double().numpy()                            # the SfM points the splats grew from
    write_capture(root / "data" / "garden", cameras, points)
    names = [f"IMG_{(7 * i) % len(cameras):04d}.png" for i in range(len(cameras))]
    by_name = [cameras[i] for i in sorted(range(len(cameras)), key=lambda i: names[i])]
    to_model = gsplat_normalisation(by_name, points, upside_down_fix=upside_down_fix) if normalize else np.eye(4)
    trained = move_model(user, to_model)
    trained.means[:, 0] += shift
    folder = write_gsplat(root, "garden", trained, data_dir="data/garden", normalize=normalize, app_opt=app_opt)
    return {"folder": folder, "user_model": user, "trained": trained, "to_model": to_model, "points": points,
            "training": [c for i, c in enumerate(by_name) if i % 8]}


def cup_gsplat_run(root: Path, cup: Path, *, upside_down_fix: bool = True,
                   eigh_signs: Sequence[float] = (1.0, 1.0, 1.0), every: int = 3,
                   user_model: GaussianModel | None = None) -> dict:
    """A gsplat run on the real COLMAP capture `cup` as gsplat would have normalised it with
    `eigh_signs`: `user_model` (SH degree 0, in the capture's frame), else splats grown from
    every `every`-th SfM point (so the other points are not on a splat), coloured by the
    points and sized by their spacing."""
    from phd_core.data import load_colmap

    capture = load_colmap(cup, "all", with_images=False)
    points, colours = capture.points.numpy(), capture.point_colors
    user = user_model
    if user is None:
        grown = torch.from_numpy(points[::every]).float()                                  # [G, 3]
        spacing = torch.cdist(grown, grown).topk(4, largest=False).values[:, 1:].mean(1)   # [G]
        user = GaussianModel(means=grown, log_scales=(0.5 * spacing).clamp_min(1e-6).log()[:, None].repeat(1, 3),
                             quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(len(grown), 1),
                             opacity_logits=torch.full((len(grown),), 2.0),
                             sh=((colours[::every] - 0.5) / SH_C0)[:, None, :].float())
    to_model = gsplat_normalisation(capture.cameras, points, upside_down_fix=upside_down_fix, eigh_signs=eigh_signs)
    folder = write_gsplat(root, "cup", move_model(user, to_model), data_dir=str(cup))
    return {"folder": folder, "user_model": user, "to_model": to_model,
            "training": [c for i, c in enumerate(capture.cameras) if i % 8]}
