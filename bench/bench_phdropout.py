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

    .venv/bin/python -m bench.bench_phdropout --model runs/lego16/model.ply --data ../shared/data/lego_200
    .venv/bin/python -m bench.bench_phdropout --quick      # smoke run on a random model

Without --model (or with --random-splats K) a seeded random splat cloud stands in for the
trained model, with lego's training cameras: numbers then only validate the script.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

from bench._harness import (
    DOCS,
    LEGO,
    RESULTS,
    ROOT,
    fmt,
    load_test_at_size,
    machine,
    machine_text,
    svg_plot,
    timed,
    write_doc,
    write_result,
)
from phd_core import uq as phd
from phd_core.data import load_dataset
from phd_core.eval import uq as uqm

DATA = LEGO
RESULT = RESULTS / "uq.json"
DOC = DOCS / "uq.md"
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
    p.add_argument("--out", type=Path, default=None, help=f"results JSON (default {RESULT.relative_to(ROOT)}, "
                   "with --quick bench/results/phdropout_quick.json)")
    p.add_argument("--doc", type=Path, default=None,
                   help=f"markdown file whose bench section is rewritten (default {DOC.relative_to(ROOT)}; "
                        "--quick writes no document unless given)")
    args = p.parse_args()
    args.out = args.out or (RESULT.with_name("phdropout_quick.json") if args.quick else RESULT)
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
            run = timed(lambda: phd.calibrate(renderer, cameras, step=step, method=method, samples=samples))
            result, seconds = run.result, run.seconds
            row.update(seconds=seconds, r_drop=result.r_drop, evaluated=len(result.ratios), capped=result.capped,
                       ratios=result.ratios, errors=result.errors, cut=False)
        except phd.CalibrationError as exc:
            row.update(seconds=None, r_drop=0.0, evaluated=len(exc.ratios), error=str(exc), cut=False)
        rows.append(row)
        print(f"calibration dr={step} {method} N={samples}: r_drop {row['r_drop']} "
              f"({row['evaluated']} ratios, {row['seconds'] or 0:.1f} s)", flush=True)
        results["calibration"] = {"resolution": args.calibration_resolution, "views": len(cameras),
                                  "epsilon": phd.DEFAULT_EPSILON, "rows": rows}
        write_result(args.out, results)
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
        run = timed(lambda: phd.uncertainty(renderer, at_size(candidates, size), ratio=ratio,
                                            samples=args.reference_samples, seed=REFERENCE_SEED))
        views, seconds = run.result, run.seconds
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
    write_result(args.out, results)
    cells = []
    for size in sizes:
        if args.budget_minutes is not None and time.perf_counter() - started > 60 * args.budget_minutes:
            cells += [{"resolution": size, "samples": n, "cut": True} for n in grid]
            continue
        cams = at_size(candidates, size)
        # Time: direct API calls on the first timing views, one per N.
        seconds_per_view, direct = {}, {}
        for n in grid:
            run = timed(lambda: phd.uncertainty(renderer, cams[:args.timing_views], ratio=ratio, samples=n, seed=0))
            views, seconds = run.result, run.seconds
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
        write_result(args.out, results)
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
            seconds = timed(lambda: phd.view_uncertainty(renderer, cam, ratio=ratio, samples=n, seed=0)).seconds
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
        coverage = [float(alpha.mean()) for alpha in data.alphas]
        summary["spearman_rmse_vs_coverage"] = uqm.spearman(rmse, coverage)
        summary["spearman_sigma_mean_vs_coverage"] = uqm.spearman([r["sigma_mean"] for r in rows], coverage)
    for row, angle in zip(rows, angles):
        row["angle_to_training_deg"] = angle
    results["evidence"] = {"views": len(rows), "resolution": size, "samples": samples, "ratio": ratio,
                           "summary": summary, "per_view": rows}
    print(f"evidence: {summary}", flush=True)


# ---------------------------------------------------------------------------------------- report

def markdown(results: dict) -> str:
    lines = [f"Measured {results['date']} on {machine_text(results['machine'])}; model: {results['model']}; "
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
        "machine": machine(),
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
    write_result(args.out, results)
    bench_grid(renderer, test.cameras, ratio, args, results, started)
    write_result(args.out, results)
    bench_speedup(renderer, test.cameras, ratio, args, results)
    write_result(args.out, results)
    rec = results["recommendation"]["cell"]
    bench_evidence(renderer, ratio, rec["samples"] if rec else phd.DEFAULT_SAMPLES, args, results)
    results["total_seconds"] = time.perf_counter() - started
    write_result(args.out, results)
    if args.doc is not None:
        plots(results, args.doc)
        write_doc(args.doc, markdown(results), "phdropout")
    print(markdown(results))
    print(f"wrote {args.out}" + (f" and the tables in {args.doc}" if args.doc else ""))


if __name__ == "__main__":
    main()
