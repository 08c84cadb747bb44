"""Reading files that other trainers wrote, without ever running their code, within bounds.

- Config and camera files (JSON, YAML) are read only up to a size (MAX_JSON_BYTES,
  MAX_CONFIG_BYTES) and a nesting depth (MAX_NESTING): past either an InputError names the file
  and the limit, never a RecursionError or a parse that takes the machine's memory.
- YAML configs dumped from Python objects (nerfstudio's config.yml, gsplat's cfg.yml) carry
  tags such as `!!python/object:nerfstudio...TrainerConfig` or
  `!!python/object/apply:pathlib.PosixPath [data, scene]`. `read_yaml` reads them with a
  safe loader that turns every such tag into plain data (mappings into dicts, argument lists
  into lists, names into strings): nothing is imported or called. Aliases are counted as what
  they expand to: a document is at most MAX_YAML_NODES nodes with every alias expanded (an
  alias tree of 10^7 leaves fits in 18 KB of YAML), and an alias inside its own anchor is refused.
- Torch checkpoints are pickles inside a zip. `read_checkpoint` checks the zip by the rules
  every uploaded archive keeps (`phd_core.io.archives`), allows the pickle to name only the
  functions torch.save uses for tensors and containers, loads it with `weights_only=True`
  (tensors, numbers, strings and containers; a checkpoint that needs anything else is refused,
  never unpickled), and refuses tensors that claim more elements than the records store (a view
  repeating one number 20 M times is a few bytes on disk). So what loading allocates is what
  `checkpoint_bytes` says before it: the records' declared sizes.
"""

from __future__ import annotations

import json
import pickle
import pickletools
import re
from pathlib import Path
from typing import Any

import torch
import yaml

from ..errors import InputError, TooLarge
from .archives import DAMAGED, ZipRules, open_zip

MAX_JSON_BYTES = 16 << 20       # a camera or config JSON file (the service's camera part has the same default cap)
MAX_CONFIG_BYTES = 1 << 20      # a YAML config or cfg_args (a trainer's is a few KB; YAML's pure-Python parser is slow)
MAX_NESTING = 100               # arrays, objects, sequences and mappings nested at most this deep
MAX_YAML_NODES = 100_000        # a YAML document's nodes with every alias expanded
CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt")
CHECKPOINT_RULES = ZipRules(max_entries=100_000)       # records: a checkpoint's tensors, its pickle and torch's notes
# What torch.save's pickle names for tensors, parameters and containers (bytes: _codecs.encode).
# torch's weights_only loader allows more, some of which allocate what the pickle asks for
# (bytearray(n), a storage type called with a size, a quantized tensor's empty storage).
CHECKPOINT_GLOBALS = {"collections OrderedDict", "torch._utils _rebuild_tensor_v2", "torch._utils _rebuild_parameter",
                      "torch._utils _rebuild_parameter_with_state", "_codecs encode"}
STORAGE_GLOBAL = re.compile(r"torch (BFloat16|Half|Float|Double|Long|Int|Short|Char|Byte|Bool|ComplexFloat|"
                            r"ComplexDouble)Storage")


def read_text(path: Path, limit: int) -> str:
    """A UTF-8 text file of at most `limit` bytes (TooLarge past it)."""
    try:
        with open(path, "rb") as file:
            data = file.read(limit + 1)
        if len(data) > limit:
            raise TooLarge(path.name, f"{path} is larger than the {limit} bytes read of such a file")
        return data.decode()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path.name, f"cannot read {path}: {exc}") from None


def read_json(path: Path) -> Any:
    """A JSON file of at most MAX_JSON_BYTES, nested at most MAX_NESTING deep."""
    try:
        value = json.loads(read_text(path, MAX_JSON_BYTES))
    except json.JSONDecodeError as exc:
        raise InputError(path.name, f"cannot parse {path}: {exc}") from None
    except RecursionError:
        raise InputError(path.name, f"{path} nests arrays or objects deeper than {MAX_NESTING} levels") from None
    _check_nesting(value, path)
    return value


def _check_nesting(value: Any, path: Path) -> None:
    levels = [(value, 1)]
    while levels:
        item, depth = levels.pop()
        if isinstance(item, (dict, list)):
            if depth > MAX_NESTING:
                raise InputError(path.name, f"{path} nests arrays or objects deeper than {MAX_NESTING} levels")
            levels += [(child, depth + 1) for child in (item.values() if isinstance(item, dict) else item)]


class _Unbounded(yaml.YAMLError):
    """A YAML document past MAX_NESTING or MAX_YAML_NODES."""


