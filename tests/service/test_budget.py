"""The memory plan and the ledger that running work and upload parses share."""

from __future__ import annotations

import threading
import time

import pytest

from service.budget import MemoryLedger, plan_work
from service.errors import ServiceError


def test_plan_fits_the_budget_and_batches_masks_instead_of_growing_with_samples():
    model = [("3dgs", 300, 20_000)]
    small = plan_work(model, 800 * 800, 256, 0, 4 << 30, size_field="downscale", kept_field="cameras")
    assert 1 <= small.mask_batch < 64 and small.bytes <= 4 << 30
    same = plan_work(model, 800 * 800, 4096, 0, 4 << 30, size_field="downscale", kept_field="cameras")
    assert same == small                                  # N does not enter: the std is streamed
    roomy = plan_work(model, 100 * 100, 256, 0, 4 << 30, size_field="downscale", kept_field="cameras")
    assert roomy.mask_batch == 64
    assert plan_work(model, 100 * 100, 3, 0, 4 << 30, size_field="downscale", kept_field="cameras").mask_batch == 3
    with pytest.raises(ServiceError) as exc:
        plan_work(model, 800 * 800, 256, 0, 64 << 20, size_field="downscale", kept_field="cameras")
    assert (exc.value.status, exc.value.field) == (413, "downscale")
    with pytest.raises(ServiceError) as exc:
        plan_work(model, 100 * 100, 2, 10 << 30, 4 << 30, size_field="downscale", kept_field="training_cameras")
    assert exc.value.field == "training_cameras"


def test_ledger_makes_concurrent_work_wait_and_times_out():
    ledger = MemoryLedger(100)
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
