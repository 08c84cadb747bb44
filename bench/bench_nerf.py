"""NeRF on the CPU: quality, training time and rendering costs of the four variants.

Trains `pe`, `pe+freenerf`, `spe+freenerf` and `hash` on the lego scene (16 evenly spaced
training views at 100x100 by default), evaluates PSNR/SSIM on 25 evenly spaced test views,
and times, in the same process and on the same view:
- one full render with and without the occupancy grid (and how much the image changes);
- a batch of N = 16 keep-masks in one call against the same 16 masks rendered one by one.

Writes bench/results/nerf.json and the table between the bench markers of docs/nerf.md.

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python -m bench.bench_nerf     # the full run (~25 min)
    .venv/bin/python -m bench.bench_nerf --iterations 200 --variants pe --test-views 5 --no-doc
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import torch

from bench._harness import DOCS, LEGO, RESULTS, ROOT, command, load_average, machine, timed, write_result
from phd_core.data import load_blender
from phd_core.eval import psnr, ssim
from phd_core.train.nerf import DEFAULT_ITERATIONS, train_nerf

VARIANTS = {
    "pe": dict(encoding="pe", freenerf=False),
    "pe+freenerf": dict(encoding="pe", freenerf=True),
    "spe+freenerf": dict(encoding="spe", freenerf=True),
    "hash": dict(encoding="hash", freenerf=False),
}
DOC_START, DOC_END = "<!-- bench:nerf:start -->", "<!-- bench:nerf:end -->"


def run_variant(name: str, args, test) -> dict:
    out = RESULTS / f"nerf_{name.replace('+', '_')}.nerf"
    training = timed(lambda: train_nerf(args.data, views=args.views, downscale=args.downscale,
                                        iterations=args.iterations, seed=args.seed, out=out,
                                        progress=args.progress, **VARIANTS[name]))
    renderer, train_s = training.result, training.seconds
    preds = [renderer.render(camera)[0] for camera in test.cameras]
    view_psnr = [psnr(p, t) for p, t in zip(preds, test.images)]
    view_ssim = ssim(torch.stack(preds), torch.stack(test.images)).tolist()
    camera = test.cameras[0]

    with_grid = timed(lambda: renderer.render(camera))
    renderer.use_grid = False
    without_grid = timed(lambda: renderer.render(camera))
    renderer.use_grid = True
    diff = (with_grid.result - without_grid.result).abs()
    grid_s, nogrid_s = with_grid.seconds, without_grid.seconds

    result = {
        "variant": name, **VARIANTS[name],
        "train_seconds": round(train_s, 1),
        "psnr": round(sum(view_psnr) / len(view_psnr), 2),
        "ssim": round(sum(view_ssim) / len(view_ssim), 4),
        "occupied_fraction": round(renderer.model.grid.fraction, 4),
        "render_seconds_grid": round(grid_s, 2),
        "render_seconds_no_grid": round(nogrid_s, 2),
        "grid_speedup": round(nogrid_s / grid_s, 2),
        "grid_vs_no_grid_max_abs": float(diff.max()),
        "grid_vs_no_grid_mean_abs": float(diff.mean()),
        "checkpoint": str(out.relative_to(ROOT)),
        "checkpoint_bytes": out.stat().st_size,
    }
    if args.masks:
        gen = torch.Generator().manual_seed(0)
        keep = torch.rand(args.masks, renderer.num_units, generator=gen) >= args.ratio
        batch = timed(lambda: renderer.render(camera, keep))
        singles = timed(lambda: torch.cat([renderer.render(camera, keep[i:i + 1]) for i in range(args.masks)]))
        batch_s, single_s = batch.seconds, singles.seconds
        result.update({
            "masks": args.masks, "mask_ratio": args.ratio,
            "mask_batch_seconds": round(batch_s, 2), "mask_separate_seconds": round(single_s, 2),
            "mask_batch_speedup": round(single_s / batch_s, 2),
            "mask_batch_max_abs_diff": float((batch.result - singles.result).abs().max()),
        })
    print(json.dumps(result), flush=True)
    return result


def markdown(report: dict) -> str:
    s = report["settings"]
    lines = [
        f"lego_200, {s['views']} training views at {s['width']}x{s['height']}, {s['iterations']} iterations, "
        f"seed {s['seed']}; test: {s['test_views']} evenly spaced test views. Machine: {report['machine']['cpus']} "
        f"CPUs shared with other jobs (load average {report['machine']['load_before']} before, "
        f"{report['machine']['load_after']} after), torch {report['machine']['torch']}, "
        f"{report['machine']['threads']} threads. Command: `{report['command']}`.",
        "",
        "| variant | PSNR | SSIM | train s | occupied | render s (grid) | render s (no grid) | grid speed-up "
        "| max abs diff | N=16 batch s | 16 separate s | batch speed-up |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["results"]:
        lines.append(
            f"| {r['variant']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {r['train_seconds']:.0f} | "
            f"{r['occupied_fraction']:.3f} | {r['render_seconds_grid']:.2f} | {r['render_seconds_no_grid']:.2f} | "
            f"{r['grid_speedup']:.1f}x | {r['grid_vs_no_grid_max_abs']:.4f} | "
            f"{r.get('mask_batch_seconds', float('nan')):.2f} | {r.get('mask_separate_seconds', float('nan')):.2f} | "
            f"{r.get('mask_batch_speedup', float('nan')):.2f}x |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=str(LEGO))
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--downscale", type=float, default=2)
    parser.add_argument("--test-views", type=int, default=25)
    parser.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--masks", type=int, default=16, help="keep-masks of the batch timing (0: skip)")
    parser.add_argument("--ratio", type=float, default=0.1, help="dropout ratio of the timed masks")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=str(RESULTS / "nerf.json"))
    parser.add_argument("--doc", default=str(DOCS / "nerf.md"))
    parser.add_argument("--no-doc", action="store_true", help="do not rewrite the table in docs/nerf.md")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args()
    names = args.variants.split(",")
    for name in names:
        if name not in VARIANTS:
            parser.error(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")

    RESULTS.mkdir(parents=True, exist_ok=True)
    test = load_blender(args.data, "test", downscale=args.downscale, views=args.test_views)
    load_before = load_average()
    results = [run_variant(name, args, test) for name in names]
    report = {
        "command": command(),
        "machine": machine(load_before=load_before, load_after=load_average()),
        "settings": {"views": args.views, "downscale": args.downscale, "width": test.cameras[0].width,
                     "height": test.cameras[0].height, "test_views": args.test_views,
                     "iterations": args.iterations, "seed": args.seed},
        "results": results,
    }
    write_result(Path(args.json), report)
    print(markdown(report))
    if not args.no_doc:
        doc = Path(args.doc)
        text = doc.read_text()
        block = f"{DOC_START}\n{markdown(report)}\n{DOC_END}"
        text = re.sub(re.escape(DOC_START) + ".*?" + re.escape(DOC_END), lambda _: block, text, flags=re.S)
        doc.write_text(text)


if __name__ == "__main__":
    main()
