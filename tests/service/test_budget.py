"""The memory plan, and the ledger that models in memory, running jobs and upload parses share."""

from __future__ import annotations

import threading
import time

import pytest
import torch

from phd_core.errors import InputError
from phd_core.renderers import RenderMemory
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.visibility import (
    COVERAGE_CAPTURE_BYTES,
    COVERAGE_ELEMENT_BYTES,
    KEPT_ELEMENT_BYTES,
    SEEN_LOADED_BYTES,
    seen_bytes,
    visibility_bytes,
)
from phd_core.uq.strategies.captured import CapturedStore, camera_key
from phd_core.uq.strategies.targets import density_bytes
from service.budget import MemoryLedger, ModelSize, load_bytes, model_bytes, plan_work
from service.errors import ServiceError
from support.fixtures import svc_random_gaussians

MODEL = [ModelSize("a", 300, 20_000, "model_id")]


def plan(pixels: int, samples: int, budget: int, *, models=MODEL, kept: int = 0, renders=None):
    return plan_work(models, pixels, samples, kept, budget, renders=renders, size_field="downscale",
                     kept_field="training_cameras")


def test_plan_fits_the_budget_and_batches_masks_instead_of_growing_with_samples():
    small = plan(800 * 800, 256, 256 << 20)
    assert 1 <= small.mask_batch < 64 and small.bytes + load_bytes(20_000) <= 256 << 20
    tiny = [ModelSize("a", 1, 20_000, "model_id")]             # masks of next to no bytes: only the std could grow
    assert plan(800 * 800, 4096, 256 << 20, models=tiny).mask_batch == plan(800 * 800, 256, 256 << 20,
                                                                             models=tiny).mask_batch   # it is streamed
    assert plan(100 * 100, 256, 4 << 30).mask_batch == 64
    assert plan(100 * 100, 3, 4 << 30).mask_batch == 3
    with pytest.raises(ServiceError) as exc:
        plan(800 * 800, 256, 64 << 20)
    assert (exc.value.status, exc.value.field) == (413, "downscale")
    with pytest.raises(ServiceError) as exc:
        plan(100 * 100, 2, 4 << 30, kept=10 << 30)
    assert exc.value.field == "training_cameras"


def test_the_renders_bounds_shrink_the_batch_and_refuse_what_cannot_fit():
    without = plan(200 * 200, 64, 1 << 30)
    render = RenderMemory(fixed=300 << 20, kept=0, per_mask=20 << 20)
    bounded = plan(200 * 200, 64, 1 << 30, renders=render)
    assert bounded.mask_batch < without.mask_batch and bounded.bytes >= (300 << 20) + bounded.mask_batch * (20 << 20)
    with pytest.raises(ServiceError) as exc:                       # one view's fragments alone exceed it
        plan(200 * 200, 64, 1 << 30, renders=RenderMemory(fixed=2 << 30, kept=0, per_mask=0))
    assert exc.value.field == "downscale"


def test_masks_grow_with_samples_times_units_and_a_model_too_big_is_named():
    few = plan(100 * 100, 64, 4 << 30, models=[ModelSize("a", 1_000_000, 1 << 20, "model_id")])
    many = plan(100 * 100, 256, 4 << 30, models=[ModelSize("a", 1_000_000, 1 << 20, "model_id")])
    assert many.bytes - few.bytes >= 192 * 1_000_000               # uniforms and keep flags of 192 more samples
    with pytest.raises(ServiceError) as exc:
        plan(100 * 100, 2, 64 << 20, models=[ModelSize("a", 300, 20 << 20, "model_b")])
    assert (exc.value.status, exc.value.code, exc.value.field) == (413, "over_memory_budget", "model_b")


def test_a_model_named_twice_loads_once_but_draws_masks_twice():
    one = plan(100 * 100, 8, 4 << 30, models=[ModelSize("a", 300, 20_000, "model_a")])
    budget = load_bytes(20_000) + one.bytes + 5 * 8 * 300         # room for one load, two mask draws
    twice = [ModelSize("a", 300, 20_000, "model_a"), ModelSize("a", 300, 20_000, "model_b")]
    assert one.mask_batch == plan(100 * 100, 8, budget, models=twice).mask_batch == 8
    other = [ModelSize("a", 300, 20_000, "model_a"), ModelSize("b", 300, 20_000, "model_b")]
    assert plan(100 * 100, 8, budget, models=other).mask_batch < 8   # two different models: two loads


# ----------------------------------------------------------------------------- the ledger

