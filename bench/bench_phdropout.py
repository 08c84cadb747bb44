"""The PH-Dropout speed/accuracy trade on a trained 3DGS model (lego_200, 16 training views).

Measures, in one run on this machine:
1. calibration: time, r_drop and evaluated ratios of the linear scan and of bisection for
   each step dr (same nested masks, default epsilon and calibration samples);
2. the reference ranking of the candidates (test-split views): sigma_max at
   N = --reference-samples and the largest resolution, with its own seed, and its
   agreement with a re-run under other masks (the ceiling for every grid cell);
3. the grid N x resolution: time per candidate view, stability of sigma_max over --seeds
   seeds (coefficient of variation per candidate, median and max over candidates) and the
   agreement of each seed's ranking with the reference (Kendall tau-b, top-5 overlap);
4. batched keep-masks against N separate renders of one mask (speed-up ratio);
5. evidence on --heldout held-out views with ground truth: Spearman between per-view
   sigma_max and per-view RMSE, per-image pixel-level Spearman/Pearson and AUSE.

Recommends the cheapest (time per view) grid cell whose mean Kendall tau >= 0.9, or, when
none does, >= 0.9 x the reference's agreement with its re-run.
Writes bench/results/uq.json after every section (a cut run keeps its numbers),
the tables between the bench markers of docs/uq.md and two SVG plots in docs/.

    .venv/bin/python bench/bench_phdropout.py --model runs/lego16/model.ply --data ../shared/data/lego_200
    .venv/bin/python bench/bench_phdropout.py --quick      # smoke run on a random model

Without --model (or with --random-splats K) a seeded random splat cloud stands in for the
trained model, with lego's training cameras: numbers then only validate the script.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from phd_core import uq as phd  # noqa: E402
from phd_core.eval import uq as uqm  # noqa: E402
from phd_core.data import load_dataset  # noqa: E402
from phd_core.io import write_bytes_atomic, write_json_atomic  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "lego_200"
RESULTS = ROOT / "bench" / "results" / "uq.json"
DOC = ROOT / "docs" / "uq.md"
REFERENCE_SEED = 1000      # the reference ranking's masks differ from every tested seed
TAU_TARGET = 0.9
TOP_K = 5


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", type=Path, help="trained 3DGS .ply (with its training-camera sidecar)")
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--random-splats", type=int, default=None, help="use a random model with this many splats")
    p.add_argument("--train-views", type=int, default=16, help="training views when the model has no cameras")
    p.add_argument("--candidates", type=int, default=30, help="test-split views to rank")
    p.add_argument("--samples", default="4,8,16,32,64,128", help="N grid")
    p.add_argument("--resolutions", default="50,100,200", help="image sizes (square) of the grid")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--timing-views", type=int, default=2, help="candidates timed per grid cell")
    p.add_argument("--reference-samples", type=int, default=256)
    p.add_argument("--steps", default="0.05,0.02,0.01", help="calibration steps dr")
    p.add_argument("--calibration-resolution", type=int, default=100)
    p.add_argument("--calibration-samples", default="2,4,8", help="sample counts compared at the first step")
    p.add_argument("--calibration-budget-minutes", type=float, default=None,
                   help="skip calibration runs that would start after this many minutes")
    p.add_argument("--speedup-samples", default="16,64")
    p.add_argument("--speedup-views", type=int, default=2)
    p.add_argument("--heldout", type=int, default=100)
    p.add_argument("--evidence-resolution", type=int, default=100)
    p.add_argument("--budget-minutes", type=float, default=None,
                   help="skip the remaining grid cells once this much time has passed")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    p.add_argument("--quick", action="store_true", help="tiny grid on a small random model (smoke test)")
    p.add_argument("--out", type=Path, default=None, help=f"results JSON (default {RESULTS.relative_to(ROOT)}, "
                   "with --quick bench/results/phdropout_quick.json)")
    p.add_argument("--doc", type=Path, default=None,
                   help=f"markdown file whose bench section is rewritten (default {DOC.relative_to(ROOT)}; "
                        "--quick writes no document unless given)")
    args = p.parse_args()
    args.out = args.out or (RESULTS.with_name("phdropout_quick.json") if args.quick else RESULTS)
    args.doc = args.doc or (None if args.quick else DOC)
    if args.quick:
        args.random_splats = args.random_splats or 2000
        args.candidates, args.samples, args.resolutions, args.seeds = 6, "4,8", "25,50", 2
        args.reference_samples, args.steps, args.calibration_resolution = 16, "0.1,0.05", 25
        args.calibration_samples = "4"
        args.speedup_samples, args.speedup_views, args.heldout, args.evidence_resolution = "8", 1, 6, 25
        args.timing_views = 1
        args.train_views = 4
    return args


def ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def at_size(cameras: list, size: int) -> list:
    return [c.resized(size, round(size * c.height / c.width)) for c in cameras]


def load_renderer(args: argparse.Namespace):
    """(renderer, description) from --model, else a seeded random splat cloud."""
    if args.random_splats is None and args.model is not None:
        from phd_core.renderers import load_model, load_model_bytes

        renderer = load_model(args.model)
        if not renderer.training_cameras:
            train = load_dataset(args.data, "train", views=args.train_views, with_images=False)
            renderer = load_model_bytes(args.model.read_bytes(), args.model.name, training_cameras=train.cameras)
        return renderer, f"{args.model} ({renderer.num_units} splats)"
    from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer

    count = args.random_splats or 20000
    g = torch.Generator().manual_seed(0)
    model = GaussianModel(
        means=(torch.rand(count, 3, generator=g) - 0.5) * 1.6,
        log_scales=torch.log(0.01 + 0.03 * torch.rand(count, 3, generator=g)),
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.rand(count, generator=g) * 4 - 1,
        sh=torch.randn(count, 1, 3, generator=g) * 0.5)
    train = load_dataset(args.data, "train", views=args.train_views, with_images=False)
    return GaussianRenderer(model, training_cameras=train.cameras), f"random splat cloud ({count} splats)"


def timed(fn, *a, **kw) -> tuple[Any, float]:
    start = time.perf_counter()
    out = fn(*a, **kw)
    return out, time.perf_counter() - start


def save(results: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, results)


# ---------------------------------------------------------------------------------------- sections

def bench_calibration(renderer, args, results, started: float) -> float:
    """Linear scan vs bisection for each step; cheapest runs first, the rest cut by the budget.

    Also r_drop of bisection at the first step for several calibration sample counts.
    Returns r_drop of the linear scan at the first step (the ratio used by the later sections).
    """
    cameras = at_size(renderer.training_cameras, args.calibration_resolution)
    steps = floats(args.steps)
    runs = ([(steps[0], "linear", phd.DEFAULT_CALIBRATION_SAMPLES)]
            + [(step, "bisection", phd.DEFAULT_CALIBRATION_SAMPLES) for step in steps]
            + [(steps[0], "bisection", n) for n in ints(args.calibration_samples)
               if n != phd.DEFAULT_CALIBRATION_SAMPLES]
            + [(step, "linear", phd.DEFAULT_CALIBRATION_SAMPLES) for step in steps[1:]])
    rows = []
    for step, method, samples in runs:
        row: dict[str, Any] = {"step": step, "method": method, "samples": samples}
        budget = args.calibration_budget_minutes
        # The first run always runs: its r_drop is the ratio of the later sections.
        if rows and budget is not None and time.perf_counter() - started > 60 * budget:
            rows.append({**row, "cut": True})
            continue
        try:
            result, seconds = timed(phd.calibrate, renderer, cameras, step=step, method=method, samples=samples)
            row.update(seconds=seconds, r_drop=result.r_drop, evaluated=len(result.ratios), capped=result.capped,
                       ratios=result.ratios, errors=result.errors, cut=False)
        except phd.CalibrationError as exc:
            row.update(seconds=None, r_drop=0.0, evaluated=len(exc.ratios), error=str(exc), cut=False)
        rows.append(row)
        print(f"calibration dr={step} {method} N={samples}: r_drop {row['r_drop']} "
              f"({row['evaluated']} ratios, {row['seconds'] or 0:.1f} s)", flush=True)
        results["calibration"] = {"resolution": args.calibration_resolution, "views": len(cameras),
                                  "epsilon": phd.DEFAULT_EPSILON, "rows": rows}
        save(results, args.out)
    return rows[0]["r_drop"]


def prefix_sigma_max(renderer, camera, keep, grid: list[int]) -> dict[int, float]:
    """sigma_max of one view for every N in `grid` from ONE render of max(grid) masks.

    The masks of `samples=N` are the first N rows of any larger draw with the same seed
    (checked in main), so each N's value is exactly what `view_uncertainty` returns.
    """
    images = torch.cat([renderer.render(camera, chunk) for chunk in keep.split(phd.MAX_MASKS_PER_RENDER)])
    return {n: float(phd.sample_std(images[:n])[0].max()) for n in grid}


def bench_grid(renderer, candidates, ratio, args, results, started: float) -> None:
    sizes, grid = ints(args.resolutions), ints(args.samples)
    # The reference at every size: the largest one is THE reference (the ranking a user wants);
    # the others separate the effect of the resolution from that of the sample count.
    references = {}
    for size in sorted(sizes, reverse=True):
        views, seconds = timed(phd.uncertainty, renderer, at_size(candidates, size), ratio=ratio,
                               samples=args.reference_samples, seed=REFERENCE_SEED)
        references[size] = {"samples": args.reference_samples, "resolution": size, "seed": REFERENCE_SEED,
                            "seconds_per_view": seconds / len(candidates),
                            "sigma_max": [v.sigma_max for v in views]}
        print(f"reference N={args.reference_samples} at {size}: {seconds / len(candidates):.2f} s/view", flush=True)
    ref_scores = references[max(sizes)]["sigma_max"]
    # The reference is an estimate too: a second run with other masks shows how well it
    # reproduces itself, which bounds the agreement any grid cell can reach against it.
    twin = phd.uncertainty(renderer, at_size(candidates, max(sizes)), ratio=ratio,
                           samples=args.reference_samples, seed=REFERENCE_SEED + 1)
    twin_scores = [v.sigma_max for v in twin]
    self_agreement = {"seed": REFERENCE_SEED + 1, "kendall_tau": uqm.kendall_tau_b(twin_scores, ref_scores),
                      "top5_overlap": uqm.top_k_overlap(twin_scores, ref_scores, min(TOP_K, len(candidates))),
                      "sigma_max": twin_scores}
    print(f"reference self-agreement: tau {fmt(self_agreement['kendall_tau'])}, "
          f"top5 {self_agreement['top5_overlap']:.2f}", flush=True)
    results["reference"] = {**references[max(sizes)], "order": uqm.order_by_score(ref_scores),
                            "self_agreement": self_agreement}
    results["references_by_resolution"] = [references[size] for size in sizes]
    save(results, args.out)
    cells = []
    for size in sizes:
        if args.budget_minutes is not None and time.perf_counter() - started > 60 * args.budget_minutes:
            cells += [{"resolution": size, "samples": n, "cut": True} for n in grid]
            continue
        cams = at_size(candidates, size)
        # Time: direct API calls on the first timing views, one per N.
        seconds_per_view, direct = {}, {}
        for n in grid:
            views, seconds = timed(phd.uncertainty, renderer, cams[:args.timing_views], ratio=ratio, samples=n, seed=0)
            seconds_per_view[n] = seconds / len(views)
            direct[n] = views[0].sigma_max
        # Accuracy: one render of max(grid) masks per (seed, candidate) serves every N.
        scores = {n: [[0.0] * len(cams) for _ in range(args.seeds)] for n in grid}   # [N][seed][candidate]
        for seed in range(args.seeds):
            keep = phd.keep_masks(phd.dropout_uniforms(renderer.num_units, max(grid), seed), ratio)
            for j, cam in enumerate(cams):
                for n, value in prefix_sigma_max(renderer, cam, keep, grid).items():
                    scores[n][seed][j] = value
        for n in grid:
            assert abs(scores[n][0][0] - direct[n]) < 1e-12, "prefix renders must equal the API's numbers"
            per_seed = scores[n]
            cv = []
            for j in range(len(cams)):
                values = [s[j] for s in per_seed]
                mean = statistics.fmean(values)
                cv.append(statistics.stdev(values) / mean if mean > 0 and len(values) > 1 else 0.0)
            taus = [uqm.kendall_tau_b(s, ref_scores) for s in per_seed]
            same = [uqm.kendall_tau_b(s, references[size]["sigma_max"]) for s in per_seed]
            overlaps = [uqm.top_k_overlap(s, ref_scores, min(TOP_K, len(cams))) for s in per_seed]
            cell = {"resolution": size, "samples": n, "seconds_per_view": seconds_per_view[n],
                    "sigma_max_cv_median": statistics.median(cv), "sigma_max_cv_max": max(cv),
                    "kendall_tau_mean": uqm.mean_defined(taus),
                    "kendall_tau_min": min((t for t in taus if t is not None), default=None),
                    "top5_overlap_mean": statistics.fmean(overlaps),
                    "kendall_tau_same_resolution_mean": uqm.mean_defined(same), "cut": False}
            cells.append(cell)
            print(f"grid {size}px N={n}: {cell['seconds_per_view']:.3f} s/view, cv {cell['sigma_max_cv_median']:.3f}, "
                  f"tau {fmt(cell['kendall_tau_mean'])} (same px {fmt(cell['kendall_tau_same_resolution_mean'])}), "
                  f"top5 {cell['top5_overlap_mean']:.2f}", flush=True)
        results["grid"] = cells
        save(results, args.out)
    results["grid"] = cells
    results["recommendation"] = recommend(cells, self_agreement["kendall_tau"])


def recommend(cells: list[dict], reference_tau: float | None) -> dict:
    """The cheapest cell with mean Kendall tau >= TAU_TARGET (the issue's rule).

    When no cell reaches it, the same rule relative to what the reference can reach: the
    cheapest cell with tau >= TAU_TARGET * (tau of the reference against its own re-run),
    provided the reference reproduces itself at all (positive tau).
    """
    done = [c for c in cells if not c["cut"] and c["kendall_tau_mean"] is not None]

    def cheapest(target: float) -> dict | None:
        good = [c for c in done if c["kendall_tau_mean"] >= target]
        return min(good, key=lambda c: c["seconds_per_view"]) if good else None

    rule = f"cheapest cell with mean Kendall tau >= {TAU_TARGET}"
    best = cheapest(TAU_TARGET)
    if best is not None or reference_tau is None or reference_tau <= 0:
        return {"rule": rule, "cell": best}
    relative = TAU_TARGET * reference_tau
    return {"rule": f"{rule}: none; relative rule: tau >= {TAU_TARGET} x reference self-agreement "
                    f"({reference_tau:.3f}) = {relative:.3f}",
            "cell": cheapest(relative), "relative_target": relative}


def bench_speedup(renderer, candidates, ratio, args, results) -> None:
    cams = at_size(candidates[:args.speedup_views], max(ints(args.resolutions)))
    rows = []
    for n in ints(args.speedup_samples):
        keep = phd.keep_masks(phd.dropout_uniforms(renderer.num_units, n, 0), ratio)
        batched = separate = 0.0
        for cam in cams:
            _, seconds = timed(phd.view_uncertainty, renderer, cam, ratio=ratio, samples=n, seed=0)
            batched += seconds
            start = time.perf_counter()
            images = torch.cat([renderer.render(cam, k[None]) for k in keep])
            phd.sample_std(images)
            separate += time.perf_counter() - start
        rows.append({"samples": n, "views": len(cams), "resolution": cams[0].width,
                     "batched_seconds_per_view": batched / len(cams),
                     "separate_seconds_per_view": separate / len(cams), "speedup": separate / batched})
        print(f"batched vs separate N={n}: x{separate / batched:.2f}", flush=True)
    results["speedup"] = rows


def angle_to_nearest(cameras: list, training: list) -> list[float]:
    """Per camera, the angle in degrees between its viewing axis and the closest training one."""
    def axis(c) -> torch.Tensor:          # OpenGL cameras look down their -z axis
        return -c.c2w[:3, 2] / c.c2w[:3, 2].norm()

    axes = torch.stack([axis(c) for c in training])                          # [T, 3]
    cosines = torch.stack([axes @ axis(c) for c in cameras]).amax(1).clamp(-1, 1)
    return torch.rad2deg(torch.acos(cosines)).tolist()


def load_test_at_size(data: Path, views: int, size: int):
    """`views` evenly spaced test-split frames with their images, downscaled to `size` pixels wide."""
    width = load_dataset(data, "test", views=1, with_images=False).cameras[0].width
    return load_dataset(data, "test", views=views, downscale=width / size)


def bench_evidence(renderer, ratio, samples, args, results) -> None:
    size = args.evidence_resolution
    data = load_test_at_size(args.data, args.heldout, size)
    views = phd.uncertainty(renderer, data.cameras, ratio=ratio, samples=samples, keep_maps=True)
    rows = []
    for view, cam, truth in zip(views, data.cameras, data.images):
        render = renderer.render(cam)[0]
        covered = view.zeta > 0      # elements some sub-model changes; the rest is empty background
        error = (render.double() - truth.double()).abs()
        rows.append({"sigma_max": view.sigma_max, "sigma_mean": view.sigma_mean,
                     "spearman_covered": uqm.spearman(view.zeta[covered], error[covered]),
                     **uqm.image_uq_metrics(view.zeta, render, truth)})
    summary = {key: uqm.mean_defined([r[key] for r in rows])
               for key in ("spearman", "spearman_covered", "pearson", "ause_rmse", "ause_mse", "ause_mae", "rmse")}
    rmse = [r["rmse"] for r in rows]
    summary["spearman_sigma_max_vs_rmse"] = uqm.spearman([r["sigma_max"] for r in rows], rmse)
    summary["spearman_sigma_mean_vs_rmse"] = uqm.spearman([r["sigma_mean"] for r in rows], rmse)
    summary["sigma_max_bar"] = phd.sigma_max_bar(views)
    # What does drive a view's error? Two candidates that need no render: how far the view
    # looks from the nearest training view, and how much of the image the object covers.
    angles = angle_to_nearest(data.cameras, renderer.training_cameras)
    summary["spearman_rmse_vs_angle_to_training"] = uqm.spearman(rmse, angles)
    summary["spearman_sigma_max_vs_angle_to_training"] = uqm.spearman([r["sigma_max"] for r in rows], angles)
    if data.alphas is not None:
        coverage = data.alphas.flatten(1).mean(1).tolist()
        summary["spearman_rmse_vs_coverage"] = uqm.spearman(rmse, coverage)
        summary["spearman_sigma_mean_vs_coverage"] = uqm.spearman([r["sigma_mean"] for r in rows], coverage)
    for row, angle in zip(rows, angles):
        row["angle_to_training_deg"] = angle
    results["evidence"] = {"views": len(rows), "resolution": size, "samples": samples, "ratio": ratio,
                           "summary": summary, "per_view": rows}
    print(f"evidence: {summary}", flush=True)


# ---------------------------------------------------------------------------------------- report

def fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "undefined"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def markdown(results: dict) -> str:
    lines = [f"Measured {results['date']} on {results['machine']}; model: {results['model']}; "
             f"torch {results['torch']} with {results['threads']} threads; command: `{results['command']}`.", ""]
    cal = results.get("calibration")
    if cal:
        lines += [f"**Calibration** ({cal['views']} training views at {cal['resolution']} px, epsilon "
                  f"{cal['epsilon']})", "",
                  "| dr | method | masks per ratio | r_drop | ratios evaluated | time (s) |",
                  "|---|---|---|---|---|---|"]
        for r in cal["rows"]:
            if r.get("cut"):
                lines.append(f"| {r['step']} | {r['method']} | {r['samples']} | cut (time budget) | | |")
            else:
                lines.append(f"| {r['step']} | {r['method']} | {r['samples']} | {r['r_drop']} | {r['evaluated']} | "
                             f"{fmt(r['seconds'], 1)} |")
        lines.append("")
    ref = results.get("reference")
    if results.get("grid") and ref:
        lines += [f"**Ranking grid** ({results['candidates']} candidate test views, dropout ratio "
                  f"{results['ratio']}; reference: N = {ref['samples']} at {ref['resolution']} px, "
                  f"{fmt(ref['seconds_per_view'], 2)} s/view; {results['seeds']} seeds per cell). The reference "
                  f"against its own re-run with other masks: Kendall tau "
                  f"{fmt(ref.get('self_agreement', {}).get('kendall_tau'))}, top-5 overlap "
                  f"{fmt(ref.get('self_agreement', {}).get('top5_overlap'), 2)}.", "",
                  "| px | N | s/view | sigma_max CV median (max) | Kendall tau mean (min) | top-5 overlap | "
                  "tau vs same-px reference |",
                  "|---|---|---|---|---|---|---|"]
        for c in results["grid"]:
            if c["cut"]:
                lines.append(f"| {c['resolution']} | {c['samples']} | cut (time budget) | | | | |")
                continue
            lines.append(f"| {c['resolution']} | {c['samples']} | {fmt(c['seconds_per_view'])} | "
                         f"{fmt(c['sigma_max_cv_median'])} ({fmt(c['sigma_max_cv_max'])}) | "
                         f"{fmt(c['kendall_tau_mean'])} ({fmt(c['kendall_tau_min'])}) | "
                         f"{fmt(c['top5_overlap_mean'], 2)} | {fmt(c.get('kendall_tau_same_resolution_mean'))} |")
        rec = results.get("recommendation", {}).get("cell")
        lines += ["", f"Recommendation ({results['recommendation']['rule']}): "
                  + (f"N = {rec['samples']} at {rec['resolution']} px ({fmt(rec['seconds_per_view'])} s/view)."
                     if rec else "no measured cell reaches the target."), ""]
    if results.get("speedup"):
        lines += ["**Batched keep-masks vs one render per mask**", "",
                  "| N | px | batched s/view | separate s/view | speed-up |", "|---|---|---|---|---|"]
        lines += [f"| {r['samples']} | {r['resolution']} | {fmt(r['batched_seconds_per_view'])} | "
                  f"{fmt(r['separate_seconds_per_view'])} | x{fmt(r['speedup'], 2)} |" for r in results["speedup"]]
        lines.append("")
    ev = results.get("evidence")
    if ev:
        s = ev["summary"]
        lines += [f"**Does the uncertainty mean something?** ({ev['views']} held-out test views at "
                  f"{ev['resolution']} px, N = {ev['samples']}, ratio {ev['ratio']})", "",
                  "| Spearman over views: (sigma_max, RMSE) | (sigma_mean, RMSE) | pixel Spearman (mean) | "
                  "pixel Spearman, covered pixels | pixel Pearson (mean) | "
                  "AUSE RMSE | AUSE MSE | AUSE MAE | sigma-max-bar | mean RMSE |",
                  "|---|---|---|---|---|---|---|---|---|---|",
                  f"| {fmt(s['spearman_sigma_max_vs_rmse'])} | {fmt(s['spearman_sigma_mean_vs_rmse'])} | "
                  f"{fmt(s['spearman'])} | {fmt(s['spearman_covered'])} | {fmt(s['pearson'])} | "
                  f"{fmt(s['ause_rmse'])} | {fmt(s['ause_mse'])} | {fmt(s['ause_mae'])} | "
                  f"{fmt(s['sigma_max_bar'])} | {fmt(s['rmse'])} |", "",
                  "What per-view RMSE follows instead (Spearman over the same views): angle to the nearest "
                  f"training view {fmt(s.get('spearman_rmse_vs_angle_to_training'))}, object coverage "
                  f"{fmt(s.get('spearman_rmse_vs_coverage'))}; sigma_max vs that angle "
                  f"{fmt(s.get('spearman_sigma_max_vs_angle_to_training'))}, sigma_mean vs coverage "
                  f"{fmt(s.get('spearman_sigma_mean_vs_coverage'))}.", ""]
    if results.get("grid"):
        lines += ["![time per view](phdropout_time.svg) ![ranking agreement](phdropout_tau.svg)", ""]
    return "\n".join(lines)


def write_doc(path: Path, body: str, section: str = "phdropout") -> None:
    """Replace the text between `<!-- bench:<section>:begin -->` and its end marker (or append)."""
    begin, end = f"<!-- bench:{section}:begin -->", f"<!-- bench:{section}:end -->"
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body}\n{end}"
    if begin in text and end in text:
        text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
    else:
        text = text + ("\n" if text else "") + block + "\n"
    write_bytes_atomic(path, text.encode())


def svg_plot(path: Path, series: dict[str, list[tuple[float, float]]], xlabel: str, ylabel: str,
             log_y: bool = False, log_x: bool = True) -> None:
    """A minimal line chart, one polyline per series (log2 x axis by default: N)."""
    width, height, left, right, top, bottom = 420, 280, 60, 110, 20, 45
    points = [p for s in series.values() for p in s if p[1] is not None and (p[1] > 0 or not log_y)]
    if not points:
        return
    fy = (lambda v: math.log10(v)) if log_y else (lambda v: v)
    fx = math.log2 if log_x else (lambda v: v)
    x0, x1 = fx(min(p[0] for p in points)), fx(max(p[0] for p in points))
    y0, y1 = min(fy(p[1]) for p in points), max(fy(p[1]) for p in points)
    x1, y1 = (x1 if x1 > x0 else x0 + 1), (y1 if y1 > y0 else y0 + 1)

    def xy(x: float, y: float) -> tuple[float, float]:
        return (left + (fx(x) - x0) / (x1 - x0) * (width - left - right),
                height - bottom - (fy(y) - y0) / (y1 - y0) * (height - top - bottom))

    colours = ["#440154", "#31688e", "#35b779", "#b5de2b", "#fde725", "#e4572e", "#888888"]
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
           f'font-size="11"><rect width="100%" height="100%" fill="white"/>',
           f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
           f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
           f'<text x="{(left + width - right) / 2}" y="{height - 8}" text-anchor="middle">{xlabel}</text>',
           f'<text x="12" y="{(top + height - bottom) / 2}" transform="rotate(-90 12 {(top + height - bottom) / 2})" '
           f'text-anchor="middle">{ylabel}</text>']
    for x in sorted({p[0] for p in points}):
        px, _ = xy(x, 10 ** y0 if log_y else y0)
        out.append(f'<text x="{px:.1f}" y="{height - bottom + 14}" text-anchor="middle">{x:g}</text>')
    for frac in (0, 0.5, 1):
        value = y0 + frac * (y1 - y0)
        label = 10 ** value if log_y else value
        py = height - bottom - frac * (height - top - bottom)
        out.append(f'<text x="{left - 4}" y="{py + 4:.1f}" text-anchor="end">{label:.3g}</text>')
    for i, (name, pts) in enumerate(series.items()):
        pts = [p for p in pts if p[1] is not None and (p[1] > 0 or not log_y)]
        colour = colours[i % len(colours)]
        coords = " ".join(f"{a:.1f},{b:.1f}" for a, b in (xy(*p) for p in pts))
        out.append(f'<polyline points="{coords}" fill="none" stroke="{colour}" stroke-width="2"/>')
        out.append(f'<text x="{width - right + 8}" y="{top + 14 * (i + 1)}" fill="{colour}">{name}</text>')
    out.append("</svg>")
    write_bytes_atomic(path, "\n".join(out).encode())


def plots(results: dict, doc: Path) -> None:
    cells = [c for c in results.get("grid", []) if not c["cut"]]
    sizes = sorted({c["resolution"] for c in cells})
    time_series = {f"{s} px": [(c["samples"], c["seconds_per_view"]) for c in cells if c["resolution"] == s]
                   for s in sizes}
    tau_series = {f"{s} px": [(c["samples"], c["kendall_tau_mean"]) for c in cells if c["resolution"] == s]
                  for s in sizes}
    svg_plot(doc.parent / "phdropout_time.svg", time_series, "samples N", "seconds per view", log_y=True)
    svg_plot(doc.parent / "phdropout_tau.svg", tau_series, "samples N", "Kendall tau vs reference")


def main() -> None:
    args = parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    started = time.perf_counter()
    renderer, description = load_renderer(args)
    test = load_dataset(args.data, "test", views=args.candidates, with_images=False)
    results: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
        "machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs".replace("  ", " "),
        "torch": torch.__version__, "threads": torch.get_num_threads(), "model": description,
        "candidates": len(test.cameras), "candidate_frames": test.indices, "seeds": args.seeds,
        "defaults": {"epsilon": phd.DEFAULT_EPSILON, "step": phd.DEFAULT_STEP, "samples": phd.DEFAULT_SAMPLES,
                     "calibration_samples": phd.DEFAULT_CALIBRATION_SAMPLES},
    }
    small, large = phd.dropout_uniforms(97, 4, 5), phd.dropout_uniforms(97, 64, 5)
    assert torch.equal(small, large[:4]), "masks of N samples must be a prefix of a larger draw (same seed)"
    ratio = bench_calibration(renderer, args, results, started)
    if ratio == 0:
        ratio = 0.1
        results["ratio_note"] = "calibration failed (r_drop = 0); the grid uses ratio 0.1"
    results["ratio"] = ratio
    save(results, args.out)
    bench_grid(renderer, test.cameras, ratio, args, results, started)
    save(results, args.out)
    bench_speedup(renderer, test.cameras, ratio, args, results)
    save(results, args.out)
    rec = results["recommendation"]["cell"]
    bench_evidence(renderer, ratio, rec["samples"] if rec else phd.DEFAULT_SAMPLES, args, results)
    results["total_seconds"] = time.perf_counter() - started
    save(results, args.out)
    if args.doc is not None:
        plots(results, args.doc)
        write_doc(args.doc, markdown(results))
    print(markdown(results))
    print(f"wrote {args.out}" + (f" and the tables in {args.doc}" if args.doc else ""))


if __name__ == "__main__":
    main()
