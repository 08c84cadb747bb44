"""Active-learning benchmark: which next-best-view strategy gives the best reconstruction?

The protocol (issue 10), the same for every strategy and seed:
1. Start from `--initial` train views: one drawn by the seed, the rest farthest-view sampled.
2. Train a 3DGS model on the chosen views (`fit`, `--iterations`, seeded, at `--resolution`).
3. Rank the remaining train poses with the strategy through the product's `rank_views`
   (r_drop calibrated on the chosen views, N = `--samples` masks) and add its top
   `--per-round` views, a batch captured together. Retrain from scratch. `--rounds` times.
4. After every round: mean PSNR over `--test-views` evenly spaced held-out test views.
Also, on each seed's initial model: the per-view Spearman correlation between each
strategy's score of a held-out test view (before any pick) and that view's true RMSE.

Each (scene, seed) is one task written to bench/results/nbv/<scene>-<seed>.json after every
strategy, so an interrupted run resumes; `--report` rewrites docs/nbv.md from those files.

    .venv/bin/python -m bench.bench_nbv --jobs 2                  # shipped strategies, seeds 0..4
    .venv/bin/python -m bench.bench_nbv --jobs 2 --seeds 0 --strategies sigma_mean kmedian kmedian_sigma \
        kmedian_sq fvs_prefilter                                  # the ones tried and not shipped
    .venv/bin/python -m bench.bench_nbv --report

A run name `<strategy>+<signal>` (e.g. `visibility_sigma+premultiplied`) runs a dropout strategy
with zeta and r_drop measured on that signal (phd_core.renderers.SIGNALS) instead of the
paper's composited colour; `<strategy>+targets` runs a coverage strategy told where the model
will be looked at from (`rank_views(targets=...)`): the scene's val split, disjoint from the
test views (a capture with one image list, cup_colmap: its train frames, the path between the
held-out ones). The results carry the name as their strategy label.

Holdout folds of a capture with one image list (`--scenes cup_colmap@1 ...`): fold k tests on every
8th frame from k and captures from the rest, so a deterministic strategy, whose seeds share one
set of 10 test views on the LLFF split, is measured on other test views too; `--report` pairs the
runs fold by fold (fold 0 is the scene itself) in their own section of docs/nbv.md:

    .venv/bin/python -m bench.bench_nbv --jobs 2 --scenes cup_colmap@1 cup_colmap@2 cup_colmap@3 cup_colmap@4 \
        cup_colmap@5 cup_colmap@6 cup_colmap@7 --seeds 0 1 2 --strategies random fvs visibility_sigma_fvs+targets \
        visibility_sigma_fvs

A run `<strategy>+testviews` is told the test views themselves: how much the target gain could
gain if the targets said exactly where the model will be looked at (a ceiling, not a protocol).

The held-out family (`--family`, issue 37): the scenes bench/nbv_scenes.py generates, no
strategy tuned on them, reported as paired differences per scene and seed (win rate, mean
margin, 95 % bootstrap interval over scenes) in their own section of docs/nbv.md:

    .venv/bin/python -m bench.nbv_scenes
    .venv/bin/python -m bench.bench_nbv --family --jobs 2 --seeds 0 1 \
        --strategies visibility_sigma_fvs fvs random visibility_sigma_fvs+targets

`--family walk` and `--family room` run the walks and rooms the same script makes (captures
along one path, split as cup_colmap is, told their own train frames as targets), each reported
in its own section.

The real family (`--family real`, issue 47): the real captures (bench._harness.REAL_CAPTURES, or any COLMAP
capture folders given as `--scenes PATH ...`), each split as cup_colmap is and read by the product's loaders,
the widest view `--resolution` px wide and every view at its own aspect. Its protocol: training pinned to
be deterministic (the round-0 model, trained once per capture and seed, is the same for every strategy;
a stored task whose first model now tests otherwise stops the run), a budget that grows with the views
(`--iterations-per-view`), and a report paired by capture and seed with a bootstrap over those pairs,
each round's ranking seconds beside it:

    PHD_CACHE_DIR=<a directory> OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_nbv \
        --family real --jobs 2 --resolution 50 --iterations-per-view 40 --per-round 3 --rounds 2 --seeds 0 1 2 \
        --strategies random fvs visibility_sigma_fvs visibility_sigma_fvs+targets
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import random
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable

import torch

from bench import nbv_experiments  # importing registers the strategies tried, not shipped
from bench._harness import (
    DATA,
    DOCS,
    REAL_CAPTURES,
    RESULTS,
    capture_path,
    fmt,
    load_average,
    machine,
    pin_determinism,
    subset,
    svg_plot,
    train,
    write_doc,
    write_result,
)
from phd_core import uq as phd
from phd_core.data import Dataset, load_dataset
from phd_core.data.frames import HOLDOUT
from phd_core.errors import InputError
from phd_core.eval import psnr, rmse, spearman
from phd_core.renderers import DEFAULT_SIGNAL, SIGNALS
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.uq.rank import add_fisher, view_visibility, visibility_evidence
from phd_core.uq.strategies import DEFAULT_STRATEGY, STRATEGIES, Evidence, get_strategy

EXPERIMENTS = nbv_experiments.EXPERIMENTS
DOC = DOCS / "nbv.md"
SHIPPED = ["random", "fvs", "sigma_max", "fvs_sigma", "fvs_sigma_floor", "visibility", "visibility_sigma",
           "visibility_sigma_fvs"]
# curves per round
PLOTTED = ["random", "fvs", "fvs_sigma_floor", "visibility", "visibility_sigma", "visibility_sigma_fvs"]
# Image width per scene where it is not --resolution (square): the real capture is 4:3, 80x60 px
# at the default resolution (as its training benchmark, docs/formats.md).
WIDTH_SCALE = {"cup_colmap": 1.6}
FOLD = "@"      # "cup_colmap@3": holdout fold 3 of a capture with one image list (scene_fold)
TARGETS = "targets"         # the run-name suffix of a run told the target views
TEST_VIEWS = "testviews"    # ... told the test views themselves: the target gain's ceiling, not a protocol
TARGETED = f"{DEFAULT_STRATEGY}+{TARGETS}"
FAMILY = RESULTS / "nbv_scenes"   # bench/nbv_scenes.py's output: the held-out families
REAL_COVER = 0.8     # the share of what the test views see that a real capture's first views see (`covering_views`)
FAMILIES = ("held", "walk", "room", "real")   # nbv_scenes.py's kinds of scene, and real captures (REAL_CAPTURES)


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=["lego_200", "donut_200", "chain_200", "cup_colmap"],
                   help="captures under --data (any format phd_core.data reads; COLMAP holds out every 8th image)")
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--resolution", type=int, default=50, help="square image size for training and testing")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--iterations-per-view", type=int, default=None, help="a budget that grows with the views: "
                   "every training runs this many iterations per view it is trained on (instead of --iterations)")
    p.add_argument("--initial", type=int, default=4, help="views the first model is trained on (at least: --cover)")
    p.add_argument("--cover", type=float, default=None, help="the real family (default there: "
                   f"{REAL_COVER}): start from more views than --initial where those do not yet see this share of "
                   "what the test views see (their SfM points: `covering_views`), so that a capture seen a wall at "
                   "a time (a room from inside) starts where views added can still be told apart")
    p.add_argument("--per-round", type=int, default=2)
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--test-views", type=int, default=40)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--strategies", nargs="+", default=SHIPPED, choices=run_names(),
                   help="strategy names, or <strategy>+<signal> for a dropout strategy on another signal")
    p.add_argument("--samples", type=int, default=phd.DEFAULT_SAMPLES)
    p.add_argument("--rerun", action="store_true", help="run the listed strategies again even where results are "
                   "stored (rows from another machine set-up start from a differently trained initial model)")
    p.add_argument("--jobs", type=int, default=1, help="(scene, seed) tasks run in parallel, one thread each")
    p.add_argument("--results", type=Path, default=None, help="default: bench/results/nbv, or nbv_<R>px for a "
                   "--resolution R other than 50 (its own doc section and plots)")
    p.add_argument("--doc", type=Path, default=DOC)
    p.add_argument("--report", action="store_true", help="only rewrite the doc from the stored results")
    p.add_argument("--costs", action="store_true", help="time rank_views per candidate for every strategy on one "
                   "model (the first scene and seed), one run, to bench/results/nbv/costs.json")
    p.add_argument("--family", nargs="?", const="held", default=None, choices=FAMILIES,
                   help="a held-out family of bench/nbv_scenes.py: held (the default), walk or room (default "
                   "--scenes: every one of that kind generated), results in bench/results/nbv_heldout, a doc "
                   "section for each kind); real: the real captures (default --scenes: bench._harness."
                   "REAL_CAPTURES, or COLMAP capture folders given as paths), each split as cup_colmap is, "
                   "--resolution the widest view's width, results in bench/results/nbv_real")
    p.add_argument("--repeat-of", type=Path, default=None, help="with --family --report: a results directory "
                   "holding the same runs again, to report how far two identical runs differ (the noise floor)")
    args = p.parse_args()
    args.captures = {}      # scene name -> capture folder, where it is not under --data
    if args.family == "real":
        args.cover = REAL_COVER if args.cover is None else args.cover
        given = REAL_CAPTURES if args.scenes == p.get_default("scenes") else args.scenes
        args.captures = {Path(s).name: Path(s) if Path(s).is_dir() else capture_path(s) for s in given}
        args.scenes = list(args.captures)
    elif args.family:
        if args.scenes == p.get_default("scenes"):
            args.scenes = sorted(path.name for path in FAMILY.glob(f"{args.family}_*") if path.is_dir())
        if args.data == DATA:
            args.data = FAMILY
    return args


def run_names() -> list[str]:
    """Every strategy, each dropout strategy on each signal other than the default, and each coverage
    strategy told the target views (or the test views themselves)."""
    return (list(STRATEGIES) + [f"{name}+{signal}" for name, strategy in STRATEGIES.items() if strategy.uses_dropout
                                for signal in SIGNALS if signal != DEFAULT_SIGNAL]
            + [f"{name}+{told}" for name, strategy in STRATEGIES.items() if strategy.uses_visibility
               for told in (TARGETS, TEST_VIEWS)])


def variant(name: str) -> tuple[str, str, str | None]:
    """(strategy, signal, what it is told: TARGETS, TEST_VIEWS or None) of a run name:
    `visibility_sigma+premultiplied`, `visibility_sigma_fvs+targets`, or a plain strategy name."""
    strategy, *suffixes = name.split("+")
    signals = [s for s in suffixes if s not in (TARGETS, TEST_VIEWS)]
    told = [s for s in suffixes if s in (TARGETS, TEST_VIEWS)]
    return strategy, signals[0] if signals else DEFAULT_SIGNAL, told[0] if told else None


def tag(args: argparse.Namespace, results: bool = False) -> str:
    """What names this resolution's (or the family's) doc section and plots apart from the four scenes
    at the default 50 px; with `results`, its results directory (one for every family: a task is
    found by its scene's name)."""
    family = ("" if args.family is None else "_real" if args.family == "real"
              else "_heldout" if results or args.family == "held" else f"_{args.family}s")
    return family + ("" if args.resolution == 50 else f"_{args.resolution}px")


def protocol(args: argparse.Namespace) -> dict:
    """The settings a stored result must match to be reused (a growing budget only where it is set, so results
    of a fixed one stay valid)."""
    kept = ("resolution", "iterations", "initial", "per_round", "rounds", "test_views", "samples")
    return {k: getattr(args, k) for k in kept} | (
        {"iterations_per_view": args.iterations_per_view} if args.iterations_per_view else {}) | (
        {"cover": args.cover} if args.cover is not None else {})


def budget(args: argparse.Namespace, views: int) -> int:
    """Training iterations for a model of `views` views: --iterations-per-view times the views, else --iterations."""
    return args.iterations_per_view * views if args.iterations_per_view else args.iterations


# ---------------------------------------------------------------------------------------- one task

def test_errors(renderer: GaussianRenderer, test: Dataset) -> tuple[float, list[float]]:
    """Mean PSNR over the test views and each view's RMSE."""
    renders = [renderer.render(camera)[0] for camera in test.cameras]
    values = [psnr(r, image) for r, image in zip(renders, test.images)]
    return sum(values) / len(values), [rmse(r, image) for r, image in zip(renders, test.images)]


def initial_views(cameras: list, count: int, seed: int) -> list[int]:
    """One view drawn by the seed, then farthest-view sampling for the rest."""
    start = random.Random(seed).randrange(len(cameras))
    pool = [i for i in range(len(cameras)) if i != start]
    empty = torch.zeros(len(pool), dtype=torch.float64)
    evidence = Evidence([cameras[i] for i in pool], [cameras[start]], empty, empty)
    order = STRATEGIES["fvs"].select(evidence, count - 1, seed).order
    return [start] + [pool[i] for i in order[:count - 1]]


def covering_views(train_data: Dataset, test: Dataset, count: int, cover: float | None, seed: int) -> list[int]:
    """`initial_views`, at least `count` and more until the views see `cover` of what the test views see: for each
    test view the share of the SfM points it sees (`nbv_experiments.seen_points`) that one of the views sees,
    averaged over the test views that see any. Farthest-view sampling's order does not depend on how many it
    picks, so the views grow one at a time along it."""
    if cover is None:
        return initial_views(train_data.cameras, count, seed)
    if train_data.points is None:
        raise ValueError("--cover needs captures with SfM points (COLMAP)")
    points = train_data.points.double()
    order = initial_views(train_data.cameras, len(train_data.cameras), seed)
    seen = torch.stack([nbv_experiments.seen_points(train_data.cameras[i], points) for i in order])   # [V, P]
    shown = [nbv_experiments.seen_points(camera, points) for camera in test.cameras]                   # T x [P]
    for views in range(count, len(order) + 1):
        covered = seen[:views].any(0)                                                                   # [P]
        if statistics.fmean(float(covered[m].double().mean()) for m in shown if m.any()) >= cover:
            return order[:views]
    return order


def scene_fold(scene: str) -> tuple[str, int | None]:
    """'cup_colmap@3' -> ('cup_colmap', 3): a capture with one image list whose test views are every
    HOLDOUT-th frame from 3 (a holdout fold; 0 is the LLFF split) and whose train views are the rest."""
    name, _, fold = scene.partition(FOLD)
    if fold and not (fold.isdigit() and int(fold) < HOLDOUT):
        raise InputError("scenes", f"{scene!r}: the fold after {FOLD!r} must be 0..{HOLDOUT - 1}")
    return name, int(fold) if fold else None


def load_split(args: argparse.Namespace, scene: str, split: str, **kw) -> Dataset:
    """A split of a scene at the protocol's size (the widest view --resolution wide; outside the real family
    WIDTH_SCALE for 4:3 captures), every view at its own aspect; of a holdout fold (`scene_fold`), the
    fold's frames of the capture's "all" split."""
    name, fold = scene_fold(scene)
    folder = args.captures.get(name, args.data / name)
    size = max(c.width for c in load_dataset(folder, "train", with_images=False).cameras)
    downscale = size / (args.resolution * (1.0 if args.family == "real" else WIDTH_SCALE.get(name, 1.0)))
    if fold is None:
        return load_dataset(folder, split, downscale=downscale, **kw)
    if split not in ("train", "test"):
        raise InputError("split", f"a holdout fold has the splits train and test, not {split!r}")
    views = kw.pop("views", None)
    every = load_dataset(folder, "all", downscale=downscale, **kw)
    chosen = [i for i in range(len(every.cameras)) if (i % HOLDOUT == fold) == (split == "test")]
    if views is not None and views < len(chosen):
        raise InputError("test_views", f"a holdout fold tests on all of its {len(chosen)} views")
    return subset(every, chosen)


def target_cameras(args: argparse.Namespace, scene: str) -> list:
    """Where the model will be looked at from, disjoint from the test views: the val split, or for a
    capture with one image list (COLMAP holds out every 8th image as test) its train frames."""
    try:
        return load_split(args, scene, "val", with_images=False).cameras
    except InputError:
        return load_split(args, scene, "train", with_images=False).cameras


def calibrated_ratio(renderer: GaussianRenderer, captured: list, signal: str = DEFAULT_SIGNAL) -> float:
    return phd.calibrate(renderer, captured, signal=signal).r_drop


def run_task(scene: str, seed: int, args: argparse.Namespace) -> str:
    pin_determinism()
    path = args.results / f"{scene}-{seed}.json"
    train_data = load_split(args, scene, "train")
    tests = len(load_split(args, scene, "test", with_images=False).cameras)
    test = load_split(args, scene, "test", views=min(args.test_views, tests))
    init = covering_views(train_data, test, args.initial, args.cover, seed)
    stored = json.loads(path.read_text()) if path.exists() else {}
    if stored.get("protocol") != protocol(args) or stored.get("initial") != init:
        stored = {}
    result = stored or {"scene": scene, "seed": seed, "protocol": protocol(args), "initial": init, "runs": {},
                        "spearman": {}}
    todo = [s for s in args.strategies
            if args.rerun or s not in result["runs"] or s not in result["spearman"]]
    if not todo:
        return f"{scene} seed {seed}: stored"
    started = time.perf_counter()
    base = train(train_data, init, budget(args, len(init)), seed)
    base_psnr, base_rmse = test_errors(base, test)
    if stored and stored.get("initial_psnr") != base_psnr:   # the strategies stored must share this first model
        raise RuntimeError(f"{scene} seed {seed}: the initial model tests at {base_psnr!r} dB, the stored runs' "
                           f"at {stored.get('initial_psnr')!r}: training is not deterministic here")
    captured = [train_data.cameras[i] for i in init]
    views_told = {TARGETS: target_cameras(args, scene) if any(variant(n)[2] == TARGETS for n in todo) else None,
                  TEST_VIEWS: test.cameras}
    initial: dict[str, tuple[float, Evidence]] = {}     # by signal: r_drop of the initial model, test evidence
    for signal in dict.fromkeys(variant(n)[1] for n in todo):
        ratio = calibrated_ratio(base, captured, signal)
        initial[signal] = ratio, phd.candidate_evidence(
            base, test.cameras, ratio=ratio, samples=args.samples, seed=seed, captured=captured, visibility=True,
            fisher=any(get_strategy(variant(n)[0]).uses_fisher for n in todo), signal=signal)[0]
    result["initial_seconds"] = round(time.perf_counter() - started, 1)
    result["initial_psnr"] = base_psnr
    for name in todo:
        strategy_name, signal, told = variant(name)
        strategy = get_strategy(strategy_name)
        ratio, test_evidence = initial[signal]
        told_targets = views_told[told] if told else None
        if told_targets:
            test_evidence = dataclasses.replace(test_evidence, target_views=view_visibility(base, told_targets))
        if strategy_name in nbv_experiments.USES_POINTS:
            test_evidence = nbv_experiments.with_points(
                test_evidence, nbv_experiments.points_for(strategy_name, train_data.points, base.model.means))
        result["spearman"][name] = spearman(strategy.select(test_evidence, 0, seed).scores, base_rmse)
        started = time.perf_counter()
        chosen, renderer, curve, ratios = list(init), base, [base_psnr], [ratio]
        seconds = []    # wall seconds of each round's ranking (evidence and selection)
        cost = []       # ... per candidate
        for round_ in range(args.rounds):
            pool = [i for i in range(len(train_data.cameras)) if i not in chosen]
            captured = [train_data.cameras[i] for i in chosen]
            candidates = [train_data.cameras[i] for i in pool]
            ranked_at = time.perf_counter()
            if strategy.uses_dropout:
                ranked = phd.rank_views(renderer, candidates, ratio=ratios[-1], samples=args.samples,
                                        seed=seed + round_, top_k=args.per_round, strategy=strategy_name,
                                        captured=captured, signal=signal, targets=told_targets)
                picks = [r.index for r in ranked]
            else:   # the same picks rank_views makes, without the dropout renders it would report
                if strategy.uses_visibility:
                    evidence = visibility_evidence(renderer, candidates, captured, told_targets)
                else:
                    empty = torch.zeros(len(candidates), dtype=torch.float64)
                    evidence = Evidence(candidates, captured, empty, empty)
                if strategy.uses_fisher:
                    add_fisher(evidence, renderer, seed + round_)
                if strategy_name in nbv_experiments.USES_POINTS:
                    evidence = nbv_experiments.with_points(
                        evidence, nbv_experiments.points_for(strategy_name, train_data.points, renderer.model.means))
                picks = strategy.select(evidence, args.per_round, seed + round_).order[:args.per_round]
            seconds.append(time.perf_counter() - ranked_at)
            cost.append(seconds[-1] / len(candidates))
            chosen += [pool[i] for i in picks]
            renderer = train(train_data, chosen, budget(args, len(chosen)), seed)
            curve.append(test_errors(renderer, test)[0])
            if strategy.uses_dropout and round_ < args.rounds - 1:
                ratios.append(calibrated_ratio(renderer, [train_data.cameras[i] for i in chosen], signal))
        result["runs"][name] = {"psnr": curve, "chosen": chosen, "ratios": ratios, "cost_per_candidate": cost,
                                "rank_seconds": seconds,
                                "seconds": round(time.perf_counter() - started, 1)}
        write_result(path, result)
        print(f"{scene} seed {seed} {name}: " + " ".join(f"{p:.2f}" for p in curve), flush=True)
    return f"{scene} seed {seed}: done"


# ---------------------------------------------------------------------------------------- report

def load_results(args: argparse.Namespace, every_seed: bool = False) -> dict[str, list[dict]]:
    """Stored tasks of the current protocol, by scene (of --seeds, or of every stored seed)."""
    by_scene: dict[str, list[dict]] = {}
    for path in sorted(args.results.glob("*.json")):
        task = json.loads(path.read_text())
        if (task.get("protocol") == protocol(args) and task["scene"] in args.scenes
                and (every_seed or task["seed"] in args.seeds)):
            by_scene.setdefault(task["scene"], []).append(task)
    return by_scene


def paired(tasks: list[dict], name: str, baseline: str = "fvs") -> str:
    """`name` minus `baseline`, seed by seed, over every stored seed that ran both."""
    pairs = [(t["runs"][name]["psnr"], t["runs"][baseline]["psnr"]) for t in tasks
             if name in t["runs"] and baseline in t["runs"]]
    if not pairs:
        return ""
    finals = [a[-1] - b[-1] for a, b in pairs]
    rounds = [statistics.mean(a[1:]) - statistics.mean(b[1:]) for a, b in pairs]

    def spread(values: list[float]) -> str:
        return f" ± {statistics.stdev(values):.2f}" if len(values) > 1 else ""
    return (f"Paired with {baseline} seed by seed over every stored seed (n = {len(pairs)}): {name} final "
            f"{statistics.mean(finals):+.2f}{spread(finals)} dB (ahead on "
            f"{sum(d > 0 for d in finals)} of {len(pairs)} seeds), mean over rounds "
            f"{statistics.mean(rounds):+.2f}{spread(rounds)} dB (ahead on "
            f"{sum(d > 0 for d in rounds)} of {len(pairs)}).")


def summary(tasks: list[dict], name: str) -> dict | None:
    runs = [t["runs"][name] for t in tasks if name in t["runs"]]
    if not runs:
        return None
    finals = [r["psnr"][-1] for r in runs]
    overall = [sum(r["psnr"][1:]) / (len(r["psnr"]) - 1) for r in runs]
    curve = [statistics.mean(values) for values in zip(*(r["psnr"] for r in runs))]
    rhos = [t["spearman"][name] for t in tasks if t["spearman"].get(name) is not None]
    costs = [c for r in runs for c in r.get("cost_per_candidate", [])]
    return {"seeds": len(runs), "final": statistics.mean(finals),
            "final_sd": statistics.stdev(finals) if len(finals) > 1 else 0.0,
            "rounds": statistics.mean(overall), "curve": curve, "finals": finals,
            "spearman": statistics.mean(rhos) if rhos else None,
            "cost": statistics.median(costs) if costs else None}


def label(name: str) -> str:
    strategy, signal, told = variant(name)
    if signal != DEFAULT_SIGNAL:
        return f"{name} ({strategy} with zeta and r_drop on the {signal} signal)"
    if told:
        return f"{name} ({strategy} told the {'test views themselves' if told == TEST_VIEWS else 'target views'})"
    return (f"**{name}** (default)" if name == DEFAULT_STRATEGY else
            f"{name} (tried, bench/nbv_experiments.py)" if name in EXPERIMENTS
            else name if name in STRATEGIES else f"{name} (tried, removed; docs/nbv.md says where its code is)")


def cost_text(row: dict) -> str:
    """Seconds of ranking per candidate (median over rounds and seeds): evidence and selection."""
    return "" if row["cost"] is None else f"{row['cost'] * 1000:.1f} ms"


def overview(by_scene: dict[str, list[dict]], every_seed: dict[str, list[dict]]) -> list[str]:
    """One row per strategy run on every scene: the mean over scenes, and each scene against FVS."""
    scenes = sorted(by_scene)
    rows = {scene: {n: summary(tasks, n) for n in {n for t in tasks for n in t["runs"]}}
            for scene, tasks in by_scene.items()}
    names = [n for n in sorted({n for r in rows.values() for n in r}) if all(rows[s].get(n) for s in scenes)]
    if not names or not all(rows[s].get("fvs") for s in scenes):
        return []
    lines = ["### All scenes", "",
             "Mean over the scenes of each scene's mean (final PSNR after the last round, and over rounds 1..R); "
             "then each scene's final PSNR minus FVS's, seed by seed where both ran (mean, and on how many seeds "
             "the strategy is ahead).", "",
             "| strategy | mean final | mean rounds | " + " | ".join(f"{s} final vs FVS" for s in scenes)
             + " | cost per candidate |", "|---|---|---|" + "---|" * len(scenes) + "---|"]
    ordered = sorted(names, key=lambda n: -statistics.mean(rows[s][n]["final"] for s in scenes))
    for name in ordered:
        deltas = []
        for scene in scenes:
            pairs = [t["runs"][name]["psnr"][-1] - t["runs"]["fvs"]["psnr"][-1] for t in every_seed.get(scene, [])
                     if name in t["runs"] and "fvs" in t["runs"]]
            deltas.append(f"{statistics.mean(pairs):+.2f} ({sum(d > 0 for d in pairs)}/{len(pairs)})" if pairs else "")
        costs = [rows[s][name]["cost"] for s in scenes if rows[s][name]["cost"] is not None]
        lines.append(f"| {label(name)} | {statistics.mean(rows[s][name]['final'] for s in scenes):.2f} | "
                     f"{statistics.mean(rows[s][name]['rounds'] for s in scenes):.2f} | " + " | ".join(deltas)
                     + f" | {f'{statistics.mean(costs) * 1000:.1f} ms' if costs else ''} |")
    return lines + [""]


def markdown(by_scene: dict[str, list[dict]], every_seed: dict[str, list[dict]], args: argparse.Namespace) -> str:
    lines = [f"Commands: `OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python -m bench.bench_nbv --jobs 2` "
             "(all four scenes; the strategies and seeds run are in the tables), then the "
             "line for the tried ones in the script's docstring (one seed), then `--report` "
             f"({platform.machine()}, {os.cpu_count()} cores, one thread per task). "
             f"Protocol: {args.resolution}x{args.resolution} px "
             f"(cup_colmap {round(args.resolution * WIDTH_SCALE['cup_colmap'])}x"
             f"{round(args.resolution * WIDTH_SCALE['cup_colmap'] * 3 / 4)}, its SfM points as the start, every 8th "
             f"image held out), {args.iterations} iterations, {args.initial} initial views "
             "(one by the seed, then FVS), "
             f"{args.per_round} views per round, {args.rounds} rounds, PSNR on {args.test_views} evenly spaced "
             f"test views (cup_colmap: its 10), N = {args.samples} masks, r_drop calibrated every round.", "",
             "Final = mean test PSNR after the last round over the seeds (with the standard deviation and each "
             "seed's value); rounds = mean PSNR over rounds 1..R; vs FVS = difference of the means (rows with fewer "
             "seeds than FVS compare with FVS's mean over all of its seeds; the paired line below each table "
             "compares seed by seed); "
             "Spearman = per held-out view, the strategy's score against the true RMSE on the initial model; "
             "cost = wall seconds of one round's ranking per candidate (median; the evidence the strategy needs "
             "and its selection: no renders for random and FVS, one render per candidate and captured view for "
             "visibility, N masked renders per candidate for the dropout strategies; calibration not included; "
             "two tasks ran at once on the 2 cores).", ""]
    lines += overview(by_scene, every_seed) + cost_table(args)
    for scene, tasks in sorted(by_scene.items()):
        rows = {name: summary(tasks, name) for name in sorted({n for t in tasks for n in t["runs"]})}
        fvs = rows.get("fvs")
        lines += [f"### {scene}", "",
                  "| strategy | seeds | final PSNR | per seed | rounds mean | final vs FVS | rounds vs FVS | "
                  "Spearman(score, RMSE) | cost per candidate |", "|---|---|---|---|---|---|---|---|---|"]
        for name, row in sorted(((n, r) for n, r in rows.items() if r), key=lambda item: -item[1]["final"]):
            delta = (f"{row['final'] - fvs['final']:+.2f}", f"{row['rounds'] - fvs['rounds']:+.2f}") if fvs \
                else ("", "")
            lines.append(f"| {label(name)} | {row['seeds']} | {row['final']:.2f} ± {row['final_sd']:.2f} | "
                         f"{' / '.join(f'{v:.2f}' for v in row['finals'])} | {row['rounds']:.2f} | {delta[0]} | "
                         f"{delta[1]} | {fmt(row['spearman'], 2)} | {cost_text(row)} |")
        plotted, common = plotted_runs(tasks)
        lines += [""] + [paired(every_seed.get(scene, []), name) for name in (DEFAULT_STRATEGY, "fvs_sigma_floor")
                         if name in rows and name != "fvs"] + [
            paired(every_seed.get(scene, []), TARGETED, baseline) for baseline in BASELINES if TARGETED in rows] + ["",
                  f"![PSNR per round on {scene}](nbv_{scene}{tag(args)}.svg)",
                  f"(mean test PSNR per round of {', '.join(plotted)} over seeds {', '.join(map(str, common))}, "
                  "which each of them ran)", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------- the held-out family

BOOTSTRAP = 10_000          # resamples of the bootstrap intervals
BASELINES = ("fvs", "random")
DISTANCE_RULE = "visibility_sigma_fvs_far+targets"   # the default told the targets before it followed a walk


def pair_differences(tasks: list[dict], name: str, baseline: str, final: bool = True,
                     unit: Callable[[dict], str] = lambda t: t["scene"]) -> dict[str, list[float]]:
    """By scene (or by another `unit` of a task), `name`'s PSNR minus `baseline`'s for each seed that ran
    both: after the last round (final), or the mean over rounds 1..R."""
    def value(run: dict) -> float:
        return run["psnr"][-1] if final else statistics.mean(run["psnr"][1:])
    by_unit: dict[str, list[float]] = {}
    for t in tasks:
        if name in t["runs"] and baseline in t["runs"]:
            by_unit.setdefault(unit(t), []).append(value(t["runs"][name]) - value(t["runs"][baseline]))
    return by_unit


def bootstrap_interval(by_scene: dict[str, list[float]], resamples: int = BOOTSTRAP,
                       seed: int = 0) -> tuple[float, float]:
    """95 % percentile interval of the mean difference, resampling scenes with replacement (each with all
    of its seeds): the seeds of one scene share its layout and cameras, so the scenes are the
    independent draws a default is meant to generalise over."""
    rng = random.Random(seed)
    scenes = sorted(by_scene)
    means = sorted(statistics.fmean([d for scene in rng.choices(scenes, k=len(scenes)) for d in by_scene[scene]])
                   for _ in range(resamples))
    return means[int(0.025 * resamples)], means[int(0.975 * resamples) - 1]


def comparison(tasks: list[dict], name: str, baseline: str, final: bool = True,
               unit: Callable[[dict], str] = lambda t: t["scene"]) -> dict | None:
    """Paired differences of `name` against `baseline` over the family (the bootstrap resamples `unit`s, by
    default scenes with their seeds): pairs, win rate, mean, interval."""
    by_scene = pair_differences(tasks, name, baseline, final, unit)
    diffs = [d for values in by_scene.values() for d in values]
    if len(by_scene) < 2:
        return None
    low, high = bootstrap_interval(by_scene)
    return {"pairs": len(diffs), "scenes": len(by_scene), "wins": sum(d > 0 for d in diffs),
            "mean": statistics.fmean(diffs), "low": low, "high": high}


def targets_markdown(every_seed: dict[str, list[dict]]) -> str:
    """The runs told the target views, scene by scene, paired seed by seed with FVS, random and the default
    told nothing: the mean final difference, its 95 % bootstrap interval over seeds and the seeds ahead."""
    names = sorted({n for tasks in every_seed.values() for t in tasks for n in t["runs"] if variant(n)[2] == TARGETS},
                   key=lambda n: (n != TARGETED, n))     # the default told the targets first
    lines = ["Final PSNR after the last round minus the other run's on the same seed: the mean over the seeds both "
             f"ran, its 95 % bootstrap interval (seeds resampled, {BOOTSTRAP} resamples) and the seeds ahead.", "",
             f"| told the targets | scene | seeds | vs fvs | vs random | vs {DEFAULT_STRATEGY} told nothing |",
             "|---|---|---|---|---|---|"]
    for name in names:
        for scene, tasks in sorted(every_seed.items()):
            seeds = sum(name in t["runs"] for t in tasks)
            cells = []
            for baseline in (*BASELINES, DEFAULT_STRATEGY):
                diffs = pair_differences(tasks, name, baseline).get(scene, [])
                if len(diffs) < 2:      # one seed: its difference, no interval
                    cells.append(f"{diffs[0]:+.2f} (one seed)" if diffs else "")
                    continue
                low, high = bootstrap_interval({str(i): [d] for i, d in enumerate(diffs)})
                cells.append(f"{statistics.fmean(diffs):+.2f} [{low:+.2f}, {high:+.2f}] "
                             f"({sum(d > 0 for d in diffs)} of {len(diffs)})")
            if seeds:
                lines.append(f"| {name} | {scene} | {seeds} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def fold_tasks(args: argparse.Namespace) -> dict[str, dict[int, list[dict]]]:
    """Stored tasks of holdout folds (`scene_fold`), by capture and fold. Fold 0 is the capture's own
    LLFF split, so its tasks are the capture's, of the seeds the other folds ran."""
    tasks = [json.loads(path.read_text()) for path in sorted(args.results.glob("*.json"))]
    tasks = [t for t in tasks if t.get("protocol") == protocol(args)]
    folds: dict[str, dict[int, list[dict]]] = {}
    for task in tasks:
        name, fold = scene_fold(task["scene"])
        if fold is not None:
            folds.setdefault(name, {}).setdefault(fold, []).append(task)
    for name, by_fold in folds.items():
        seeds = {t["seed"] for group in by_fold.values() for t in group}
        by_fold.setdefault(0, [t for t in tasks if t["scene"] == name and t["seed"] in seeds])
    return folds


def folds_markdown(folds: dict[str, dict[int, list[dict]]]) -> str:
    """Each strategy against FVS and random (a run told views: and the default told nothing; told the
    targets: and the default told them too, and its earlier rule) over a capture's holdout folds, and
    random against FVS:
    a fold's seeds share its test views, so the folds are the independent draws (bootstrap over
    folds, each with all of its seeds)."""
    lines = ["Final PSNR after the last round minus the other run's on the same fold and seed: the mean over the "
             f"pairs, its 95 % bootstrap interval (folds resampled with all of their seeds, {BOOTSTRAP} resamples), "
             "the pairs ahead, and the mean difference on each fold (fold 0 is the LLFF split: the scene's tables).",
             "", "| strategy | capture | folds | pairs | vs | mean [95 %] (ahead) | per fold |",
             "|---|---|---|---|---|---|---|"]
    for capture, by_fold in sorted(folds.items()):
        names = sorted({n for tasks in by_fold.values() for t in tasks for n in t["runs"]} - set(BASELINES),
                       key=lambda n: (n != TARGETED, n))
        pairs = [(n, b) for n in names for b in BASELINES + ((DEFAULT_STRATEGY,) if variant(n)[2] else ())
                 + tuple(b for b in (TARGETED, DISTANCE_RULE) if variant(n)[2] == TARGETS and n != b)]
        for name, baseline in pairs + [BASELINES[::-1]]:       # and random against fvs
            diffs = {str(fold): pair_differences(tasks, name, baseline).get(tasks[0]["scene"], [])
                     for fold, tasks in sorted(by_fold.items()) if tasks}
            diffs = {fold: d for fold, d in diffs.items() if d}
            pooled = [d for values in diffs.values() for d in values]
            if len(diffs) < 2:
                continue
            low, high = bootstrap_interval(diffs)
            per_fold = ", ".join(f"{fold}: {statistics.fmean(d):+.2f}" for fold, d in diffs.items())
            lines.append(f"| {name} | {capture} | {len(diffs)} | {len(pooled)} | {baseline} | "
                         f"{statistics.fmean(pooled):+.2f} [{low:+.2f}, {high:+.2f}] "
                         f"({sum(d > 0 for d in pooled)} of {len(pooled)}) | {per_fold} |")
    return "\n".join(lines)


def interval_text(c: dict) -> str:
    return f"{c['mean']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}]"


def noise_floor(args: argparse.Namespace, tasks: list[dict]) -> list[str]:
    """How far the same runs, run again (--repeat-of), land from the first: the floor under every margin."""
    if args.repeat_of is None:
        return []
    first = {(t["scene"], t["seed"]): t for t in tasks}
    gaps, runs = [], 0
    for path in sorted(args.repeat_of.glob("*.json")):
        again = json.loads(path.read_text())
        twin = first.get((again.get("scene"), again.get("seed")))
        for name, run in (again.get("runs") or {}).items():
            if twin and name in twin["runs"]:
                gaps += [abs(a - b) for a, b in zip(run["psnr"], twin["runs"][name]["psnr"])]
                runs += 1
    if not runs:
        return []
    return [f"Noise floor: the same runs again (`--results {args.repeat_of}`, {runs} runs, "
            f"{len(gaps)} PSNR values, every round): the largest difference is {max(gaps):.4f} dB "
            f"({'bit for bit the same' if max(gaps) == 0 else 'not deterministic'}).", ""]


def family_markdown(by_scene: dict[str, list[dict]], args: argparse.Namespace) -> str:
    """A held-out family: each strategy's mean, then every strategy paired with FVS and random."""
    tasks = [t for scene_tasks in by_scene.values() for t in scene_tasks]
    names = sorted({n for t in tasks for n in t["runs"]})
    plans = {p["name"]: p for p in json.loads((args.data / "layouts.json").read_text())["scenes"]} \
        if (args.data / "layouts.json").exists() else {}
    kind = "" if args.family == "held" else f" {args.family}"
    held = args.family == "held"
    told = ("the val split (drawn from the test views' shape, other poses)" if held else
            "the capture's train frames (the walk between the held-out frames, as cup_colmap's)")
    tested = f"the {args.test_views} test views" if held else "every test view (every 8th frame of the walk)"
    lines = [f"Command: `OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 nice -n 5 .venv/bin/python -m bench.bench_nbv "
             f"--family{kind} --jobs 2 --resolution {args.resolution} --iterations {args.iterations} "
             f"--rounds {args.rounds} --seeds {' '.join(map(str, args.seeds))} "
             f"--strategies {' '.join(args.strategies)}` after "
             f"`.venv/bin/python -m bench.nbv_scenes` ({platform.machine()}, {os.cpu_count()} cores shared with "
             f"other work, one thread per task). Protocol: {args.resolution}x{args.resolution} px, "
             f"{args.iterations} iterations, {args.initial} initial views (one by the seed, then FVS), "
             f"{args.per_round} views per round, {args.rounds} rounds, PSNR on {tested}, "
             f"N = {args.samples} masks; `+targets` runs are told {told}. {len(by_scene)} scenes, seeds "
             f"{', '.join(map(str, args.seeds))}.", "",
             "Each strategy's mean over every (scene, seed) task, for the strategies run on all of them (one "
             "tried on part of the family is only paired below, on the tasks it ran):", "",
             "| strategy | runs | mean final PSNR | mean over rounds | cost per candidate |", "|---|---|---|---|---|"]
    everywhere = [n for n in names if all(n in t["runs"] for t in tasks)]
    rows = {n: summary(tasks, n) for n in everywhere}
    for name in sorted(everywhere, key=lambda n: -rows[n]["final"]):
        row = rows[name]
        lines.append(f"| {label(name)} | {row['seeds']} | {row['final']:.2f} | {row['rounds']:.2f} | "
                     f"{cost_text(row)} |")
    lines += ["", "Paired by scene and seed: the strategy's PSNR minus the baseline's (after the last round, and "
              "the mean over rounds), how often it is ahead, and the mean with its 95 % bootstrap interval "
              f"(scenes resampled with their seeds, {BOOTSTRAP} resamples).", "",
              "| strategy | against | pairs | ahead | final: mean [95 % interval] | rounds: mean [95 % interval] |",
              "|---|---|---|---|---|---|"]
    verdict = {}
    # and what the targets add to the default, and the runs told them against the default's earlier rule
    for baseline in (*BASELINES, DEFAULT_STRATEGY, DISTANCE_RULE):
        for name in names:
            final, rounds = comparison(tasks, name, baseline), comparison(tasks, name, baseline, final=False)
            if (name == baseline or name == BASELINES[1] or final is None or rounds is None
                    or (baseline in (DEFAULT_STRATEGY, DISTANCE_RULE) and not variant(name)[2])):
                continue
            verdict[(name, baseline)] = final
            lines.append(f"| {label(name)} | {baseline} | {final['pairs']} ({final['scenes']} scenes) | "
                         f"{final['wins']} of {final['pairs']} | {interval_text(final)} | {interval_text(rounds)} |")
    against_fvs = {n: c for (n, b), c in verdict.items() if b == "fvs" and not variant(n)[2]}
    if against_fvs:     # the default has no targets to go by: chosen among the runs without them
        best = max(against_fvs, key=lambda n: against_fvs[n]["low"])
        default = against_fvs.get(DEFAULT_STRATEGY)
        said = ("" if default is None else
                f"The default `{DEFAULT_STRATEGY}` against FVS: {interval_text(default)} dB final, ahead on "
                f"{default['wins']} of {default['pairs']} pairs; its interval "
                + ("lies above 0. " if default["low"] > 0 else "includes 0 (not shown ahead). "))
        lines += ["", said + f"Highest interval against FVS (by its lower end) of the runs without targets: `{best}` "
                  f"({interval_text(against_fvs[best])} dB)."]
    lines += [""] + noise_floor(args, tasks)
    lines += ["| scene | objects | candidates | test views | " + " | ".join(names) + " |",
              "|---|---|---|---|" + "---|" * len(names)]
    for scene, scene_tasks in sorted(by_scene.items()):
        plan = plans.get(scene, {})
        objects = ", ".join(p["asset"] for p in plan.get("layout", []))
        finals = [summary(scene_tasks, n) for n in names]
        lines.append(f"| {scene} | {objects} | {plan.get('train', '')} | {plan.get('test', '')} | "
                     + " | ".join(f"{r['final']:.2f}" if r else "" for r in finals) + " |")
    lines.append("")
    lines.append("(final PSNR per scene: the mean over its seeds)")
    return "\n".join(lines)


def real_markdown(by_scene: dict[str, list[dict]], args: argparse.Namespace) -> str:
    """The real family: each strategy's mean, every strategy paired with FVS and random (and a run told the
    targets with the default told nothing) capture by capture and seed by seed, the bootstrap over the
    (capture, seed) pairs, then every task's final PSNR and whether each curve rose every round."""
    tasks = [t for scene_tasks in by_scene.values() for t in scene_tasks]
    names = sorted({n for t in tasks for n in t["runs"]}, key=lambda n: (n not in BASELINES, n))
    views = [args.initial + args.per_round * r for r in range(args.rounds + 1)]
    cover = "" if args.cover is None else f" --cover {args.cover}"
    start = (f"{args.initial} initial views (one by the seed, then FVS)" if args.cover is None else
             f"at least {args.initial} initial views (one by the seed, then FVS), more until they see {args.cover:.0%} "
             "of what the test views see (their SfM points; bench_nbv.covering_views): the table's `views` column")
    shared = all(len({r["psnr"][0] for r in t["runs"].values()}) == 1 for t in tasks)
    scenes = "" if tuple(args.scenes) == REAL_CAPTURES else f" --scenes {' '.join(args.scenes)}"
    lines = [f"Command: `PHD_CACHE_DIR=<a directory> OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 nice -n 10 .venv/bin/python "
             f"-m bench.bench_nbv --family real{scenes} --jobs 2 --resolution {args.resolution} --iterations-per-view "
             f"{args.iterations_per_view} --initial {args.initial}{cover} --per-round {args.per_round} "
             f"--rounds {args.rounds} "
             f"--seeds {' '.join(map(str, args.seeds))} --strategies {' '.join(names)}` "
             f"({platform.machine()}, {os.cpu_count()} cores shared with other work, one thread per task; load "
             f"average when this was written: {' '.join(map(str, load_average()))}). Protocol: the captures "
             "read by phd_core.data.load_dataset (distorted ones undistorted by pycolmap), every 8th frame a test "
             f"view, the rest candidates and the `+targets` runs' targets; the widest view {args.resolution} px "
             f"wide, every view at its own aspect; {start}, "
             f"{args.per_round} views per round, {args.rounds} rounds ({' -> '.join(map(str, views))} views "
             f"from {args.initial}); "
             f"training {args.iterations_per_view} iterations per view "
             f"({' -> '.join(str(budget(args, v)) for v in views)}), from scratch every round, deterministic "
             "(bench._harness.pin_determinism); N = "
             f"{args.samples} masks. Round 0 is trained once per (capture, seed) and shared by every strategy: "
             + ("identical in every task." if shared else "NOT identical in some task.") + "", "",
             "| strategy | runs | mean final PSNR | mean over rounds | ranking seconds per round (median) |",
             "|---|---|---|---|---|"]
    for name in names:
        runs = [t["runs"][name] for t in tasks if name in t["runs"]]
        ranking = statistics.median(s for r in runs for s in r["rank_seconds"])
        lines.append(f"| {label(name)} | {len(runs)} | {statistics.fmean(r['psnr'][-1] for r in runs):.2f} | "
                     f"{statistics.fmean(statistics.fmean(r['psnr'][1:]) for r in runs):.2f} | {ranking:.1f} |")
    lines += ["", "Paired capture by capture and seed by seed: the strategy's PSNR minus the other's (after the last "
              "round, and the mean over rounds 1..R), how often it is ahead, and the mean with its 95 % bootstrap "
              f"interval ((capture, seed) pairs resampled, {BOOTSTRAP} resamples).", "",
              "| strategy | against | pairs | ahead | final: mean [95 % interval] | rounds: mean [95 % interval] |",
              "|---|---|---|---|---|---|"]
    def pair(t: dict) -> str:
        return f"{t['scene']} {t['seed']}"
    for name in names:
        for baseline in (*BASELINES, *((DEFAULT_STRATEGY,) if variant(name)[2] else ())):
            final, rounds = (comparison(tasks, name, baseline, last, pair) for last in (True, False))
            if name == baseline or final is None or rounds is None or (name, baseline) == BASELINES[::-1]:
                continue
            lines.append(f"| {label(name)} | {baseline} | {final['pairs']} | {final['wins']} of {final['pairs']} | "
                         f"{interval_text(final)} | {interval_text(rounds)} |")
    lines += ["", "Every task's final PSNR, and the rounds' PSNR where a curve did not rise every round:", "",
              "| capture | seed | candidates | test views | views | round 0 | " + " | ".join(names) + " |",
              "|---|---|---|---|---|---|" + "---|" * len(names)]
    sizes = {scene: [len(load_split(args, scene, split, with_images=False).cameras) for split in ("train", "test")]
             for scene in by_scene}
    for t in tasks:
        cells = []
        for name in names:
            curve = t["runs"].get(name, {}).get("psnr")
            rose = curve is not None and all(b > a for a, b in zip(curve, curve[1:]))
            cells.append("" if curve is None else f"{curve[-1]:.2f}" if rose
                         else f"{curve[-1]:.2f} (not rising: {' / '.join(f'{p:.2f}' for p in curve)})")
        first = next(iter(t["runs"].values()))["psnr"][0]
        counts = " -> ".join(str(len(t["initial"]) + args.per_round * r) for r in range(args.rounds + 1))
        lines.append(f"| {t['scene']} | {t['seed']} | {sizes[t['scene']][0]} | {sizes[t['scene']][1]} | {counts} | "
                     f"{first:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plotted_runs(tasks: list[dict]) -> tuple[list[str], list[int]]:
    """The PLOTTED strategies a scene ran, and the seeds every one of them ran."""
    names = [n for n in PLOTTED if any(n in t["runs"] for t in tasks)]
    return names, [t["seed"] for t in tasks if all(n in t["runs"] for n in names)]


def plots(by_scene: dict[str, list[dict]], args: argparse.Namespace) -> None:
    """PSNR per round of the plotted strategies, over the seeds every one of them ran (so the
    curves share their starting models)."""
    for scene, tasks in by_scene.items():
        names, common = plotted_runs(tasks)
        tasks = [t for t in tasks if t["seed"] in common]
        series = {}
        for name in names:
            row = summary(tasks, name)
            if row:     # views: the mean over the tasks where --cover starts them from more than --initial
                first = statistics.fmean(len(t["initial"]) for t in tasks if name in t["runs"])
                views = [first + args.per_round * r for r in range(len(row["curve"]))]
                series[name] = list(zip(views, row["curve"]))
        svg_plot(args.doc.parent / f"nbv_{scene}{tag(args)}.svg", series, "captured views", "test PSNR (dB)",
                 log_x=False)


def measure_costs(args: argparse.Namespace) -> dict:
    """Seconds per candidate of the product's `rank_views` (dropout statistics for every candidate,
    plus what the strategy needs), every strategy on one initial model, in one run."""
    scene, seed = args.scenes[0], args.seeds[0]
    train_data = load_split(args, scene, "train")
    init = initial_views(train_data.cameras, args.initial, seed)
    renderer = train(train_data, init, budget(args, len(init)), seed)
    captured = [train_data.cameras[i] for i in init]
    candidates = [c for i, c in enumerate(train_data.cameras) if i not in init]
    ratio = calibrated_ratio(renderer, captured)
    phd.rank_views(renderer, candidates[:2], ratio=ratio, samples=args.samples, strategy="fisher", captured=captured)
    targets = target_cameras(args, scene)
    costs = {}
    for name in args.strategies:
        strategy, signal, told = variant(name)
        started = time.perf_counter()
        phd.rank_views(renderer, candidates, ratio=ratio, samples=args.samples, seed=seed, top_k=args.per_round,
                       strategy=strategy, captured=captured, signal=signal, targets=targets if told else None)
        costs[name] = (time.perf_counter() - started) / len(candidates)
        print(f"{name}: {costs[name] * 1000:.1f} ms per candidate", flush=True)
    result = {"scene": scene, "seed": seed, "candidates": len(candidates), "captured": len(captured),
              "splats": renderer.num_units, "samples": args.samples, "resolution": args.resolution,
              "machine": machine(), "seconds_per_candidate": costs}
    write_result(args.results / "costs.json", result)
    return result


def cost_table(args: argparse.Namespace) -> list[str]:
    path = args.results / "costs.json"
    if not path.exists():
        return []
    costs = json.loads(path.read_text())
    base = costs["seconds_per_candidate"].get("fvs")
    lines = ["### What ranking costs", "",
             f"Command: `.venv/bin/python -m bench.bench_nbv --costs --scenes {costs['scene']} --seeds {costs['seed']} "
             f"--strategies {' '.join(costs['seconds_per_candidate'])}`: one {costs['scene']} model from "
             f"{costs['captured']} views ({costs['splats']} splats), {costs['candidates']} candidates at "
             f"{costs['resolution']} px, N = {costs['samples']}, the product's `rank_views` (which reports sigma_max "
             "and sigma_mean for every candidate whatever the strategy), in one run.", "",
             "| strategy | seconds per candidate | vs fvs |", "|---|---|---|"]
    for name, value in sorted(costs["seconds_per_candidate"].items(), key=lambda item: item[1]):
        lines.append(f"| {name} | {value:.4f} | {value / base:.2f}x |" if base else f"| {name} | {value:.4f} | |")
    return lines + [""]


def main() -> None:
    args = parse_args()
    args.results = args.results or RESULTS / f"nbv{tag(args, results=True)}"
    if args.costs:
        measure_costs(args)
        return
    if not args.report:
        tasks = [(scene, seed) for seed in args.seeds for scene in args.scenes]
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            for message in pool.map(run_task, *zip(*tasks), [args] * len(tasks)):
                print(message, flush=True)
    by_scene = load_results(args)
    if args.family == "real":
        write_doc(args.doc, real_markdown(by_scene, args), section=f"nbv{tag(args)}")
        plots(by_scene, args)
        print(f"wrote {args.doc}")
        return
    if args.family:
        write_doc(args.doc, family_markdown(by_scene, args), section=f"nbv{tag(args)}")
        print(f"wrote {args.doc}")
        return
    every_seed = load_results(args, every_seed=True)
    write_doc(args.doc, markdown(by_scene, every_seed, args), section=f"nbv{tag(args)}")
    if any(variant(n)[2] for tasks in every_seed.values() for t in tasks for n in t["runs"]):
        write_doc(args.doc, targets_markdown(every_seed), section=f"nbv{tag(args)}_targets")
    folds = fold_tasks(args)
    if folds:
        write_doc(args.doc, folds_markdown(folds), section=f"nbv{tag(args)}_folds")
    plots(by_scene, args)
    print(f"wrote {args.doc}")


if __name__ == "__main__":
    main()
