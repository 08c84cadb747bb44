"""The executor seam without Ray: the local default, the registry, and an executor that
runs chunks out of order on pickled copies gives exactly the local answers."""

from __future__ import annotations

import pickle
import sys

import pytest

from phd_cli import main
from phd_core import uq
from phd_core.errors import InputError
from phd_core.executors import EXECUTORS, LOCAL, make_executor
from phd_core.executors.ray import RayExecutor
from support.toy_renderers import BlobRenderer, ring_cameras


class ScrambledExecutor:
    """Chunks of two, run last first, each on a pickled copy of its inputs (as a remote worker sees them)."""

    name = "scrambled"

    def __init__(self):
        self.chunks_run = 0

    def share(self, value):
        return pickle.dumps(value)

    def split(self, items):
        items = list(items)
        return [items[i:i + 2] for i in range(0, len(items), 2)]

    def map(self, fn, chunks, *shared, done=None):
        results = [None] * len(chunks)
        for i in reversed(range(len(chunks))):
            copies = [pickle.loads(s) if isinstance(s, bytes) else pickle.loads(pickle.dumps(s)) for s in shared]
            chunk = pickle.loads(chunks[i]) if isinstance(chunks[i], bytes) else pickle.loads(pickle.dumps(chunks[i]))
            results[i] = pickle.loads(pickle.dumps(fn(chunk, *copies)))
            self.chunks_run += 1
            if done is not None:
                done(i)
        return results


@pytest.fixture(scope="module")
def blobs() -> BlobRenderer:
    return BlobRenderer.random(40, seed=2, training_cameras=ring_cameras(5, size=12, height=0.6))


def test_local_maps_one_view_per_chunk_in_order_and_stops_at_an_error_from_done() -> None:
    chunks = LOCAL.split(["a", "b", "c"])
    assert chunks == [["a"], ["b"], ["c"]]
    seen = []
    assert LOCAL.map(lambda chunk, suffix: chunk[0] + suffix, chunks, "!", done=seen.append) == ["a!", "b!", "c!"]
    assert seen == [0, 1, 2]
    ran = []

    def stop(i: int) -> None:
        if i == 1:
            raise LookupError("stop")

    with pytest.raises(LookupError):
        LOCAL.map(lambda chunk: ran.append(chunk), chunks, done=stop)
    assert ran == [["a"], ["b"]]                 # nothing after the chunk whose `done` raised


def test_ranking_calibration_and_selection_do_not_depend_on_chunking_or_order(blobs) -> None:
    candidates = ring_cameras(7, size=12, height=1.4)
    executor = ScrambledExecutor()
    for strategy in ("sigma_max", uq.DEFAULT_STRATEGY):
        local = uq.rank_views(blobs, candidates, ratio=0.3, samples=6, seed=5, strategy=strategy)
        spread = uq.rank_views(blobs, candidates, ratio=0.3, samples=6, seed=5, strategy=strategy, executor=executor)
        assert [r.to_dict() for r in spread] == [r.to_dict() for r in local]
        assert len({r.sigma_max for r in local}) == len(local)     # distinct: an order mix-up would show
    assert executor.chunks_run == 2 * 4                              # 7 views in chunks of 2, per strategy

    calibration = uq.calibrate(blobs, blobs.training_cameras, epsilon=0.01, step=0.1, samples=3, seed=1)
    spread = uq.calibrate(blobs, blobs.training_cameras, epsilon=0.01, step=0.1, samples=3, seed=1,
                          executor=executor)
    assert spread.to_dict() == calibration.to_dict() and 0 < calibration.r_drop < 0.9

    other = BlobRenderer.random(30, seed=4, training_cameras=ring_cameras(4, size=12, height=1.2))
    for rule in uq.SELECTION_RULES:
        local = uq.select_models(blobs, other, candidates, ratio_a=0.2, ratio_b=0.2, samples=4, rule=rule)
        spread = uq.select_models(blobs, other, candidates, ratio_a=0.2, ratio_b=0.2, samples=4, rule=rule,
                                  executor=executor)
        assert spread.to_dict() == local.to_dict()
        assert {v.choice for v in local.views} == {"a", "b"}


def test_progress_counts_views_and_a_cancel_stops_the_map(blobs) -> None:
    seen: list[float] = []
    uq.uncertainty(blobs, ring_cameras(5, size=12), ratio=0.2, samples=3, progress=seen.append,
                   executor=ScrambledExecutor())
    # chunks of 2, 2 and 1 views, run last first; below 1 until the end
    assert seen == pytest.approx([1 / 5, 3 / 5, 0.99, 1.0])

    class Cancelled(Exception):
        pass

    def cancel(fraction: float) -> None:
        raise Cancelled

    executor = ScrambledExecutor()
    with pytest.raises(Cancelled):
        uq.rank_views(blobs, ring_cameras(6, size=12), ratio=0.2, samples=3, progress=cancel, executor=executor)
    assert executor.chunks_run == 1


def test_input_errors_cross_process_boundaries_as_themselves() -> None:
    for error in (InputError("cameras[2].w", "must be positive"),
                  uq.CalibrationError("epsilon", "r_drop = 0", [0.1], [0.5])):
        copy = pickle.loads(pickle.dumps(error))
        assert type(copy) is type(error) and str(copy) == str(error)
        assert (copy.field, copy.reason) == (error.field, error.reason)
    assert (copy.ratios, copy.errors) == ([0.1], [0.5])


def test_unknown_executors_and_missing_ray_are_clear_errors(monkeypatch, capsys, tmp_path) -> None:
    assert set(EXECUTORS) >= {"local", "ray"}
    assert make_executor("local") is LOCAL
    with pytest.raises(InputError) as info:
        make_executor("dask", field="executor")
    assert info.value.field == "executor" and "known: local, ray" in info.value.reason

    from pydantic import ValidationError

    from service.settings import Settings

    with pytest.raises(ValidationError, match="unknown executor 'dask'"):
        Settings(data_dir=tmp_path, executor="dask")
    assert Settings(data_dir=tmp_path).executor == "local"
    monkeypatch.setenv("PHD_EXECUTOR", "ray")
    monkeypatch.setenv("PHD_EXECUTOR_ADDRESS", "ray://head:10001")
    settings = Settings.from_env(data_dir=tmp_path)
    assert (settings.executor, settings.executor_address) == ("ray", "ray://head:10001")

    monkeypatch.setitem(sys.modules, "ray", None)                   # as if ray were not installed
    with pytest.raises(InputError, match=r"pip install 'ph-dropout-service\[ray\]'"):
        RayExecutor("auto").connect()
    model = tmp_path / "m.ply"
    from phd_core.renderers.gs3d import write_ply
    from support.fixtures import svc_random_gaussians

    write_ply(svc_random_gaussians(20), model)
    cameras = tmp_path / "c.json"
    cameras.write_text('[{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]], "w": 8, "h": 8, '
                       '"fl_x": 8, "fl_y": 8}]')
    code = main(["rank", "--model", str(model), "--candidates", str(cameras), "--dropout-ratio", "0.1",
                 "--ray", "auto"])
    err = capsys.readouterr().err
    assert code == 2 and "ray: Ray is not installed" in err
    code = main(["serve", "--ray", "auto", "--data-dir", str(tmp_path / "data"), "--port", "0"])
    assert code == 2 and "phd serve: error: ray: Ray is not installed" in capsys.readouterr().err
