"""Reading files that other trainers wrote, without ever running their code.

- YAML configs dumped from Python objects (nerfstudio's config.yml, gsplat's cfg.yml) carry
  tags such as `!!python/object:nerfstudio...TrainerConfig` or
  `!!python/object/apply:pathlib.PosixPath [data, scene]`. `read_yaml` reads them with a
  safe loader that turns every such tag into plain data (mappings into dicts, argument lists
  into lists, names into strings): nothing is imported or called.
- Torch checkpoints are pickles. `read_checkpoint` loads them with `weights_only=True`, which
  accepts only tensors, numbers, strings and containers; a checkpoint that needs anything
  else (a class, a function) is refused, never unpickled.
"""

from __future__ import annotations

import pickle
import re
from pathlib import Path
from typing import Any

import torch
import yaml

from ..errors import InputError


class _PlainLoader(yaml.SafeLoader):
    """A SafeLoader that reads Python-tagged nodes as the plain data inside them."""


def _plain(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_PlainLoader.add_multi_constructor("tag:yaml.org,2002:python/", _plain)


def read_yaml(path: Path) -> Any:
    """A YAML file as plain data (dicts, lists, strings, numbers); Python tags are read as data."""
    try:
        return yaml.load(path.read_text(), Loader=_PlainLoader)   # noqa: S506 - a SafeLoader subclass
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path.name, f"cannot read {path}: {exc}") from None
    except yaml.YAMLError as exc:
        raise InputError(path.name, f"{path} is not valid YAML: {str(exc).splitlines()[0]}") from None


def yaml_path(value: Any) -> Path | None:
    """A path as YAML-dumped Python writes it: a string, or PosixPath's list of parts."""
    if isinstance(value, str) and value:
        return Path(value)
    if isinstance(value, list) and value and all(isinstance(part, str) for part in value):
        return Path(*value)
    return None


def read_checkpoint(path: Path) -> Any:
    """A torch checkpoint of plain tensors and containers (torch.load with weights_only=True)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's message also suggests weights_only=False; keep only what the file asked for.
        found = re.search(r"[^\n]*(unsupported|Unsupported) (GLOBAL|global|operand)[^\n]*", str(exc))
        reason = found.group(0).strip() if found else "it holds objects other than tensors, numbers and containers"
        raise InputError(path.name, f"{path} needs Python code to load, so it is refused (never unpickled): "
                                    f"{reason}") from None
    except (OSError, RuntimeError, EOFError, ValueError) as exc:
        raise InputError(path.name, f"cannot read torch checkpoint {path}: {str(exc).splitlines()[0]}") from None
