"""The splat PLY format (the standard Inria 3DGS one, which the 2DGS reference trainer uses
with two scale columns), and the sidecar JSON `phd train` writes beside a splat model.

The PLY file holds one float32 record per `GaussianModel` splat with the properties

    x y z nx ny nz f_dc_0..2 f_rest_0..f_rest_{3(K-1)-1} opacity scale_0..2 rot_0..3

where f_rest is channel-major: f_rest index = c * (K - 1) + (k - 1) for colour channel c
and SH coefficient k >= 1. The reader looks properties up by name and skips anything else
(normals, `filter_3D`, colours, other elements), because the trainer's forks differ in
exactly those details. Every malformed file raises `InputError` naming the PLY field.

The 2DGS reference trainer writes the same layout with two scale columns (scale_0,
scale_1); `scale_axes` tells the two apart from the header alone, and the readers and the
writer take the model class (`GaussianModel` or a subclass with `scale_axes = 2`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from ...errors import InputError
from ...io import write_bytes_atomic
from .model import SH_COEFFS, GaussianModel

_REST_COUNTS = {3 * (k - 1): k for k in SH_COEFFS}  # f_rest count -> K: 0, 9, 24, 45

# PLY scalar type names (and their sized aliases) -> numpy type codes, without byte order.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
ASCII_BLOCK_BYTES = 1 << 22   # ASCII body parsed this many bytes of lines at a time
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def is_ply(head: bytes) -> bool:
    """True if `head` (the first bytes of a file) starts like a PLY file."""
    return head.startswith(b"ply\n") or head.startswith(b"ply\r\n")


def scale_axes(head: bytes) -> int | None:
    """The number of scale_<i> properties of the vertex element declared in `head` (the first
    bytes of a PLY), or None when `head` holds no complete PLY header."""
    if not is_ply(head):
        return None
    element, count = None, 0
    for line in head.split(b"\n")[1:]:
        words = line.split()
        if words[:1] == [b"end_header"]:
            return count
        if words[:1] == [b"element"] and len(words) > 1:
            element = words[1]
        elif words[:1] == [b"property"] and element == b"vertex" and words[-1].startswith(b"scale_"):
            count += 1
    return None


def property_names(num_coeffs: int, axes: int = 3) -> list[str]:
    """The per-splat float properties of a standard 3DGS PLY with K = num_coeffs (or a 2DGS
    one with axes = 2 scale columns), in order."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * (num_coeffs - 1))]
            + ["opacity", *(f"scale_{i}" for i in range(axes)), "rot_0", "rot_1", "rot_2", "rot_3"])


# ----------------------------------------------------------------------------- reading

@dataclass
class _Element:
    """One `element` of a PLY header: its name, record count and (name, type) properties.
    A list property has type ("list", count_type, item_type)."""

    name: str
    count: int
    properties: list[tuple[str, str | tuple[str, str, str]]]

    def fixed_dtype(self, order: str) -> np.dtype | None:
        """The numpy record type of one binary record, or None if a list makes it variable."""
        if any(isinstance(kind, tuple) for _, kind in self.properties):
            return None
        return np.dtype([(name, order + _PLY_TYPES[cast(str, kind)]) for name, kind in self.properties])


def _parse_header(data: bytes) -> tuple[str, list[_Element], int]:
    """Parse the header: returns (format, elements, offset of the first body byte)."""
    if not is_ply(data[:5]):
        raise InputError("ply.header", "not a PLY file: it must start with a line 'ply'")
    fmt = None
    elements: list[_Element] = []
    pos, line_no = 0, 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise InputError("ply.header", "the header has no 'end_header' line")
        line_no += 1
        try:
            words = data[pos:end].decode("ascii").split()
        except UnicodeDecodeError:
            raise InputError("ply.header", f"line {line_no} is not ASCII text; the header has "
                                           "no 'end_header' line before binary data") from None
        pos = end + 1
        if line_no == 1 or not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "end_header":
            break
        if keyword == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise InputError("ply.header", f"line {line_no}: unsupported format "
                                               f"'{' '.join(words[1:])}', expected ascii or binary")
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3:
                raise InputError("ply.header", f"line {line_no}: expected 'element <name> <count>'")
            name, count = words[1], words[2]
            if not (count.isascii() and count.isdigit()):
                raise InputError(f"ply.{name}", f"element count must be a non-negative integer, got '{count}'")
            elements.append(_Element(name, int(count), []))
        elif keyword == "property":
            if not elements:
                raise InputError("ply.header", f"line {line_no}: property before any element")
            if len(words) == 5 and words[1] == "list":
                kind: str | tuple[str, str, str] = ("list", words[2], words[3])
                types = words[2:4]
            elif len(words) == 3:
                kind = words[1]
                types = [kind]
            else:
                raise InputError("ply.header", f"line {line_no}: expected 'property <type> <name>'")
            unknown = [t for t in types if t not in _PLY_TYPES]
            if unknown:
                raise InputError("ply.header", f"line {line_no}: unknown property type '{unknown[0]}'")
            name = words[-1]
            if any(name == existing for existing, _ in elements[-1].properties):
                raise InputError(f"ply.{name}", f"property appears twice in element '{elements[-1].name}'")
            elements[-1].properties.append((name, kind))
        else:
            raise InputError("ply.header", f"line {line_no}: unknown keyword '{keyword}'")
    if fmt is None:
        raise InputError("ply.header", "no 'format' line")
    return fmt, elements, pos


