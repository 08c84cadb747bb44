"""The memory plan of a service rank, by strategy, under a budget: accepted or the 413's field.

    .venv/bin/python -m bench.bench_rank_plan [--size 800] [--budget-mib 1024] [--count 10]
    (cd DIR_WITH_AN_OLDER_phd_core_AND_service && python -m bench.bench_rank_plan ...)   # another version
    .venv/bin/python -m bench.bench_rank_plan --model lego.ply --measure     # and the requests' real peaks

Issue 34's "800 px lego rank at 1 GiB": `--model`, a lego model with its training cameras (what
`phd train --data lego_200` writes), or a stand-in: the 45,624-splat SH-3 donut of `tiled_model`
stored with lego_200's 100 training cameras (200x200) as its captured set; `--count` lego test
poses at `--size` px as candidates, N = 16. The plan is made as a worker makes it (the model loaded and
projected into every camera); for the default strategy twice when the code stores what the captured
views saw: before the first rank ("cold") and after it ("warm"). Prints one JSON line per plan.
"""

from __future__ import annotations

import argparse
import inspect
import json
import tempfile
from pathlib import Path

from bench._harness import LEGO, reset_peak, tiled_model, vm
from client import PHDClient
from phd_core.data import load_blender
from phd_core.renderers import load_model
from phd_core.renderers.gs3d import write_ply
from service.budget import MemoryLedger
from service.errors import ServiceError
from service.requests import stored_cameras
from service.schemas import RankRequest
from service.settings import Settings
from service.store import ModelStore
from service.work import model_loader, rank_job
from tests.support.fixtures import SvcProcess


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, default=800)
    p.add_argument("--budget-mib", type=int, default=1024)
    p.add_argument("--count", type=int, default=10)
    p.add_argument("--measure", action="store_true", help="also run each planned request in a real `phd serve` "
                   "under the budget: its peak RSS over the idle server's, against the plan")
    p.add_argument("--model", type=Path, help="a 3DGS PLY with its sidecar (e.g. what `phd train` wrote): its "
                   "splats and training cameras instead of the stand-in's")
    args = p.parse_args()
    train = load_blender(LEGO, "train", with_images=False).cameras
    if args.model is not None:
        opened = load_model(args.model)
        train = opened.training_cameras or []
    candidates = [c.resized(args.size, args.size) for c in load_blender(LEGO, "test", with_images=False,
                                                                          views=args.count).cameras]
    with tempfile.TemporaryDirectory() as tmp:
        store = ModelStore(Path(tmp))
        path = store.new_temp_path()
        model = tiled_model(1, 3) if args.model is None else opened.model
        write_ply(model, path)
        record = store.add(path, name="donut.ply" if args.model is None else args.model.name, kind="3dgs",
                           size_bytes=path.stat().st_size, sha256="0" * 64, num_units=model.num_splats, describe={},
                           training_frames=[c.to_frame() for c in train])
        budget = args.budget_mib << 20
        settings = Settings(data_dir=Path(tmp), memory_budget_bytes=budget)
        ledger = MemoryLedger(budget, 1, model_loader(store))
        renderer = model_loader(store)(record.id)
        stores = "store" in inspect.signature(rank_job).parameters      # this version keeps the coverage
        rows: list[tuple[dict, RankRequest]] = []
        plans = [("sigma_max", ""), ("visibility_sigma_fvs", "cold" if stores else "")]
        for strategy, label in plans + ([("visibility_sigma_fvs", "warm")] if stores else []):
            if label == "warm":         # what the first rank stores: the captured views' coverage
                from phd_core.uq.strategies.captured import CapturedStore, captured_seen

                captured_seen(renderer, stored_cameras(record), CapturedStore(store.cache(record)))
            body = RankRequest(cameras=[c.to_frame() for c in candidates], samples=16, dropout_ratio=0.5,
                               strategy=strategy)
            try:
                work, _ = rank_job(record, body, settings, lambda name: name, ledger,
                                   **({"store": store} if stores else {}))
                plan = work.plan({record.id: renderer}, lambda fraction: None)
                row = {"strategy": strategy, "store": label, "plan_mib": round(plan.bytes / 2**20),
                       "mask_batch": plan.mask_batch, "accepted": True}
            except ServiceError as refused:
                row = {"strategy": strategy, "store": label, "accepted": False, "field": refused.field,
                       "message": refused.message}
            print(json.dumps(row), flush=True)
            rows.append((row, body))
        if args.measure:
            measure(store.path(record), train, rows, budget, Path(tmp))


def measure(model: Path, train: list, rows: list[tuple[dict, RankRequest]], budget: int, root: Path) -> None:
    """Each accepted request, in order, in one fresh `phd serve` under `budget` (so the second
    default rank finds the coverage the first stored): its peak RSS over the idle server's."""
    server = SvcProcess(root / "served", start_timeout=300, PHD_MEMORY_BUDGET_BYTES=str(budget))
    try:
        with PHDClient(server.url, timeout=1800) as phd:
            model_id = phd.upload_model(model, cameras=train).id
            phd.rank(model_id, cameras=[c.to_frame() for c in train[:1]], samples=2, dropout_ratio=0.5)   # warm-up
            for row, body in rows:
                if not row["accepted"]:
                    continue
                idle = reset_peak(server.proc.pid)
                phd.rank(model_id, **body.model_dump(include={"cameras", "samples", "dropout_ratio", "strategy"}))
                peak = vm(server.proc.pid, "VmHWM") - idle
                print(json.dumps({**row, "peak_over_idle_mib": round(peak / 2**20),
                                  "within_plan": peak <= row["plan_mib"] << 20, "within_budget": peak <= budget}),
                      flush=True)
    finally:
        server.kill()


if __name__ == "__main__":
    main()
