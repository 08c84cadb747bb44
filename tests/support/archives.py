"""Archives for the upload tests and the folder fuzzer, built the way an attacker builds them:
zips written byte by byte (members deflated in advance, whatever their headers say), and torch
checkpoints laid out as torch.save lays them out whose records inflate to gigabytes, made
without ever holding those gigabytes (no tensor of that size exists here)."""

from __future__ import annotations

import collections
import io
import math
import pickle
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

# gsplat's splat tensors per splat, SH degree 0 (tests/support/trainers.write_gsplat).
GSPLAT_SHAPES = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "sh0": (1, 3), "shN": (0, 3)}


@dataclass
class Member:
    """A zip member as it lies in the archive: its bytes there, and what its headers declare."""

    name: str
    data: bytes                       # as stored (deflated when method is ZIP_DEFLATED)
    size: int                         # declared inflated size
    crc: int
    method: int = zipfile.ZIP_DEFLATED


def stored(name: str, data: bytes) -> Member:
    return Member(name, data, len(data), zlib.crc32(data), zipfile.ZIP_STORED)


def raw_zip(members: list[Member]) -> bytes:
    """A zip of `members` exactly as given: local headers, data, central directory, end record."""
    body, directory = bytearray(), bytearray()
    for m in members:
        local, entry = _headers(m, len(body))
        body += local + m.data
        directory += entry
    return bytes(body + directory + _end(len(members), len(directory), len(body)))


def listing_zip(count: int) -> bytes:
    """A zip whose central directory lists one empty file `count` times (every entry points at
    its one local header): 47 bytes an entry, and `count` objects for whoever lists them."""
    local, entry = _headers(stored("x", b""), 0)
    return local + entry * count + _end(count, len(entry) * count, len(local))


def _headers(member: Member, offset: int) -> tuple[bytes, bytes]:
    """(local header, central directory entry) of `member`, whose local header is at `offset`."""
    name = member.name.encode()
    fields = (member.method, 0, 0x21, member.crc, len(member.data), member.size, len(name))   # method, time, 1980, ...
    return (struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, *fields, 0) + name,
            struct.pack("<4s6H3L5H2L", b"PK\x01\x02", 20, 20, 0, *fields, 0, 0, 0, 0, 0, offset) + name)


def _end(count: int, directory_size: int, directory_offset: int) -> bytes:
    """The end of central directory record, with zip64's end record and locator before it past 65,535 entries."""
    zip64 = b""
    if count > 0xFFFF:
        zip64 = (struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, count, count, directory_size,
                             directory_offset)
                 + struct.pack("<4sLQL", b"PK\x06\x07", 0, directory_offset + directory_size, 1))
        count = 0xFFFF
    return zip64 + struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, count, count, directory_size, directory_offset, 0)


def deflated_zeros(name: str, size: int, chunk: int = 1 << 20) -> Member:
    """A member of `size` zero bytes, deflated chunk by chunk with full flushes: every chunk then
    deflates to the same bytes, so the stream is one chunk's repeated (about 1,000 times smaller
    than its zeros for 1 MiB chunks, 280 for 8 KiB) and made without inflating anything."""
    deflate = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = deflate.compress(bytes(chunk)) + deflate.flush(zlib.Z_FULL_FLUSH)
    whole, rest = divmod(size, chunk)
    data = block * whole + deflate.compress(bytes(rest)) + deflate.flush()
    crc = 0
    for _ in range(whole):
        crc = zlib.crc32(bytes(chunk), crc)
    return Member(name, data, size, zlib.crc32(bytes(rest), crc))


class _Storage:
    """One storage record of a checkpoint: its key and element count (float32)."""

    def __init__(self, key: str, numel: int):
        self.key, self.numel = key, numel