def _vertex_columns(data: bytes) -> tuple[dict[str, np.ndarray], int]:
    """Locate the vertex element and return ({property name: [G] column}, G)."""
    fmt, elements, offset = _parse_header(data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError("ply.vertex", "the file has no 'element vertex'")
    before, vertex = elements[:names.index("vertex")], elements[names.index("vertex")]
    lists = [name for name, kind in vertex.properties if isinstance(kind, tuple)]
    if lists:
        raise InputError(f"ply.{lists[0]}", "vertex list properties are not part of a 3DGS PLY")
    count = vertex.count

    if fmt == "ascii":
        values = _ascii_records(data, offset, sum(e.count for e in before), count, len(vertex.properties))
        return {name: values[:, j] for j, (name, _) in enumerate(vertex.properties)}, count

    order = _FORMATS[fmt]
    assert order is not None  # every format but ascii (returned above) has a byte order
    for element in before:
        dtype = element.fixed_dtype(order)
        if dtype is None:
            raise InputError("ply.header", f"element '{element.name}' precedes vertex and has a list "
                                           "property, so the vertex data cannot be located")
        offset += element.count * dtype.itemsize
    dtype = vertex.fixed_dtype(order)
    assert dtype is not None  # list properties were rejected above
    available = len(data) - offset
    if available < count * dtype.itemsize:
        raise InputError("ply.vertex", f"truncated: the header declares {count} vertices of "
                                       f"{dtype.itemsize} bytes ({count * dtype.itemsize} bytes), "
                                       f"only {max(0, available)} bytes follow")
    records = np.frombuffer(data, dtype, count=count, offset=offset)  # [G] structured
    return {name: records[name] for name, _ in vertex.properties}, count


def _ascii_records(data: bytes, offset: int, skip: int, count: int, width: int) -> np.ndarray:
    """The ASCII vertex records: [count, width] float64, one record per line after `skip` lines.

    Parsed ASCII_BLOCK_BYTES of lines at a time into a preallocated array, so the temporaries
    (line and word objects, about 50 bytes per value) never exceed one block: peak memory is
    the file plus 8 bytes per value, instead of about 12x the file for the whole body at once.
    """
    pos = offset
    for _ in range(skip):                                # the records of elements before vertex
        end = data.find(b"\n", pos)
        pos = len(data) if end < 0 else end + 1
    if count * 2 * width > len(data) - pos + 1:          # every value takes >= 2 bytes ("0 ")
        raise InputError("ply.vertex", f"truncated: the header declares {count} vertices of {width} values, "
                                       f"more than the {max(0, len(data) - pos)} bytes of the body can hold")
    values = np.empty((count, width), dtype=np.float64)  # [G, P]
    row = 0
    while row < count:
        if pos >= len(data):
            raise InputError("ply.vertex", f"truncated: the header declares {count} vertices, the body holds {row}")
        end = data.find(b"\n", min(pos + ASCII_BLOCK_BYTES, len(data) - 1))
        end = len(data) if end < 0 else end + 1
        lines = data[pos:end].splitlines()[:count - row]
        pos = end
        words = []
        for i, line in enumerate(lines):
            fields = line.split()
            if len(fields) != width:
                raise InputError("ply.vertex", f"vertex {row + i} has {len(fields)} values, the header declares "
                                               f"{width}")
            words += fields
        try:
            values[row:row + len(lines)] = np.array(words, dtype=np.float64).reshape(len(lines), width)
        except ValueError as exc:
            raise InputError("ply.vertex", f"the ASCII body holds a value that is not a number ({exc})") from None
        row += len(lines)
    return values


def parse_ply(data: bytes, name: str = "model", model_type: type[GaussianModel] = GaussianModel) -> GaussianModel:
    """Read a 3DGS PLY held in memory (an upload), or a 2DGS one with model_type a 2DGS model;
    `name` only labels error messages."""
    try:
        return _model_from_columns(*_vertex_columns(data), model_type)
    except InputError as exc:
        raise InputError(exc.field, f"{exc.reason} (in {name})") from None


def _model_from_columns(columns: dict[str, np.ndarray], count: int,
                        model_type: type[GaussianModel] = GaussianModel) -> GaussianModel:
    """Gather the used properties by name into a float32 model, checking every value."""
    axes = model_type.scale_axes
    if f"scale_{axes}" in columns:
        raise InputError(f"ply.scale_{axes}", f"this model kind has {axes} scale columns, the file has more "
                                               "(2DGS PLYs have scale_0, scale_1; 3DGS ones add scale_2)")
    n_rest = sum(name.startswith("f_rest_") for name in columns)
    if n_rest not in _REST_COUNTS:
        raise InputError("ply.f_rest", f"found {n_rest} f_rest properties; SH degree 0, 1, 2 or 3 "
                                       "needs 0, 9, 24 or 45")
    k = _REST_COUNTS[n_rest]
    used = [name for name in property_names(k, axes) if name not in ("nx", "ny", "nz")]
    missing = [name for name in used if name not in columns]
    if missing:
        field = "ply.f_rest" if missing[0].startswith("f_rest_") else f"ply.{missing[0]}"
        raise InputError(field, f"required property missing (all missing: {', '.join(missing)})")
    packed = np.empty((count, len(used)), dtype=np.float32)  # [G, 11 + axes + 3(K-1)]
    for j, prop in enumerate(used):
        packed[:, j] = columns[prop]
    finite = np.isfinite(packed)
    if not finite.all():
        row, col = np.argwhere(~finite)[0]
        raise InputError(f"ply.{used[col]}", f"vertex {row} is {packed[row, col]}; every value must be finite")

    values = torch.from_numpy(packed)
    dc = values[:, 3:6]  # [G, 3]
    higher = values[:, 6:6 + n_rest].reshape(count, 3, k - 1).transpose(1, 2)  # [G, K-1, 3]
    return model_type(
        means=values[:, 0:3].clone(),
        log_scales=values[:, 7 + n_rest:7 + axes + n_rest].clone(),
        quats=values[:, 7 + axes + n_rest:11 + axes + n_rest].clone(),
        opacity_logits=values[:, 6 + n_rest].clone(),
        sh=torch.cat([dc[:, None, :], higher], dim=1).contiguous(),
    )


def read_ply(path: str | Path, model_type: type[GaussianModel] = GaussianModel) -> GaussianModel:
    """Read a standard 3DGS PLY file (binary either endianness, or ASCII); a 2DGS one with
    model_type a 2DGS model."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError("ply.path", f"cannot read {path}: {exc.strerror or exc}") from None
    return parse_ply(data, path.name, model_type)


# ----------------------------------------------------------------------------- writing

def write_ply(model: GaussianModel, path: str | Path) -> None:
    """Write `model` as a standard binary little-endian 3DGS PLY (normals zero), or in the
    2DGS reference layout (two scale columns) for a 2DGS model.

    Atomic: the bytes go to a temporary file in the same directory, which replaces `path`
    only once complete, so a failure never leaves a partial file or clobbers an old one.
    """
    model.validate()
    path = Path(path)
    count, k = model.num_splats, model.sh.shape[1]
    sh = model.sh.detach().cpu()  # [G, K, 3]
    rest = sh[:, 1:, :].transpose(1, 2).reshape(count, 3 * (k - 1))  # channel-major [G, 3(K-1)]
    packed = torch.cat([
        model.means.detach().cpu(), torch.zeros(count, 3, dtype=torch.float32), sh[:, 0, :], rest,
        model.opacity_logits.detach().cpu()[:, None], model.log_scales.detach().cpu(),
        model.quats.detach().cpu(),
    ], dim=1)  # [G, 14 + axes + 3(K-1)]
    header = "".join(["ply\n", "format binary_little_endian 1.0\n", f"element vertex {count}\n",
                      *(f"property float {n}\n" for n in property_names(k, model.scale_axes)), "end_header\n"])
    body = packed.numpy().astype("<f4").tobytes()

    write_bytes_atomic(path, header.encode("ascii") + body)


# ----------------------------------------------------------------------------- sidecar

SIDECAR_FORMAT = "phd-3dgs-sidecar/1"   # the JSON `phd train` writes next to a PLY


def sidecar_path(ply: str | Path) -> Path:
    ply = Path(ply)
    return ply.with_name(ply.stem + ".json")


def read_sidecar(ply: str | Path) -> dict[str, Any] | None:
    """The sidecar `phd train` wrote next to a splat PLY (`phd_core.train.splats`), or None when absent."""
    path = sidecar_path(ply)
    if not path.exists():
        return None
    try:
        sidecar = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError("sidecar", f"cannot read {path}: {exc}") from None
    if not isinstance(sidecar, dict) or sidecar.get("format") != SIDECAR_FORMAT:
        raise InputError("sidecar", f"{path} is not a phd training sidecar")
    return sidecar
