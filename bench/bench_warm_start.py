"""Warm start against cold start at the same step count (issue 49): a capture trained on k views
gets more photos; S steps continuing from the k-view model (`fit(init=...)`) against S steps from
the seeded splats. Test PSNR over the scene's test split (evenly spaced views) and wall seconds.

    cold        the seeded splats (SfM points or the alpha hull), the whole schedule
    warm        the library's warm start: the k-view model, densification resumed, no opacity reset
    warm-slow   the same with the position rate at a tenth (`TrainConfig.lr_means`): a shorter warm-up
    warm-reset  the warm start with the cold run's opacity resets (`splats.opacity_reset_interval`
                made to ignore the warm start): what skipping them is worth

The k views are evenly spaced among the n views of the second round, which add n - k new ones.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_warm_start        # ~30 min on a loaded 2-core machine
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_warm_start --scenes cup_colmap --steps 600 \
        --variants cold warm --out bench/results/warm_start_long.json --section warm-start-long

Writes bench/results/warm_start.json (or --out) and the table between the `bench:warm-start`
markers (or --section's) of docs/gaussians.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from bench._harness import (
    DATA,
    DOCS,
    RESULTS,
    ROOT,
    command,
    load_at_start,
    load_average,
    machine,
    machine_text,
    pin_determinism,
    write_doc,
    write_result,
)
from phd_core.data import Dataset, load_dataset
from phd_core.eval import psnr
from phd_core.renderers.gs3d import GaussianModel, rasterize
from phd_core.train import splats
from phd_core.train.gs3d import TrainConfig, fit, training_background

SCENES = {"cup_colmap": (DATA / "cup_colmap", 8.0), "donut_200": (DATA / "donut_200", 2.0)}   # ~100 px wide
VARIANTS = ("cold", "warm", "warm-slow", "warm-reset")


def evenly(count: int, among: int) -> list[int]:
    """`count` evenly spaced indices of range(among)."""
    return sorted({round(i * among / count) for i in range(count)})


def test_psnr(model: GaussianModel, train: Dataset, test: Dataset) -> float:
    """The mean PSNR of the test views rendered over the training background."""
    background = torch.tensor(training_background(train))
    assert test.images is not None          # loaded with them
    with torch.no_grad():
        scores = [psnr(rasterize(model, cam, background).rgb[0].clamp(0, 1), image)
                  for cam, image in zip(test.cameras, test.images)]
    return sum(scores) / len(scores)


def run_variant(variant: str, data: Dataset, steps: int, seed: int,
                first: GaussianModel) -> tuple[GaussianModel, float]:
    """One second-round run of `variant` (module docstring) and its wall seconds."""
    config = TrainConfig(iterations=steps, seed=seed,
                         lr_means=TrainConfig.lr_means / 10 if variant == "warm-slow" else TrainConfig.lr_means)
    interval = splats.opacity_reset_interval

    def as_cold(config: TrainConfig, *, warm: bool) -> int:
        return interval(config, warm=False)

    if variant == "warm-reset":
        splats.opacity_reset_interval = as_cold
    try:
        started = time.perf_counter()
        model, _ = fit(data, config, progress=False, init=None if variant == "cold" else first)
        return model, time.perf_counter() - started
    finally:
        splats.opacity_reset_interval = interval


def scene_rows(name: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    path, downscale = SCENES[name]
    available = len(load_dataset(path, "train", with_images=False).cameras)
    views = [round(i * available / args.views) for i in range(args.views)]             # the second round's
    earlier = [views[i] for i in evenly(args.earlier, args.views)]                    # the first round's
    second = load_dataset(path, "train", downscale=downscale, views=views)
    first_data = load_dataset(path, "train", downscale=downscale, views=earlier)
    test = load_dataset(path, "test", downscale=downscale, views=args.test_views)
    rows = []
    for seed in args.seeds:
        started = time.perf_counter()
        first, _ = fit(first_data, TrainConfig(iterations=args.first_steps, seed=seed), progress=False)
        first_seconds = time.perf_counter() - started
        for steps in args.steps:
            for variant in args.variants:
                model, seconds = run_variant(variant, second, steps, seed, first)
                rows.append({"scene": name, "seed": seed, "steps": steps, "variant": variant,
                             "test_psnr": round(test_psnr(model, second, test), 3), "seconds": round(seconds, 1),
                             "splats": model.num_splats, "first_psnr": round(test_psnr(first, first_data, test), 3),
                             "first_seconds": round(first_seconds, 1), "first_splats": first.num_splats,
                             "size": f"{second.cameras[0].width}x{second.cameras[0].height}",
                             "views": views, "earlier": earlier, "test_views": len(test.cameras)})
                print(rows[-1]["scene"], seed, steps, variant, rows[-1]["test_psnr"], rows[-1]["seconds"], flush=True)
    return rows


def table(record: dict[str, Any]) -> str:
    """Mean test PSNR and seconds over the seeds, per scene, steps and variant, with the warm - cold gain."""
    rows = record["rows"]
    lines = [f"Command: `OMP_NUM_THREADS=1 nice -n 10 {record['command']}` (one thread, deterministic kernels; "
             f"{machine_text(record['machine'])}, 1-minute load {load_at_start(record['machine'])[0]} at the start, "
             f"{record['load_average_end'][0]} at the end). First round: {record['first_steps']} steps on "
             f"{record['earlier']} views; "
             f"second round: S steps on {record['views']} views (the first round's plus "
             f"{record['views'] - record['earlier']} new ones), from the first round's model (warm) or from "
             f"scratch (cold). Test PSNR: the mean over the test split's evenly spaced views; mean over seeds "
             f"{record['seeds']} (each seed its own first round); per-seed values in {record['out']}.",
             "",
             "| scene | size | first round PSNR | S | variant | test PSNR (dB) | vs cold (dB) | seconds | splats |",
             "|---|---|---|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for steps in dict.fromkeys(r["steps"] for r in rows):
            group = [r for r in rows if r["scene"] == scene and r["steps"] == steps]
            mean = {v: {k: statistics.fmean(r[k] for r in group if r["variant"] == v)
                        for k in ("test_psnr", "seconds", "splats", "first_psnr")}
                    for v in dict.fromkeys(r["variant"] for r in group)}
            for variant, m in mean.items():
                gain = f"{m['test_psnr'] - mean['cold']['test_psnr']:+.2f}" if "cold" in mean else ""
                lines.append(f"| {scene} | {group[0]['size']} | {m['first_psnr']:.2f} | {steps} | {variant} | "
                             f"{m['test_psnr']:.2f} | {gain} | {m['seconds']:.1f} | {m['splats']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=sorted(SCENES))
    p.add_argument("--earlier", type=int, default=8, help="views of the first round (default 8)")
    p.add_argument("--views", type=int, default=12, help="views of the second round (default 12)")
    p.add_argument("--first-steps", type=int, default=200, help="steps of the first round (default 200)")
    p.add_argument("--steps", type=int, nargs="+", default=[100, 200], help="steps S of the second round")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--test-views", type=int, default=10, help="evenly spaced test views scored (default 10)")
    p.add_argument("--out", type=Path, default=RESULTS / "warm_start.json")
    p.add_argument("--section", default="warm-start", help="docs/gaussians.md's bench section for the table")
    args = p.parse_args()
    if not 0 < args.earlier < args.views:
        p.error("--earlier must be positive and below --views")
    pin_determinism()
    record: dict[str, Any] = {"command": command(), "machine": machine(), "earlier": args.earlier,
                              "views": args.views, "first_steps": args.first_steps, "seeds": args.seeds,
                              "out": os.path.relpath(args.out.resolve(), ROOT), "rows": []}
    for scene in args.scenes:
        record["rows"] += scene_rows(scene, args)
    record["load_average_end"] = load_average()
    write_result(args.out, record)
    write_doc(DOCS / "gaussians.md", table(record), section=args.section)


if __name__ == "__main__":
    main()
