"""nerfstudio's splatfacto output folder, as `ns-train splatfacto` leaves it:

    outputs/<experiment>/splatfacto/<timestamp>/
      config.yml                           the TrainerConfig, YAML with Python tags (read as plain data)
      dataparser_transforms.json           {"transform": [3 x 4], "scale": s}
      nerfstudio_models/step-000029999.ckpt   torch checkpoint; the splats are in its pipeline state
      exports/splat/splat.ply              `ns-export gaussian-splat` (any .ply inside the folder)

The splats come from a PLY inside the folder when there is one (the newest), else from the
latest checkpoint, loaded with weights_only (tensors only: a checkpoint that needs code is
refused). Keys `*.gauss_params.{means, scales, quats, features_dc, features_rest,
opacities}` (older versions: `_model.means`, ...): log-scales, wxyz quaternions, opacity
logits, SH coefficients; with `sh_degree: 0` features_dc holds RGB logits instead.

Frames. splatfacto trains in its dataparser's frame. The nerfstudio dataparser sorts the
frames of transforms.json by file name, turns and centres them (transform T, 3x4) and scales
them (s): p_model = s (T [p; 1]), camera rotations R -> T[:, :3] R. dataparser_transforms.json
stores that map from the *original* data frame: when transforms.json carries an
`applied_transform` A (ns-process-data writes one; the dataparser assumes a default one when
the data folder has colmap/sparse/0) the stored T is T_orient A and the stored scale includes
`applied_scale`. The user's frame is transforms.json's, so user -> model is the stored
similarity after A^-1, divided by applied_scale. The splats are moved into the user's frame on
loading (`GaussianModel.transformed`), so cameras given and returned are the user's.

Training cameras: transforms.json from config.yml's data path (absolute, or relative to the
working directory or to any folder above the output folder), split as the dataparser splits it
(`eval_mode` fraction (default, train_split_fraction 0.9), interval, filename, all; or the
file's own `train_filenames`). Background: `background_color` white, black or three numbers in
[0, 1]; "random" (splatfacto's default) renders over (0.149, 0.1647, 0.2157), what splatfacto
evaluates over. config.yml's fields are checked by `phd_core.io.configs.SplatfactoConfig`.
Without transforms.json the model loads in the frame dataparser_transforms.json maps from, and
`frame_without_data` tells from the stored rotation whether that is the COLMAP model's (an
applied_transform is folded in) or transforms.json's, which the pose format then names.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import torch

from ...data.frames import read_transforms
from ...data.nerfstudio import load_nerfstudio
from ...errors import InputError, check_float
from ...io.configs import Dataparser, SplatfactoConfig, parse_config
from ...io.foreign import read_checkpoint, read_json, read_yaml
from ...scene import Camera, Similarity
from ..gs3d import GaussianModel, read_ply
from ..splats.maths import SH_C0
from .base import OUTPUTS, OutputFormat, TrainerOutput, data_candidates, sh_from_parts

FRAME_FILE = "dataparser_transforms.json"
GAUSS_PARAMS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
# The applied_transform the dataparser assumes for data with colmap/sparse/0 and no such key.
COLMAP_APPLIED_TRANSFORM = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]
# The one ns-process-data writes for COLMAP data (1.1.5: y and z swapped, then the new z negated).
ORIENTATION_MARGIN = math.radians(30)   # a reading of the stored turn wins by this much (frame_without_data)
PROCESS_DATA_APPLIED_TRANSFORM = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]]


def detect(path: Path) -> bool:
    return path.is_dir() and (path / "config.yml").is_file() and (path / FRAME_FILE).is_file()


def read(folder: Path, within: Path | None = None) -> TrainerOutput:
    config = parse_config(SplatfactoConfig, read_yaml(folder / "config.yml"), "config.yml")
    stored = read_frame(folder / FRAME_FILE)                      # nerfstudio's original data frame -> model frame
    model, source = read_splats(folder, config.pipeline.model.sh_degree)
    cameras, frame, camera_format, notes, capture, splits = training_cameras(folder, config, stored, within)
    notes.insert(0, f"nerfstudio {config.method_name}: splats from {source.relative_to(folder)}, moved from the "
                    f"dataparser's frame (the user's scaled by {frame.scale:.6g}, turned and centred) into the user's")
    return TrainerOutput(model.transformed(frame.inverse()), cameras, config.pipeline.model.background_color, source,
                         frame=frame, notes=notes, camera_format=camera_format, capture=capture, splits=splits,
                         name=run_name(folder, config))


def run_name(folder: Path, config: SplatfactoConfig) -> str:
    """"<experiment>/<method>" from config.yml (the folder is only the run's timestamp); without an
    experiment_name, the folder two levels up (outputs/<experiment>/<method>/<timestamp>)."""
    return f"{config.experiment_name or folder.resolve().parent.parent.name}/{config.method_name}"


def read_frame(path: Path) -> Similarity:
    """dataparser_transforms.json as the similarity p -> scale * (transform @ [p; 1])."""
    data = read_json(path)
    if not isinstance(data, dict) or "transform" not in data or "scale" not in data:
        raise InputError(path.name, "must be an object with 'transform' (3x4) and 'scale'")
    scale = check_float(data["scale"], f"{path.name}.scale", 0, open_min=True)
    transform = Similarity.from_matrix(data["transform"], f"{path.name}.transform")
    return transform.then(Similarity.make(scale, torch.eye(3), torch.zeros(3)))


# ----------------------------------------------------------------------------- splats

def read_splats(folder: Path, sh_degree: int) -> tuple[GaussianModel, Path]:
    """(model in the trainer's frame, the file it came from)."""
    plys = [p for p in folder.rglob("*.ply") if p.is_file()]
    if plys:
        ply = max(plys, key=lambda p: (p.stat().st_mtime, str(p)))
        return read_ply(ply), ply
    steps = {int(m.group(1)): p for p in (folder / "nerfstudio_models").glob("step-*.ckpt")
             if (m := re.fullmatch(r"step-(\d+)\.ckpt", p.name))}
    if not steps:
        raise InputError("model", f"{folder} has neither an exported .ply (ns-export gaussian-splat) nor "
                                  "nerfstudio_models/step-*.ckpt")
    path = steps[max(steps)]
    return checkpoint_model(path, sh_degree), path


def checkpoint_model(path: Path, sh_degree: int) -> GaussianModel:
    """The splats of a splatfacto checkpoint's pipeline state."""
    data = read_checkpoint(path)
    state = data.get("pipeline") if isinstance(data, dict) else None
    if not isinstance(state, dict):
        raise InputError(f"{path.name}.pipeline", "missing: a nerfstudio checkpoint is a dict whose 'pipeline' "
                                                  "holds the model's state")
    found = {}
    for name in GAUSS_PARAMS:
        keys = [k for k in state if k.endswith(f"gauss_params.{name}")] or [k for k in state if k == f"_model.{name}"]
        if len(keys) != 1:
            raise InputError(f"{path.name}.pipeline", f"needs one '*gauss_params.{name}' tensor (splatfacto's state), "
                                                      f"found {len(keys)}")
        value = state[keys[0]]
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            raise InputError(f"{path.name}.pipeline.{keys[0]}", "must be a floating-point tensor")
        found[name] = value.detach().float()
    dc, rest = found["features_dc"], found["features_rest"]           # [G, 3], [G, K-1, 3]
    if sh_degree == 0:                                                # colours are RGB logits, not SH
        dc = (torch.sigmoid(dc) - 0.5) / SH_C0
    opacities = found["opacities"]
    model = GaussianModel(found["means"], found["scales"], found["quats"],
                          opacities[:, 0] if opacities.dim() == 2 and opacities.shape[1:] == (1,) else opacities,
                          sh_from_parts(dc, rest, f"{path.name}.pipeline.features_rest"))
    try:
        model.validate()
    except InputError as exc:
        raise InputError(f"{path.name}.pipeline.{exc.field}", exc.reason) from None
    return model


# ----------------------------------------------------------------------------- cameras and frame

def training_cameras(folder: Path, config: SplatfactoConfig, stored: Similarity, within: Path | None = None
                     ) -> tuple[list[Camera], Similarity, str | None, list[str], Path | None, dict[str, list[int]]]:
    """(training cameras in transforms.json's frame, user frame -> model frame, the pose
    convention of that frame, notes, transforms.json when found, the run's train/test frames as
    indices into it)."""
    parser = config.pipeline.datamanager.dataparser
    data = parser.data or config.data
    json_path = _find_transforms(folder, data, within)
    if json_path is None:
        camera_format, frame_name = frame_without_data(stored, parser)
        return [], stored, camera_format, [
            f"no transforms.json found for config.yml's data path {data} (looked from the working directory and "
            f"every folder above {folder}): the model has no training cameras, and poses are in the frame "
            f"{FRAME_FILE} maps from: {frame_name}"], None, {}
    frames, meta = read_transforms(json_path)
    applied = meta.get("applied_transform")
    if applied is None and (json_path.parent / "colmap" / "sparse" / "0").is_dir():
        applied = COLMAP_APPLIED_TRANSFORM
    frame = stored
    if applied is not None:
        frame = Similarity.from_matrix(applied, f"{json_path.name}.applied_transform").inverse().then(frame)
    applied_scale = check_float(meta.get("applied_scale", 1.0), f"{json_path.name}.applied_scale", 0, open_min=True)
    frame = frame.then(Similarity.make(1.0 / applied_scale, torch.eye(3), torch.zeros(3)))
    views = train_frames(frames, meta, parser)
    cameras = load_nerfstudio(json_path, views=views, with_images=False).cameras
    notes = [f"training cameras: {len(cameras)} of the {len(frames)} frames of {json_path}"]
    held_out = sorted(set(range(len(frames))) - set(views))
    return cameras, frame, "nerfstudio", notes, json_path, {"train": views, "test": held_out}


def frame_without_data(stored: Similarity, parser: Dataparser) -> tuple[str | None, str]:
    """(pose convention, description) of the frame dataparser_transforms.json maps from, told
    without transforms.json. The stored rotation is nerfstudio's orientation times the data's
    applied_transform (if any). Orientation "up" (the default) is the shortest turn of the
    cameras' mean up onto +z: its axis is horizontal (R[1, 0] = R[0, 1]), and it is a small turn
    for data that is nearly upright already, as ns-process-data makes COLMAP's. So the reading
    (no applied_transform, ns-process-data's, the older COLMAP one) whose orientation is such a
    turn, and the smallest by ORIENTATION_MARGIN, wins: with an applied_transform the frame is
    the COLMAP model's (poses go back in COLMAP's convention), without one transforms.json's."""
    readings = {}
    for name, applied in (("none", None), ("ns-process-data", PROCESS_DATA_APPLIED_TRANSFORM),
                          ("older COLMAP data", COLMAP_APPLIED_TRANSFORM)):
        rotation = stored.rotation
        if applied is not None:
            rotation = rotation @ torch.tensor(applied, dtype=torch.float64)[:, :3].T
        if abs(float(rotation[1, 0] - rotation[0, 1])) < 1e-6:           # a turn about a horizontal axis
            readings[name] = math.acos(max(-1.0, min(1.0, (float(torch.trace(rotation)) - 1) / 2)))
    ranked = sorted(readings, key=readings.__getitem__)
    unclear = ("transforms.json's, or the COLMAP model's when the data came from ns-process-data (" + "{}" + ")")
    if parser.orientation_method != "up":
        return None, unclear.format("orientation_method is not 'up', so which cannot be told")
    if not ranked or (len(ranked) > 1 and readings[ranked[1]] - readings[ranked[0]] < ORIENTATION_MARGIN):
        return None, unclear.format("the stored transform fits both")
    if ranked[0] == "none":
        return "nerfstudio", "transforms.json's (its poses had no applied_transform)"
    return "colmap", (f"the COLMAP model's the data was made from (the stored transform includes {ranked[0]}'s "
                      "applied_transform); poses are given back in COLMAP's convention")


def train_frames(frames: list, meta: dict, parser: Dataparser) -> list[int]:
    """Indices (into `frames`) of the training frames, as the nerfstudio dataparser splits them:
    frames sorted by file name, then `train_filenames` or the config's eval_mode."""
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(f"frames[{i}].file_path", "missing or not a string")
    order = sorted(range(len(frames)), key=lambda i: Path(frames[i]["file_path"]))
    names = [Path(frames[i]["file_path"]) for i in order]
    count = len(order)
    if isinstance(meta.get("train_filenames"), list):
        wanted = {Path(name) for name in meta["train_filenames"] if isinstance(name, str)}
        chosen = [k for k, name in enumerate(names) if name in wanted]
    elif parser.eval_mode == "fraction":
        chosen = np.linspace(0, count - 1, math.ceil(count * parser.train_split_fraction), dtype=int).tolist()
    elif parser.eval_mode == "interval":
        chosen = [k for k in range(count) if k % parser.eval_interval]
    elif parser.eval_mode == "filename":
        chosen = [k for k, name in enumerate(names) if "train" in name.name]
    else:                                                                   # "all"
        chosen = list(range(count))
    if not chosen:
        raise InputError("transforms.json", "the dataparser's split leaves no training frame")
    return [order[k] for k in chosen]


def _find_transforms(folder: Path, data: Path | None, within: Path | None) -> Path | None:
    for candidate in [] if data is None else data_candidates(folder, data, within):
        json_path = candidate if candidate.suffix == ".json" else candidate / "transforms.json"
        if json_path.is_file():
            return json_path
    return None


OUTPUTS.register(OutputFormat("nerfstudio", f"a nerfstudio splatfacto output folder (config.yml + {FRAME_FILE})",
                              detect, read, order=20))
