"""The paper's active-learning trends (Section 5.2) on 3DGS models trained on more and more views.

For each model (a `phd train` .ply with its training cameras): r_drop by Algorithm 1 on its
own training poses (engine defaults), and again on a finer step by bisection (the coarse
grid can give every model the same r_drop); sigma-max-bar over held-out test views at the
default r_drop (the paper's reading) and at one fixed ratio (the same sub-model size for
every model); the held-out RMSE for context. Across models:

    rho_U = Spearman(sigma-max-bar, number of training views)   expected negative
    rho_R = Spearman(r_drop, number of training views)          expected positive

Writes bench/results/trend.json and the table between the `bench:trend` markers of
docs/uq.md.

    for v in 4 8 16 32 100; do phd train --data ../shared/data/lego_200 --views $v --out runs/lego$v/model.ply; done
    .venv/bin/python -m bench.bench_trend --models runs/lego{4,8,16,32,100}/model.ply --threads 1
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from bench._harness import (
    DOCS,
    LEGO,
    RESULTS,
    fmt,
    load_test_at_size,
    machine,
    machine_text,
    timed,
    write_doc,
    write_result,
)
from phd_core import uq as phd
from phd_core.eval import rmse
from phd_core.eval import uq as uqm
from phd_core.renderers import load_model

DATA = LEGO
DOC = DOCS / "uq.md"
RESULT = RESULTS / "trend.json"


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", type=Path, nargs="+", required=True, help="trained 3DGS .ply files")
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--test-views", type=int, default=25, help="evenly spaced held-out test views")
    p.add_argument("--resolution", type=int, default=100, help="held-out image size (square)")
    p.add_argument("--samples", type=int, default=phd.DEFAULT_SAMPLES)
    p.add_argument("--fixed-ratio", type=float, default=0.3, help="the common dropout ratio of the second column")
    p.add_argument("--fine-step", type=float, default=0.01, help="step of the second, bisection calibration")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--out", type=Path, default=RESULT)
    p.add_argument("--doc", type=Path, default=DOC)
    return p.parse_args()


def measure(path: Path, test, args: argparse.Namespace) -> dict:
    """r_drop, sigma-max-bar (own r_drop and fixed ratio) and held-out RMSE of one model."""
    renderer = load_model(path)
    if not renderer.training_cameras:
        raise SystemExit(f"{path}: no training cameras stored with the model (train it with `phd train`)")
    row = {"model": str(path), "views": len(renderer.training_cameras), "units": renderer.num_units}
    try:
        run = timed(lambda: phd.calibrate(renderer, renderer.training_cameras))
        calibration, row["calibration_seconds"] = run.result, run.seconds
        row["r_drop"] = calibration.r_drop
    except phd.CalibrationError:
        row["r_drop"] = 0.0
    try:
        row["r_drop_fine"] = phd.calibrate(renderer, renderer.training_cameras, step=args.fine_step,
                                           method="bisection").r_drop
    except phd.CalibrationError:
        row["r_drop_fine"] = 0.0
    for key, ratio in (("sigma_max_bar", row["r_drop"]), ("sigma_max_bar_fixed", args.fixed_ratio)):
        views = phd.uncertainty(renderer, test.cameras, ratio=ratio, samples=args.samples)
        row[key] = phd.sigma_max_bar(views)
    renders = torch.cat([renderer.render(c) for c in test.cameras])
    row["rmse"] = float(rmse(renders, torch.stack(test.images)))
    print(f"{path}: {row['views']} views, r_drop {row['r_drop']} (fine {row['r_drop_fine']}), "
          f"sigma-max-bar {row['sigma_max_bar']:.4f} (at {args.fixed_ratio}: {row['sigma_max_bar_fixed']:.4f}), "
          f"RMSE {row['rmse']:.4f}", flush=True)
    return row


def markdown(results: dict) -> str:
    t = results["trends"]
    lines = [f"Measured {results['date']} on {machine_text(results['machine'])}; torch {results['torch']} with "
             f"{results['threads']} threads; command: `{results['command']}`. "
             f"sigma-max-bar over {results['test_views']} test views at {results['resolution']} px, "
             f"N = {results['samples']}; r_drop by the engine defaults on each model's training poses, and by "
             f"bisection at step {results['fine_step']}.", "",
             f"| training views | splats | r_drop | r_drop (step {results['fine_step']}) | sigma-max-bar at r_drop | "
             f"sigma-max-bar at r = {results['fixed_ratio']} | held-out RMSE |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['views']} | {r['units']} | {r['r_drop']} | {r['r_drop_fine']} | {fmt(r['sigma_max_bar'], 4)} | "
              f"{fmt(r['sigma_max_bar_fixed'], 4)} | {fmt(r['rmse'], 4)} |" for r in results["rows"]]
    lines += ["", f"rho_U (sigma-max-bar at r_drop vs views) = {fmt(t['rho_u'])}; rho_R (r_drop vs views) = "
              f"{fmt(t['rho_r'])} (undefined when every model has the same r_drop), at step "
              f"{results['fine_step']} {fmt(t['rho_r_fine'])}; at the fixed ratio rho_U = {fmt(t['rho_u_fixed'])}.",
              ""]
    return "\n".join(lines)


def main() -> None:
    args = parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    test = load_test_at_size(args.data, args.test_views, args.resolution)
    rows = sorted((measure(path, test, args) for path in args.models), key=lambda r: r["views"])
    views = [r["views"] for r in rows]
    trends = uqm.trend_correlations(views, [r["sigma_max_bar"] for r in rows], [r["r_drop"] for r in rows])
    trends["rho_u_fixed"] = uqm.spearman([r["sigma_max_bar_fixed"] for r in rows], views)
    trends["rho_r_fine"] = uqm.spearman([r["r_drop_fine"] for r in rows], views)
    results = {"date": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
               "machine": machine(), "torch": torch.__version__,
               "threads": torch.get_num_threads(), "test_views": len(test.cameras), "resolution": args.resolution,
               "samples": args.samples, "fixed_ratio": args.fixed_ratio, "fine_step": args.fine_step,
               "rows": rows, "trends": trends}
    write_result(args.out, results)
    write_doc(args.doc, markdown(results), section="trend")
    print(markdown(results))


if __name__ == "__main__":
    main()