class Models:
    """Real small renderers, loaded by id; counts the loads, and holds each load until `go` is set."""

    def __init__(self, fail: frozenset[str] = frozenset()):
        self.loads: list[str] = []
        self.fail = fail
        self.go = threading.Event()
        self.go.set()

    def __call__(self, model_id: str) -> GaussianRenderer:
        self.loads.append(model_id)
        self.go.wait(10)
        if model_id in self.fail:
            raise InputError("model", f"{model_id} is broken")
        return GaussianRenderer(svc_random_gaussians(50, seed=len(self.loads)))


def wait_until(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


SIZE = 1000                                       # file bytes of every model below
KEEP, LOAD = model_bytes(SIZE), load_bytes(SIZE)


def test_ledger_makes_concurrent_work_wait_and_times_out():
    ledger = MemoryLedger(100, 4, Models())
    order = []
    with ledger.reserve(70):
        def second():
            with ledger.reserve(50):
                order.append("second")

        thread = threading.Thread(target=second)
        thread.start()
        time.sleep(0.2)
        assert order == [] and ledger.used == 70          # waits: 70 + 50 > 100
        with pytest.raises(TimeoutError):
            with ledger.reserve(40, timeout=0.1):
                pass
        order.append("first done")
    thread.join(5)
    assert order == ["first done", "second"] and ledger.used == 0
    with pytest.raises(ValueError):                       # more than the budget can never be granted
        with ledger.reserve(101):
            pass


def test_a_model_in_memory_is_counted_once_and_kept_idle_until_room_is_needed():
    load = Models()
    ledger = MemoryLedger(2 * KEEP + LOAD, 4, load)
    with ledger.models({"a": SIZE}, 100) as renderers:
        assert ledger.used == KEEP + 100                  # the load's parse bytes went back once loaded
        first = renderers["a"]
    assert ledger.used == KEEP and ledger.loaded() == ["a"]          # idle, still in memory
    with ledger.models({"a": SIZE}, LOAD) as renderers:   # only the new bytes: the model is already held
        assert renderers["a"] is first and ledger.used == KEEP + LOAD
    assert load.loads == ["a"]
    with ledger.reserve(2 * KEEP + LOAD):                 # needs all of it: the idle model goes
        assert ledger.loaded() == [] and ledger.used == 2 * KEEP + LOAD
    assert ledger.used == 0


def test_a_model_in_use_is_never_evicted_the_others_go_least_recently_used_first():
    ledger = MemoryLedger(3 * KEEP + LOAD - 1, 4, Models())
    for model_id in "abc":
        with ledger.models({model_id: SIZE}, 0):
            pass
    with ledger.models({"a": SIZE}, 0):                   # a is now the most recently used
        pass
    assert ledger.loaded() == ["b", "c", "a"]
    seen, release = [], threading.Event()

    def everything() -> None:                             # the whole budget: every model must go
        with ledger.reserve(ledger.budget):
            seen.append(ledger.loaded())
            release.wait(10)

    with ledger.models({"b": SIZE}, 0):                   # b in use
        with ledger.models({"d": SIZE}, 0):               # d's load needs room: c goes, not b
            assert ledger.loaded() == ["a", "b", "d"]
        thread = threading.Thread(target=everything)
        thread.start()
        time.sleep(0.2)
        assert seen == [] and "b" in ledger.loaded()      # waits for b rather than evicting it
    wait_until(lambda: seen)
    assert seen == [[]] and ledger.used == ledger.budget
    release.set()
    thread.join(10)
    assert ledger.used == 0


def test_idle_models_are_capped_and_a_deleted_model_leaves_with_its_last_job():
    ledger = MemoryLedger(10 * LOAD, 2, Models())
    for model_id in "abc":
        with ledger.models({model_id: SIZE}, 0):
            pass
    assert ledger.loaded() == ["b", "c"] and ledger.used == 2 * KEEP
    with ledger.models({"b": SIZE}, 0):
        ledger.forget("b")
        assert ledger.loaded() == ["c"] and ledger.used == 2 * KEEP   # still held by the job
    assert ledger.used == KEEP


def test_two_jobs_share_one_load_and_a_failed_load_fails_both_and_frees_its_bytes():
    load = Models(fail=frozenset({"bad"}))
    ledger = MemoryLedger(4 * LOAD, 4, load)
    for model_id in ("a", "bad"):
        got = []

        def job() -> None:
            try:
                with ledger.models({model_id: SIZE}, 10) as renderers:
                    got.append(renderers[model_id])
            except InputError as exc:
                got.append(exc.field)

        load.go.clear()
        threads = [threading.Thread(target=job) for _ in range(2)]
        threads[0].start()
        wait_until(lambda: model_id in load.loads)        # the first job is loading it
        threads[1].start()
        # The first holds the load's peak (its 10 inside it), the second its 10 while it waits on that load.
        wait_until(lambda: ledger.used == LOAD + 10 + (KEEP if model_id == "bad" else 0))
        load.go.set()
        for thread in threads:
            thread.join(10)
        assert load.loads.count(model_id) == 1
        if model_id == "a":
            assert len(got) == 2 and got[0] is got[1]
        else:
            assert got == ["model", "model"]
    assert ledger.used == KEEP and ledger.loaded() == ["a"]


def test_an_uploaded_model_stays_in_memory_in_the_bytes_of_its_parse():
    ledger = MemoryLedger(2 * LOAD, 1, Models())
    renderer = GaussianRenderer(svc_random_gaussians(20))
    with ledger.reserve(LOAD) as parse:
        parse.keep("a", renderer, SIZE)
        assert ledger.used == LOAD                        # nothing reserved anew
    assert ledger.used == KEEP and ledger.loaded() == ["a"]
    with ledger.reserve(LOAD) as parse:
        parse.keep("b", renderer, SIZE)
    assert ledger.loaded() == ["b"] and ledger.used == KEEP    # one idle model at most: a went
    with ledger.reserve(KEEP - 1) as parse:
        parse.keep("c", renderer, SIZE)                   # the bytes cannot hold it: not kept
    assert ledger.loaded() == ["b"] and ledger.used == KEEP


def test_every_built_in_family_loads_within_its_model_bytes(svc_model_files, tmp_path):
    from phd_core.renderers import FAMILIES, load_model
    from phd_core.renderers.gs2d import SurfelModel, write_surfel_ply

    g = torch.Generator().manual_seed(0)
    write_surfel_ply(SurfelModel(torch.rand(300, 3, generator=g), torch.rand(300, 2, generator=g) - 3,
                                 torch.randn(300, 4, generator=g), torch.zeros(300), torch.rand(300, 16, 3)),
                     tmp_path / "surfels.ply")
    for path in (svc_model_files["ply"], svc_model_files["nerf"], tmp_path / "surfels.ply"):
        renderer = load_model(path)
        model = renderer.model
        tensors = (list(model.parameters()) + list(model.buffers()) if isinstance(model, torch.nn.Module)
                   else list(model.tensors()))
        assert sum(t.numel() * t.element_size() for t in tensors) <= model_bytes(path.stat().st_size)
        assert FAMILIES[renderer.kind].memory is not None        # and it bounds its renders
    assert {load_model(p).kind for p in (svc_model_files["ply"], svc_model_files["nerf"], tmp_path / "surfels.ply")} \
        == set(FAMILIES)


def test_a_visibility_strategy_plans_its_captured_views_and_what_each_view_sees(svc_start, svc_model_files):
    from client import PHDClient
    from service.schemas import RankRequest
    from service.work import rank_job
    from support.fixtures import svc_cameras

    server = svc_start()
    service = server.app.state.service
    with PHDClient(server.url) as phd:      # captured poses rendered at 300x300, candidates at 40x40
        model_id = phd.upload_model(svc_model_files["ply"], cameras=svc_cameras(3, size=300)).id
    record, renderers = service.store.get(model_id), {model_id: service.ledger.load(model_id)}
    candidates = [c.to_frame() for c in svc_cameras(2, size=40, phase=0.5)]

    def plan(strategy: str):
        body = RankRequest(cameras=candidates, samples=8, dropout_ratio=0.1, strategy=strategy)
        work, _ = rank_job(record, body, service.settings, lambda name: name, service.ledger, store=service.store)
        return work.renders, work.plan(renderers, lambda fraction: None)

    plain, plain_plan = plan("sigma_max")
    seen, seen_plan = plan("visibility_sigma")
    assert len(seen.models[0][2]) == len(plain.models[0][2]) + 3          # the captured poses are rendered too
    # What each candidate sees: at most every splat of the model (300), and at most 4 a pixel; each
    # captured view the same, in the compact form it is kept and stored in.
    views, captured = svc_cameras(2, size=40, phase=0.5), svc_cameras(3, size=300)
    assert seen.kept_bytes - plain.kept_bytes == (sum(visibility_bytes(300, c) for c in views) + COVERAGE_CAPTURE_BYTES
                                                  + seen_bytes(300, captured))
    assert visibility_bytes(300, views[0]) == (KEPT_ELEMENT_BYTES + COVERAGE_ELEMENT_BYTES) * 300
    assert visibility_bytes(10**6, views[0]) == (KEPT_ELEMENT_BYTES + COVERAGE_ELEMENT_BYTES) * 4 * 40 * 40
    # The 300x300 captured views' renders, and what each sees, outweigh the 40x40 renders.
    assert seen_plan.bytes > plain_plan.bytes + seen_bytes(300, captured)
    # Under a budget the plain strategy fits and this one does not, the refusal names the strategy
    # and the cheaper one that fits, beside the resolution.
    tight = service.settings.model_copy(update={"memory_budget_bytes": model_bytes(record.size_bytes)
                                                + plain_plan.bytes + (1 << 20)})
    body = RankRequest(cameras=candidates, samples=8, dropout_ratio=0.1, strategy="visibility_sigma")
    with pytest.raises(ServiceError) as refused:
        work, _ = rank_job(record, body, tight, lambda name: name, service.ledger, store=service.store)
        work.plan(renderers, lambda fraction: None)
    assert refused.value.status == 413 and refused.value.field == "strategy"
    assert "strategy 'fvs_sigma_floor', which fits" in refused.value.message and "downscale" in refused.value.message
    work, _ = rank_job(record, body.model_copy(update={"strategy": "fvs_sigma_floor"}), tight, lambda name: name,
                       service.ledger, store=service.store)
    assert work.plan(renderers, lambda fraction: None).bytes <= plain_plan.bytes

    # Once a rank has stored what the captured views saw, a rank renders its candidates only and
    # plans the stored views' elements (at most the bound).
    with PHDClient(server.url) as phd:
        phd.rank(model_id, cameras=candidates, samples=4, dropout_ratio=0.1, strategy="visibility_sigma")
    stored = CapturedStore(service.store.cache(record)).index()
    assert len(stored) == 3 and 0 < sum(stored.values()) <= 3 * 300
    again, again_plan = plan("visibility_sigma")
    assert len(again.models[0][2]) == len(plain.models[0][2])
    assert again.kept_bytes - plain.kept_bytes == (sum(visibility_bytes(300, c) for c in views) + COVERAGE_CAPTURE_BYTES
                                                   + SEEN_LOADED_BYTES * sum(stored.values()))
    assert again_plan.bytes < seen_plan.bytes
    # Told target views, the rank also plans what each target sees and their distances to the poses.
    aimed = svc_cameras(3, size=40, phase=0.8)
    body = RankRequest(cameras=candidates, samples=8, dropout_ratio=0.1, strategy="visibility_sigma_fvs",
                       targets=[c.to_frame() for c in aimed])
    told, _ = rank_job(record, body, service.settings, lambda name: name, service.ledger, store=service.store)
    assert told.renders.kept_bytes - again.kept_bytes == (sum(visibility_bytes(300, c) for c in aimed)
                                                          + density_bytes(3, len(candidates), 3))
    # A rank told one of those poses as captured reads that view alone, and plans that one only.
    body = RankRequest(cameras=candidates, samples=8, dropout_ratio=0.1, strategy="visibility_sigma",
                       captured=[captured[1].to_frame()])
    one, _ = rank_job(record, body, service.settings, lambda name: name, service.ledger, store=service.store)
    assert one.renders.kept_bytes - plain.kept_bytes == (sum(visibility_bytes(300, c) for c in views)
                                                         + COVERAGE_CAPTURE_BYTES
                                                         + SEEN_LOADED_BYTES * stored[camera_key(captured[1])])
    # Deleting the model deletes what was stored with it.
    cache_dir = service.store.cache(record).dir
    assert cache_dir.is_dir()
    with PHDClient(server.url) as phd:
        phd.delete_model(model_id)
    assert not cache_dir.exists()


def test_the_premultiplied_signal_plans_its_fourth_channel():
    pixels, per_mask = 200 * 200, RenderMemory(fixed=0, kept=0, per_mask=36 * 200 * 200)
    three, four = (plan_work(MODEL, pixels, 64, 0, 4 << 30, renders=per_mask, size_field="downscale",
                             kept_field="cameras", channels=c) for c in (3, 4))
    assert three.mask_batch == four.mask_batch == 64
    # A float64 accumulator channel (64 bytes a pixel), and per mask the render's and the engine's
    # float32 copy of the fourth channel (4 + 4 bytes a pixel).
    assert four.bytes - three.bytes == pixels * 64 + 64 * pixels * 8
    tight = 16 * 48 * pixels + pixels * 192 + model_bytes(20_000) + 64 * 300 * 5 + (1 << 20)
    assert plan(pixels, 64, tight, renders=per_mask).mask_batch > plan_work(
        MODEL, pixels, 64, 0, tight, renders=per_mask, size_field="downscale", kept_field="cameras",
        channels=4).mask_batch
