"""The bounds of phd_core.io.archives and phd_core.io.foreign on their own: where a zip's
directory is, how its entries are counted, what a checkpoint allocates, how YAML aliases count
(the service's tests send the same files through a real server)."""

from __future__ import annotations

import io
import struct
import zipfile

import pytest
import torch

from phd_core.errors import InputError
from phd_core.io.archives import ZipRules, open_zip
from phd_core.io.foreign import MAX_YAML_NODES, checkpoint_bytes, read_checkpoint, read_yaml
from support.archives import listing_zip, zip_of


def test_entries_are_counted_from_the_directory_not_only_from_the_end_record(tmp_path):
    path = tmp_path / "many.zip"
    path.write_bytes(listing_zip(20_000))
    with pytest.raises(InputError, match="lists 20000 entries, more than the 10000 allowed"):
        open_zip(path, ZipRules(max_entries=10_000), "many.zip")
    lying = bytearray(path.read_bytes())
    struct.pack_into("<2H", lying, len(lying) - 22 + 8, 5, 5)          # the end record says 5 entries
    path.write_bytes(lying)
    with pytest.raises(InputError, match="lists more than the 10000 entries allowed"):
        open_zip(path, ZipRules(max_entries=10_000), "many.zip")


def test_a_zip64_end_record_and_a_comment_are_found_where_zipfile_finds_them(tmp_path):
    path = tmp_path / "zip64.zip"
    path.write_bytes(listing_zip(70_000))                             # past 65,535: zip64's end record
    with open_zip(path, ZipRules(max_entries=100_000), "zip64.zip") as zipped:
        assert len(zipped.infolist()) == 70_000
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zipped:
        zipped.writestr("a.txt", b"a")
        zipped.comment = b"a comment after the end record"
    path.write_bytes(buffer.getvalue())
    with open_zip(path, ZipRules(max_entries=1), "comment.zip") as zipped:
        assert zipped.read("a.txt") == b"a"


def test_a_checkpoint_reads_as_torch_wrote_it_and_allocates_what_its_records_declare(tmp_path):
    state = {"step": 7, "splats": {"means": torch.randn(50, 3), "sh0": torch.randn(50, 1, 3)}}
    path = tmp_path / "ckpt.pt"
    torch.save(state, path)
    with zipfile.ZipFile(path) as zipped:
        records = {info.filename: zipped.read(info) for info in zipped.infolist()}
    assert checkpoint_bytes(path) == sum(map(len, records.values()))
    deflated = tmp_path / "deflated.pt"                     # the same records deflated: read the same
    deflated.write_bytes(zip_of(records))
    for read in (read_checkpoint(path), read_checkpoint(deflated)):
        assert read["step"] == 7 and all(torch.equal(read["splats"][k], v) for k, v in state["splats"].items())


def test_yaml_aliases_count_as_what_they_expand_to(tmp_path):
    path = tmp_path / "cfg.yml"
    path.write_text("a: &a [1, 2, 3]\nb: *a\nc: !!python/object/apply:pathlib.PosixPath [data, x]\n")
    assert read_yaml(path) == {"a": [1, 2, 3], "b": [1, 2, 3], "c": ["data", "x"]}
    leaves = MAX_YAML_NODES // 10
    path.write_text(f"a: &a [{', '.join(['0'] * 10)}]\nb: [{', '.join(['*a'] * leaves)}]\n")
    with pytest.raises(InputError, match="aliases expand it past"):
        read_yaml(path)
    path.write_text("a: &a [1, *a]\n")
    with pytest.raises(InputError, match="refers to a node that contains it"):
        read_yaml(path)


def test_yaml_past_its_depth_or_size_is_refused_naming_the_file(tmp_path):
    deep = tmp_path / "deep.yml"
    deep.write_text("a: " + "[" * 101 + "]" * 101)
    with pytest.raises(InputError, match="deeper than 100 levels") as refused:
        read_yaml(deep)
    assert refused.value.field == "deep.yml"
    big = tmp_path / "big.yml"
    big.write_bytes(b"#" * (2 << 20))
    with pytest.raises(InputError, match="larger than the 1048576 bytes"):
        read_yaml(big)
