"""The parts of trainers' config files that the readers use, as typed schemas (pydantic).

Every field a reader uses is checked for its kind and range when the file is read, so a wrong
value is an InputError naming the file and the field (`config.yml.pipeline.datamanager.
dataparser.train_split_fraction: ...`), never an exception further on. Fields not listed are
ignored; missing ones take the trainer's default. Paths are at most MAX_PATH_BYTES, names 255
bytes, with no NUL (the system would refuse them with errors of its own), and text that reaches
a model's name or notes is cut to NAME_CHARS.

    SplatfactoConfig  nerfstudio's config.yml (a TrainerConfig dumped as YAML)
    GsplatConfig      gsplat simple_trainer's cfg.yml
    InriaArgs         the reference 3DGS trainer's cfg_args (a Namespace's repr, its values as text)
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, ValidationError

from ..errors import InputError, cut, shown

MAX_PATH_BYTES = 1024       # a data path a config names
NAME_CHARS = 100            # an experiment's or method's name as a model's name and notes quote it
# splatfacto's backgrounds; "random" renders over what splatfacto evaluates over.
SPLATFACTO_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "random": (0.1490, 0.1647, 0.2157)}


def _path(value: Any) -> Path | None:
    """A path as YAML-dumped Python writes it (a string, or PosixPath's list of parts); "" is none."""
    parts = [value] if isinstance(value, str) else value
    if value is None or value == "":
        return None
    if not (isinstance(parts, list) and parts and all(isinstance(part, str) for part in parts)):
        raise ValueError("must be a path: a string or a list of its parts")
    path = Path(*parts)
    if "\0" in str(path) or len(str(path).encode()) > MAX_PATH_BYTES or any(len(p.encode()) > 255 for p in path.parts):
        raise ValueError(f"must be a path of at most {MAX_PATH_BYTES} bytes (255 a name) without NUL characters")
    return path


def _splatfacto(method: str) -> str:
    if not method.startswith("splatfacto"):
        raise ValueError("is not splatfacto: only nerfstudio's Gaussian splatting outputs are read (a NeRF such as "
                         "nerfacto is not)")
    return cut(method, NAME_CHARS)


def _background(value: Any) -> tuple[float, float, float]:
    if isinstance(value, str) and value in SPLATFACTO_BACKGROUNDS:
        return SPLATFACTO_BACKGROUNDS[value]
    if (isinstance(value, list) and len(value) == 3
            and all(not isinstance(c, bool) and isinstance(c, (int, float)) and 0 <= c <= 1 for c in value)):
        return float(value[0]), float(value[1]), float(value[2])
    raise ValueError(f"must be {', '.join(SPLATFACTO_BACKGROUNDS)} or three numbers in [0, 1]")


def _flag(value: Any) -> bool:
    if value not in ("True", "False"):
        raise ValueError("must be True or False")
    return value == "True"


ConfigPath = Annotated[Path | None, BeforeValidator(_path)]
Name = Annotated[str, Field(strict=True), AfterValidator(lambda text: cut(text, NAME_CHARS))]
Count = Annotated[int, Field(gt=0, strict=True)]


class _Section(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True)


class Dataparser(_Section):
    data: ConfigPath = None
    eval_mode: Literal["fraction", "interval", "filename", "all"] = "fraction"
    train_split_fraction: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False, strict=True)] = 0.9
    eval_interval: Count = 8
    orientation_method: Annotated[str, Field(strict=True)] = "up"


class Datamanager(_Section):
    dataparser: Dataparser = Dataparser()


class SplatfactoModel(_Section):
    sh_degree: Annotated[int, Field(ge=0, le=3, strict=True)] = 3
    background_color: Annotated[tuple[float, float, float], BeforeValidator(_background)] = \
        SPLATFACTO_BACKGROUNDS["random"]


class Pipeline(_Section):
    datamanager: Datamanager = Datamanager()
    model: SplatfactoModel = SplatfactoModel()


class SplatfactoConfig(_Section):
    """config.yml: the method, the run's name, where the data was and how the dataparser split it."""

    method_name: Annotated[str, Field(strict=True), AfterValidator(_splatfacto)]
    experiment_name: Name | None = None
    data: ConfigPath = None
    pipeline: Pipeline = Pipeline()


class GsplatConfig(_Section):
    """cfg.yml: the COLMAP capture, whether the world was normalised, the held-out interval."""

    data_type: Literal["colmap"] = "colmap"
    data_dir: ConfigPath = None
    normalize_world_space: StrictBool = True
    test_every: Count = 8


class InriaArgs(_Section):
    """cfg_args: the capture it trained on, the held-out split (--eval) and the background."""

    source_path: Annotated[Path | None, BeforeValidator(lambda text: _path(text.strip("'\"")))] = None
    eval: Annotated[bool, BeforeValidator(_flag)] = False
    white_background: Annotated[bool, BeforeValidator(_flag)] = False


Schema = TypeVar("Schema", bound=BaseModel)


def parse_config(schema: type[Schema], data: Any, file: str) -> Schema:
    """`data` (a parsed config) as `schema`; the first problem an InputError naming `file` and the field."""
    try:
        return schema.model_validate(data)
    except ValidationError as exc:
        error = exc.errors()[0]
        where = ".".join(str(part) for part in (file, *error["loc"]))
        if error["type"] == "missing":
            raise InputError(where, "missing") from None
        if not error["loc"]:
            raise InputError(where, f"must be a mapping of the trainer's settings, got {shown(data)}") from None
        reason = error["msg"].removeprefix("Value error, ")
        raise InputError(where, f"{reason}, got {shown(error['input'])}") from None