class _Tensor:
    """A contiguous float32 tensor over a whole storage, pickled as torch.save pickles one."""

    def __init__(self, storage: _Storage, shape: tuple[int, ...]):
        self.storage, self.shape = storage, shape

    def __reduce__(self):
        stride = tuple(math.prod(self.shape[i + 1:]) for i in range(len(self.shape)))
        return torch._utils._rebuild_tensor_v2, (self.storage, 0, self.shape, stride, False,
                                                 collections.OrderedDict())


class _Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if isinstance(obj, _Storage):              # as torch.save names a storage record
            return "storage", torch.FloatStorage, obj.key, "cpu", obj.numel
        return None


def zero_checkpoint(splats: int, chunk: int = 1 << 20) -> bytes:
    """A gsplat checkpoint (`{"step", "splats"}`) of `splats` zero splats whose records are
    deflated zeros (chunks of `chunk` bytes: `deflated_zeros`): 20 M splats, 1.1 GB of tensors,
    take about 1 MB."""
    shapes = {key: (splats, *shape) for key, shape in GSPLAT_SHAPES.items()}
    storages = {key: _Storage(str(k), math.prod(shape)) for k, (key, shape) in enumerate(shapes.items())}
    buffer = io.BytesIO()
    _Pickler(buffer, protocol=2).dump({"step": 6999, "splats": {key: _Tensor(storages[key], shape)
                                                                for key, shape in shapes.items()}})
    return raw_zip([stored("archive/data.pkl", buffer.getvalue()), stored("archive/byteorder", b"little"),
                    *(deflated_zeros(f"archive/data/{s.key}", 4 * s.numel, chunk) for s in storages.values()),
                    stored("archive/version", b"3\n")])


def view_checkpoint(splats: int) -> bytes:
    """A gsplat checkpoint whose tensors view one stored zero each, `splats` times (stride 0):
    a few hundred bytes on disk for any splat count."""
    buffer = io.BytesIO()
    torch.save({"step": 6999, "splats": {key: torch.zeros(1).expand(splats, *shape)
                                         for key, shape in GSPLAT_SHAPES.items()}}, buffer)
    return buffer.getvalue()


def allocating_checkpoint(size: int) -> bytes:
    """A torch checkpoint whose pickle calls bytearray(size), which torch's weights_only loader
    allows: a few bytes that allocate `size`."""
    pickled = b"\x80\x02cbuiltins\nbytearray\nJ" + struct.pack("<l", size) + b"\x85R."   # GLOBAL BININT TUPLE1 REDUCE
    return raw_zip([stored("archive/data.pkl", pickled), stored("archive/version", b"3\n")])


def gsplat_zip(checkpoint: bytes, method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """A gsplat result folder as a user zips it, holding `checkpoint` as its latest step."""
    files = {"garden/cfg.yml": b"data_dir: data/garden\n", "garden/ckpts/ckpt_29999_rank0.pt": checkpoint}
    return zip_of(files, method)


BOMBS: dict[str, Callable[[], bytes]] = {   # the uploads issue 46's probe inflated, each a zip
    "20 M zero splats deflated in a checkpoint deflated again in the zip (4 KB)":
        lambda: gsplat_zip(zero_checkpoint(20_000_000)),
    "20 M splats each a view of one stored zero": lambda: gsplat_zip(view_checkpoint(20_000_000)),
    "a checkpoint's pickle calling bytearray(1 GiB)": lambda: gsplat_zip(allocating_checkpoint(1 << 30)),
    "1 M directory entries (47 MB)": lambda: listing_zip(1_000_000),
}


def folder_files(root: Path, under: Path) -> dict[str, bytes]:
    """The files under `root` by their paths relative to `under` (a folder as a zip holds it)."""
    return {path.relative_to(under).as_posix(): path.read_bytes() for path in sorted(root.rglob("*"))
            if path.is_file()}


def zip_of(files: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """An ordinary zip of `files` (zipfile's)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", method) as zipped:
        for name, data in files.items():
            zipped.writestr(zipfile.ZipInfo(name), data, method)    # dated 1980: the same files, the same bytes
    return buffer.getvalue()