class _PlainLoader(yaml.SafeLoader):
    """A SafeLoader that reads Python-tagged nodes as the plain data inside them, within
    MAX_NESTING levels and MAX_YAML_NODES nodes with every alias expanded."""

    def __init__(self, stream: str):
        super().__init__(stream)
        self.depth = 0
        self.expanded: dict[int, int] = {}      # id(node) -> its node count, every alias in it expanded

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        alias = self.check_event(yaml.AliasEvent)
        self.depth += 1
        if self.depth > MAX_NESTING:
            raise _Unbounded(f"it nests deeper than {MAX_NESTING} levels")
        node = super().compose_node(parent, index)
        self.depth -= 1
        if alias:                               # the anchored node itself, counted again where it is used
            if id(node) not in self.expanded:
                raise _Unbounded("an alias refers to a node that contains it")
            size = self.expanded[id(node)]
        elif isinstance(node, yaml.MappingNode):
            size = 1 + sum(self.expanded[id(key)] + self.expanded[id(value)] for key, value in node.value)
        elif isinstance(node, yaml.SequenceNode):
            size = 1 + sum(self.expanded[id(item)] for item in node.value)
        else:
            size = 1
        if size > MAX_YAML_NODES:
            raise _Unbounded(f"its aliases expand it past {MAX_YAML_NODES} nodes")
        self.expanded[id(node)] = size
        return node


def _plain(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_PlainLoader.add_multi_constructor("tag:yaml.org,2002:python/", _plain)


def read_yaml(path: Path) -> Any:
    """A YAML file of at most MAX_CONFIG_BYTES as plain data (dicts, lists, strings, numbers);
    Python tags are read as data."""
    text = read_text(path, MAX_CONFIG_BYTES)
    try:
        return yaml.load(text, Loader=_PlainLoader)   # noqa: S506 - a SafeLoader subclass
    except _Unbounded as exc:
        raise InputError(path.name, f"{path} is refused: {exc}") from None
    except yaml.YAMLError as exc:
        raise InputError(path.name, f"{path} is not valid YAML: {str(exc).splitlines()[0]}") from None


def checkpoint_bytes(path: Path) -> int:
    """What loading the torch checkpoint at `path` allocates (its records' declared sizes),
    once its zip keeps CHECKPOINT_RULES and its pickle names only CHECKPOINT_GLOBALS."""
    with open_zip(path, CHECKPOINT_RULES, path.name) as zipped:
        members = zipped.infolist()
        pickles = [m for m in members if m.filename.count("/") == 1 and m.filename.endswith("/data.pkl")]
        if len(pickles) != 1:
            raise InputError(path.name, f"{path} is not a torch checkpoint: a zip written by torch.save holds one "
                                        f"<name>/data.pkl, this one {len(pickles)}")
        try:
            named = {str(arg) for op, arg, _ in pickletools.genops(zipped.read(pickles[0])) if op.name == "GLOBAL"}
        except (ValueError, *DAMAGED) as exc:
            raise InputError(path.name, f"cannot read torch checkpoint {path}: {exc}") from None
    refused = sorted(g for g in named if g not in CHECKPOINT_GLOBALS and not STORAGE_GLOBAL.fullmatch(g))
    if refused:
        raise InputError(path.name, f"{path} needs Python code to load, so it is refused (never unpickled): its "
                                    f"pickle names {refused[0].replace(' ', '.')}, which a checkpoint of tensors and "
                                    "containers does not need")
    return sum(member.file_size for member in members)


def read_checkpoint(path: Path) -> Any:
    """A torch checkpoint of plain tensors and containers (torch.load with weights_only=True),
    allocating no more than `checkpoint_bytes(path)`."""
    stored = checkpoint_bytes(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's message also suggests weights_only=False; keep only what the file asked for.
        found = re.search(r"[^\n]*(unsupported|Unsupported) (GLOBAL|global|operand)[^\n]*", str(exc))
        reason = found.group(0).strip() if found else "it holds objects other than tensors, numbers and containers"
        raise InputError(path.name, f"{path} needs Python code to load, so it is refused (never unpickled): "
                                    f"{reason}") from None
    except (OSError, RuntimeError, EOFError, ValueError) as exc:
        raise InputError(path.name, f"cannot read torch checkpoint {path}: {str(exc).splitlines()[0]}") from None
    claimed = _claimed_bytes(data, path)
    if claimed > stored:
        raise InputError(path.name, f"{path} is refused: its tensors claim {claimed} bytes, more than the {stored} "
                                    "its records store (views that repeat elements)")
    return data


def _claimed_bytes(data: Any, path: Path) -> int:
    """The bytes of the distinct tensor views in `data`, or of their distinct storages when
    more (each container walked once: a pickle may share one many times); an InputError for a
    tensor that is not a plain strided one."""
    views: dict[tuple, int] = {}
    storages: dict[int, int] = {}
    seen: set[int] = set()
    pending = [data]
    while pending:
        item = pending.pop()
        if isinstance(item, torch.Tensor):
            if item.layout != torch.strided:
                raise InputError(path.name, f"{path} holds a {item.layout} tensor: only dense tensors are read")
            storage = item.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
            key = (storage.data_ptr(), item.storage_offset(), tuple(item.shape), item.stride(), item.dtype)
            views[key] = item.numel() * item.element_size()
        elif isinstance(item, (dict, list, tuple, set, frozenset)) and id(item) not in seen:
            seen.add(id(item))
            pending += [*item.keys(), *item.values()] if isinstance(item, dict) else list(item)
    return max(sum(views.values()), sum(storages.values()))
