"""ModelCache: entries found again for the same model and settings, missed for any change."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import torch

from phd_core.io.cache import ModelCache, content_digest


def test_an_entry_is_found_for_the_same_model_and_settings_only(tmp_path: Path) -> None:
    model = tmp_path / "model.ply"
    model.write_bytes(b"splats v1")
    cache = ModelCache(model)
    assert cache.load_json("calibration", {"eps": 0.1}) is None
    assert cache.save_json("calibration", {"eps": 0.1}, {"r_drop": 0.3})
    assert ModelCache(model).load_json("calibration", {"eps": 0.1}) == {"r_drop": 0.3}
    assert ModelCache(model).load_json("calibration", {"eps": 0.2}) is None      # other settings miss
    model.write_bytes(b"splats v2")                                              # another model misses
    os.utime(model, ns=(1, 1))
    assert ModelCache(model).load_json("calibration", {"eps": 0.1}) is None


def test_tensors_round_trip_bit_for_bit(tmp_path: Path) -> None:
    model = tmp_path / "m.ply"
    model.write_bytes(b"x")
    seen = {"ids": torch.arange(5), "share": torch.rand(5, dtype=torch.float64)}
    assert ModelCache(model).save_tensors("coverage", {"views": 3}, seen)
    back = ModelCache(model).load_tensors("coverage", {"views": 3})
    assert back is not None and all(torch.equal(back[k], v) for k, v in seen.items())


def test_a_folder_model_keeps_its_cache_inside_and_out_of_its_digest(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "point_cloud").mkdir(parents=True)
    (run / "point_cloud" / "p.ply").write_bytes(b"abc")
    before = content_digest(run)
    cache = ModelCache(run)
    assert cache.save_json("calibration", {}, {"r_drop": 0.1})
    assert cache.dir == run / ".phd-cache" and content_digest(run) == before
    (run / "cameras.json").write_text("[]")
    assert content_digest(run) != before


def test_a_cache_that_cannot_be_written_skips_the_write_and_says_why(tmp_path: Path) -> None:
    model = tmp_path / "m.ply"
    model.write_bytes(b"x")
    (tmp_path / "m.ply.phd-cache").write_text("a file where the cache folder would go")
    cache = ModelCache(model)
    assert not cache.save_json("calibration", {}, {"r_drop": 0.1})
    assert cache.skipped is not None and "cache not written" in cache.skipped
    assert cache.load_json("calibration", {}) is None


def test_a_model_deleted_meanwhile_gets_no_cache_folder_back(tmp_path: Path) -> None:
    """A result computed while its model was deleted (a rank racing a delete) is not written."""
    model = tmp_path / "m.ply"
    model.write_bytes(b"x")
    cache = ModelCache(model)
    assert cache.save_json("calibration", {}, {"r_drop": 0.1})
    shutil.rmtree(cache.dir)
    model.unlink()
    assert not cache.save_json("calibration", {}, {"r_drop": 0.1}) and "no longer exists" in (cache.skipped or "")
    assert not cache.dir.exists()
