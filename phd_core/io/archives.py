"""Zip archives a user hands over (a folder uploaded as one zip; a torch checkpoint, which
torch.save writes as a zip), bounded before anything in them is inflated.

`open_zip` reads the end-of-central-directory record itself (zip64's too) and walks the
central directory entry by entry, reading only each entry's fixed part: a zip that lists more
entries than its `ZipRules` allow is refused once that many are read, before `zipfile` reads
the whole directory and builds an object per entry (1.5 M empty entries in a 126 MiB zip took
832 MiB that way). Then each member's declared sizes are checked: how many times it inflates
(a zip bomb's mark; PLYs, checkpoints and JSON inflate well below the limit), so the whole
inflates no more than its worst member, and what all of them inflate to; members are stored or
deflated, never encrypted. Declared sizes can lie: `zipfile` stops a member at its declared size
and checks its CRC, and whoever writes members out counts the bytes they really inflate to.
Every refusal is an InputError naming the archive and the rule (`TooLarge` for a size limit).
"""

from __future__ import annotations

import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from ..errors import InputError, TooLarge, shown

MAX_ZIP_RATIO = 500             # inflated / deflated bytes of a member: above, a zip bomb
# The records zipfile reads the directory by (APPNOTE.TXT 4.3.12-4.3.16), as zipfile's own structs.
END = struct.Struct("<4s4H2LH")           # signature, disks, entries here and in all, directory size and offset
END_SIGNATURE = b"PK\x05\x06"
ZIP64_LOCATOR = struct.Struct("<4sLQL")   # signature, disk, zip64 end record's offset, disks
ZIP64_END = struct.Struct("<4sQ2H2L4Q")   # ..., entries here and in all, directory size and offset
ENTRY = struct.Struct("<4s4B4HL2L5H2L")   # a directory entry's fixed part, then its name, extra, comment
ENTRY_SIGNATURE = b"PK\x01\x02"
NAME_LENGTH = 12                          # ENTRY's field index of the name's length (extra's, comment's follow)
UNPACKED = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)
UNREAD_FLAGS = 0x1 | 0x20 | 0x40          # general purpose flags: encrypted, patched data, strong encryption
# What reading a member raises when its bytes are damaged: a bad local header or CRC, a corrupt
# deflate stream, data that ends early, an offset before the file's start (the seek's EINVAL).
DAMAGED = (zipfile.BadZipFile, zlib.error, EOFError, OSError)


@dataclass(frozen=True)
class ZipRules:
    """What a zip may hold."""

    max_entries: int                     # directory entries (folders included)
    max_bytes: int | None = None         # what all members declare they inflate to (None: the ratio bounds it)
    max_ratio: int = MAX_ZIP_RATIO       # how many times any member inflates


def open_zip(path: Path, rules: ZipRules, name: str) -> zipfile.ZipFile:
    """The zip at `path` opened once its directory and every member's declared sizes keep
    `rules`; else an InputError (TooLarge past max_bytes) naming `name`, the archive."""
    with open(path, "rb") as file:
        _count_entries(file, rules.max_entries, name)
    try:
        zipped = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise InputError(name, f"is not a readable zip file ({exc})") from None
    try:
        _check_members(zipped.infolist(), rules, name)
    except InputError:
        zipped.close()
        raise
    return zipped


def _count_entries(file: BinaryIO, limit: int, name: str) -> None:
    """Refuse a zip whose directory lists more than `limit` entries (or is damaged), reading at
    most `limit` entries of it. Where the directory lies is found as zipfile finds it: the end
    record at the file's end, else the last one in its final 64 KiB (a comment may follow)."""
    size = file.seek(0, 2)
    tail_start = max(0, size - END.size - 0xFFFF)
    file.seek(tail_start)
    tail = file.read()
    at = len(tail) - END.size
    if at < 0 or tail[at:at + 4] != END_SIGNATURE or tail[-2:] != b"\0\0":
        at = tail.rfind(END_SIGNATURE)
    if at < 0 or len(tail) - at < END.size:
        raise InputError(name, "is not a zip file (it has no end-of-central-directory record)")
    end = tail_start + at                                  # where the end record starts in the file
    _, _, _, _, entries, directory_size, _, _ = END.unpack_from(tail, at)
    start = end - directory_size
    if end >= ZIP64_LOCATOR.size + ZIP64_END.size:
        file.seek(end - ZIP64_LOCATOR.size)
        if file.read(4) == b"PK\x06\x07":                  # zip64: the counts and sizes are in its own end record
            file.seek(end - ZIP64_LOCATOR.size - ZIP64_END.size)
            record = file.read(ZIP64_END.size)
            if record[:4] == b"PK\x06\x06":
                _, _, _, _, _, _, _, entries, directory_size, _ = ZIP64_END.unpack(record)
                start = end - ZIP64_LOCATOR.size - ZIP64_END.size - directory_size
    if entries > limit:
        raise InputError(name, f"lists {entries} entries, more than the {limit} allowed")
    if start < 0:
        raise InputError(name, "is damaged: its central directory would start before the file")
    file.seek(start)
    count = read = 0
    while read < directory_size:                           # zipfile's own loop over the directory
        fixed = file.read(ENTRY.size)
        if len(fixed) < ENTRY.size or fixed[:4] != ENTRY_SIGNATURE:
            raise InputError(name, f"is damaged: entry {count} of its central directory is not one")
        count += 1
        if count > limit:
            raise InputError(name, f"lists more than the {limit} entries allowed")
        lengths = ENTRY.unpack(fixed)[NAME_LENGTH:NAME_LENGTH + 3]       # name, extra field, comment
        read += ENTRY.size + sum(lengths)
        file.seek(start + read)
    if count != entries:
        raise InputError(name, f"is damaged: its end record counts {entries} entries, its directory {count}")


def _check_members(members: list[zipfile.ZipInfo], rules: ZipRules, name: str) -> None:
    """Each member stored or deflated, unencrypted, inflating at most `rules.max_ratio` times;
    all of them together at most `rules.max_bytes`."""
    for member in members:
        if member.flag_bits & UNREAD_FLAGS:
            raise InputError(name, f"{shown(member.filename)} is encrypted or patched: zip it without a password")
        if member.compress_type not in UNPACKED:
            raise InputError(name, f"{shown(member.filename)} is compressed with method {member.compress_type}: only "
                                   "stored and deflated members are read")
        if member.file_size > rules.max_ratio * max(member.compress_size, 1):
            raise InputError(name, f"{shown(member.filename)} inflates {member.file_size} bytes from "
                                   f"{member.compress_size}, more than {rules.max_ratio} times: refused as a zip bomb")
    total = sum(member.file_size for member in members)
    if rules.max_bytes is not None and total > rules.max_bytes:
        raise TooLarge(name, f"its files inflate to {total} bytes, more than the {rules.max_bytes} allowed")
