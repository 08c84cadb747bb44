"""`phd calibrate`, `phd uq`, `phd rank` and `phd select`: PH-Dropout from the command line.

Thin wrappers: parse arguments, load the model and cameras, call `phd_core.uq`,
print a summary and write JSON (and heat maps) atomically.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from phd_core import uq as phd
from phd_core.data import POSES, candidate_name, export_cameras, export_convention, load_cameras, source_pose
from phd_core.errors import InputError
from phd_core.eval import image_uq_metrics, mean_defined, spearman
from phd_core.executors import LOCAL, Executor, make_executor
from phd_core.io import ModelCache, write_heatmap, write_json_atomic
from phd_core.io.heatmap import check_vmax
from phd_core.renderers import DEFAULT_SIGNAL, SIGNALS, signals_help
from phd_core.scene import Camera
from phd_core.uq.calibrate import check_calibration
from phd_core.uq.candidates import GENERATORS
from phd_core.uq.rank import check_rank
from phd_core.uq.sampling import check_ratio, check_samples
from phd_core.uq.strategies import DEFAULT_STRATEGY, STRATEGIES, STRATEGY_ADVICE
from phd_core.uq.strategies.captured import CapturedStore

from .models import OpenedModel, check_cameras_see, check_capture, model_views, open_model
from .options import add_background_arg, add_other_capture_arg, model_help
from .report import TABLE_ROWS, add_progress_args, calibrated, progress_bar, rank_table


def register(subparsers: argparse._SubParsersAction) -> None:
    calibrate = subparsers.add_parser(
        "calibrate", help="find r_drop for a model (Algorithm 1)",
        description="Raise the dropout ratio in steps while the mean absolute change of the training views "
                    "stays below epsilon; print r_drop and the error curve, and store the result beside the model "
                    "(MODEL.phd-cache/, or .phd-cache/ in a trainer's folder), where `phd rank`, `uq` and `select` "
                    "find it when they calibrate on the same cameras with the same settings. Cameras: --data "
                    "(its train split; a trainer's folder: its run's), --cameras JSON, else "
                    "the training cameras stored with the model.")
    _add_model_args(calibrate)
    source = calibrate.add_mutually_exclusive_group()
    source.add_argument("--data", type=Path, help="the capture the model was trained on (another is refused): "
                        "calibrate on the poses of its --split")
    source.add_argument("--cameras", type=Path, help="training poses: transforms-style JSON (or a list of frames), "
                        "a reference cameras.json, a COLMAP model or poses_bounds.npy")
    calibrate.add_argument("--split", default="train", help="dataset split with --data (default train)")
    calibrate.add_argument("--views", type=int, default=None, help="use this many evenly spaced frames of --data")
    _add_camera_size_args(calibrate)
    _add_calibration_args(calibrate, standalone=True)
    _add_executor_args(calibrate)
    calibrate.add_argument("--out", type=Path, help="also write the result as JSON to this file")
    add_other_capture_arg(calibrate)
    add_progress_args(calibrate)
    calibrate.set_defaults(func=run_calibrate)

    uq = subparsers.add_parser(
        "uq", help="uncertainty report of a dataset split: sigma-max-bar, per-view sigma_max, heat maps",
        description="Calibrate (or reuse the stored calibration, or take --dropout-ratio), render --samples "
                    "masked copies of every view of the split and write report.json and one heat map per view into "
                    "--out. With the split's images: Spearman, Pearson and AUSE between zeta and the error.")
    _add_model_args(uq)
    uq.add_argument("--data", type=Path, default=None, help="the capture the model was trained on, wherever it lies "
                    "now (default: the one its sidecar or checkpoint names; for a trainer's folder the capture its "
                    "run read); another is refused")
    uq.add_argument("--split", default="test", help="split to evaluate (default test; a trainer's folder on its "
                    "own capture: the frames its run held out)")
    uq.add_argument("--views", type=int, default=None, help="evaluate this many evenly spaced frames")
    _add_camera_size_args(uq, sizes=False)
    _add_uncertainty_args(uq)
    _add_calibration_args(uq)
    _add_executor_args(uq)
    uq.add_argument("--vmax", type=float, default=None,
                    help="heat-map scale: zeta at or above this is the top colour (default: the largest "
                         "sigma_max of the report, shared by every map)")
    uq.add_argument("--no-heatmaps", action="store_true", help="write only report.json")
    uq.add_argument("--out", type=Path, default=Path("phd-uq"), help="output directory (default phd-uq)")
    add_other_capture_arg(uq)
    add_progress_args(uq)
    uq.set_defaults(func=run_uq)

    rank = subparsers.add_parser(
        "rank", help="rank candidate camera poses for the next capture (the first is the one to capture first)",
        description="Render every candidate pose under --samples dropout masks and order the candidates by "
                    f"--strategy (default {DEFAULT_STRATEGY}, the active-learning benchmark's winner, docs/nbv.md); "
                    "every candidate reports sigma_max, sigma_mean and the strategy's score. The ratio is "
                    "--dropout-ratio, else the stored calibration (`phd calibrate`), else calibrated now on the "
                    "model's training cameras and stored. Prints a table of the first --top-k (or "
                    f"{TABLE_ROWS}) with each pose's centre and viewing direction; JSON with --json or --out.")
    _add_model_args(rank)
    rank.add_argument("--candidates", required=True,
                      help="a generator spec NAME[:COUNT][,key=value...] (" + ", ".join(GENERATORS) + "; e.g. "
                      "orbit:64, see `phd candidates`), placed around the model's training cameras; or a file: "
                      "transforms-style JSON or a list of frames (needs w/h, or give --width/--height), or any "
                      "capture (all its frames)"),
    rank.add_argument("--strategy", choices=sorted(STRATEGIES), default=DEFAULT_STRATEGY,
                      help="; ".join(f"{name}: {s.summary}" for name, s in sorted(STRATEGIES.items()))
                      + ". " + STRATEGY_ADVICE)
    rank.add_argument("--captured", type=Path, default=None,
                      help="JSON of the poses already captured (default: the model's training cameras)")
    rank.add_argument("--targets", default=None, metavar="FILE|GENERATOR",
                      help="the views the model will be looked at from (a walkthrough path, a turntable ring), as "
                      "--candidates takes them (a file, a capture or a generator spec such as orbit:32): the coverage "
                      "strategies weigh each part of the model by what these views show of it; default: every view "
                      "alike")
    rank.add_argument("--top-k", type=int, default=None,
                      help="keep only the first k: a batch meant to be captured together")
    rank.add_argument("--coarse", type=float, default=None, metavar="SCALE",
                      help="coarse to fine: rank every candidate at SCALE (0-1) times its size first, then re-rank "
                           "the best --refine at full size (price and agreement: docs/performance.md)")
    rank.add_argument("--refine", type=int, default=None,
                      help="with --coarse: candidates re-ranked at full size (default 20 %% of them, at least --top-k)")
    _add_camera_size_args(rank)
    _add_uncertainty_args(rank)
    _add_calibration_args(rank)
    _add_executor_args(rank)
    rank.add_argument("--out", type=Path, help="write the ranking JSON here (default: print a table); every ranked "
                      "candidate carries its camera (a transforms frame) and, when the model's cameras came from "
                      "a known source, the same pose in that source's convention (source_pose)")
    rank.add_argument("--json", action="store_true", help="print the ranking JSON (that --out writes) instead of "
                      "the table")
    rank.add_argument("--export", type=Path, metavar="FILE",
                      help="also write the ranked batch (the first --top-k, else all) for a capture tool: a *.json "
                           "file is a nerfstudio transforms.json, a file named transforms_train.json a Blender one "
                           "(camera_angle_x), one named cameras.json the reference trainer's, a path without a suffix "
                           "a COLMAP text model folder (or say --export-format)")
    rank.add_argument("--export-format", choices=sorted(POSES), default=None,
                      help="the convention of --export, instead of reading it off the name")
    add_progress_args(rank)
    rank.set_defaults(func=run_rank)

    select = subparsers.add_parser(
        "select", help="per view, which of two models to trust (ensemble selection)",
        description="Render every view under --samples dropout masks of each model (each at its own ratio) "
                    "and choose, per view, the model with the lower score under --rule. With a split's images: "
                    "PSNR/SSIM of a, b and the selection.")
    select.add_argument("--model-a", type=Path, required=True, help="the first model: " + model_help())
    select.add_argument("--model-b", type=Path, required=True, help="the second model")
    add_background_arg(select, "splat models: the colour both are rendered over (default: each model's own)")
    views = select.add_mutually_exclusive_group()
    views.add_argument("--data", type=Path, help="the capture both models were trained on (another is refused): the "
                       "views of its --split (default: the one model a names)")
    views.add_argument("--cameras", type=Path, help="the views: transforms-style JSON, a cameras.json, any capture")
    select.add_argument("--split", default="test", help="split of --data (default test; model a's run's own when "
                        "it is a trainer's folder on its capture)")
    select.add_argument("--views", type=int, default=None, help="this many evenly spaced frames of --data")
    select.add_argument("--rule", choices=list(phd.SELECTION_RULES), default=phd.DEFAULT_SELECTION_RULE,
                        help=phd.rules_help())
    _add_camera_size_args(select)
    _add_uncertainty_args(select)
    _add_calibration_args(select)
    select.add_argument("--ratio-a", type=float, default=None, help="model a's ratio (default --dropout-ratio, "
                        "else calibrated on its training cameras)")
    select.add_argument("--ratio-b", type=float, default=None, help="model b's ratio (likewise)")
    _add_executor_args(select)
    select.add_argument("--out", type=Path, help="write the selection JSON here (default: print it)")
    add_other_capture_arg(select)
    add_progress_args(select)
    select.set_defaults(func=run_select)


# ---------------------------------------------------------------------------------------- arguments

def _add_model_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, required=True, help=model_help())
    add_background_arg(parser, "splat models: the colour to render over (default: the one the model came with: "
                       "its sidecar's or cfg_args', else white)")


def _add_camera_size_args(parser: argparse.ArgumentParser, sizes: bool = True) -> None:
    parser.add_argument("--downscale", type=float, default=1.0,
                        help="render at 1/F of each camera's resolution (default 1)")
    if sizes:
        parser.add_argument("--width", type=int, default=None, help="image width for frames without w/h")
        parser.add_argument("--height", type=int, default=None, help="image height for frames without w/h")


def _add_calibration_args(parser: argparse.ArgumentParser, *, standalone: bool = False) -> None:
    group = parser.add_argument_group("calibration")
    group.add_argument("--epsilon", type=float, default=phd.DEFAULT_EPSILON,
                       help=f"mean absolute error allowed on the training views (default {phd.DEFAULT_EPSILON})")
    group.add_argument("--step", type=float, default=phd.DEFAULT_STEP,
                       help=f"dropout-ratio step (default {phd.DEFAULT_STEP})")
    samples_flag = "--samples" if standalone else "--calibration-samples"
    group.add_argument(samples_flag, dest="calibration_samples", metavar="N", type=int,
                       default=phd.DEFAULT_CALIBRATION_SAMPLES,
                       help=f"masks per ratio (default {phd.DEFAULT_CALIBRATION_SAMPLES})")
    group.add_argument("--method", choices=("linear", "bisection"), default="linear",
                       help="linear scan (Algorithm 1) or bisection over the same nested masks")
    group.add_argument("--signal", choices=list(SIGNALS), default=DEFAULT_SIGNAL,
                       help="what the calibration error and zeta are measured on (default "
                            f"{DEFAULT_SIGNAL}, the paper's): {signals_help()}")
    if standalone:
        group.add_argument("--seed", type=int, default=0, help="mask seed (default 0)")
    else:
        ratio = group.add_mutually_exclusive_group()
        ratio.add_argument("--dropout-ratio", type=float, default=None,
                           help="skip calibration and use this ratio")
        ratio.add_argument("--recalibrate", action="store_true",
                           help="calibrate again even when a calibration with these settings is stored beside the "
                                "model (and store the new one)")


def _add_uncertainty_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--samples", type=int, default=phd.DEFAULT_SAMPLES,
                        help=f"dropout masks per view (default {phd.DEFAULT_SAMPLES})")
    parser.add_argument("--seed", type=int, default=0, help="mask seed (default 0)")


def _add_executor_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ray", metavar="auto|local|ADDRESS", default=None,
                        help="render on a Ray cluster (pip install '.[ray]'; docs/scale-out.md): auto = the "
                             "cluster `ray start` runs here (or RAY_ADDRESS), local = a private one on this "
                             "machine, else its address (host:6379, ray://host:10001). Same result as without")


# ---------------------------------------------------------------------------------------- helpers

def _executor(args: argparse.Namespace) -> Executor:
    return LOCAL if args.ray is None else make_executor("ray", args.ray)


def _check_settings(args: argparse.Namespace) -> None:
    """The command's numbers, checked before a model is opened, read or calibrated, so that a
    typo in any of them costs no calibration and stores none."""
    check_calibration(args.epsilon, args.step, args.calibration_samples, args.seed, args.method, args.signal)
    if hasattr(args, "samples"):                       # uq, rank, select: zeta is a std over the masks
        check_samples(args.samples, ddof=1)
    for name in ("dropout_ratio", "ratio_a", "ratio_b"):
        if getattr(args, name, None) is not None:
            check_ratio(getattr(args, name), name)
    if getattr(args, "vmax", None) is not None:         # uq's heat-map scale
        check_vmax(args.vmax)


def _views(args: argparse.Namespace, model: OpenedModel, warnings: list[str]):
    """The views of --split (of --data, or of a trainer folder's own capture) with their images
    composited over what the model renders over (so errors compare like with like), or without
    images (and a warning) when the split has none."""
    background = tuple(model.renderer.describe().get("background") or (1.0, 1.0, 1.0))
    options = dict(views=args.views, downscale=args.downscale, background=background, other_capture=args.other_capture)
    try:
        return model_views(model, args.data, args.split, **options)
    except InputError as exc:
        if not exc.field.endswith("file_path"):
            raise
        warnings.append(f"images of split {args.split!r} not available ({exc}): no error metrics")
        return model_views(model, args.data, args.split, with_images=False, **options)


def _scaled(cameras: list[Camera], downscale: float) -> list[Camera]:
    return cameras if downscale == 1 else [c.scaled(downscale) for c in cameras]


def _training_cameras(model: OpenedModel, downscale: float) -> list[Camera]:
    cameras = model.renderer.training_cameras
    if not cameras:
        raise InputError("cameras", "the model carries no training cameras: give --data or --cameras "
                         "(calibrate), or --dropout-ratio")
    return _scaled(list(cameras), downscale)


def _ratio(args: argparse.Namespace, model: OpenedModel, cameras: list[Camera] | None = None
           ) -> tuple[float, dict[str, Any] | None]:
    """--dropout-ratio, else r_drop on `cameras` (default: the model's training cameras): the
    stored calibration unless --recalibrate, else calibrated now. The calibration comes back as
    a dict (None when the ratio was given)."""
    if args.dropout_ratio is not None:
        return args.dropout_ratio, None
    result = calibrated(args, model, cameras or _training_cameras(model, args.downscale),
                        reuse=not args.recalibrate)
    return result.r_drop, result.to_dict()


def _candidates(args: argparse.Namespace, renderer, field: str = "candidates") -> list[Camera]:
    """--candidates (or --targets, `field`): a file or capture when the path exists, else a generator spec."""
    spec = getattr(args, field)
    path = Path(spec)
    if path.exists():
        return load_cameras(path, split="all", width=args.width, height=args.height)
    if "/" in spec or spec.lower().endswith((".json", ".npy")):
        raise InputError(field, f"no such file: {path}")
    from .candidates import make

    poses = make(spec, renderer)
    if args.width is not None or args.height is not None:
        if args.width is None or args.height is None:
            raise InputError("width", "give --width and --height together")
        poses = [c.resized(args.width, args.height) for c in poses]
    return poses


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, data)


def _emit(out: Path | None, data: Any, summary: str) -> None:
    """The result as JSON on stdout, or written to `out` with a one-line summary."""
    if out is None:
        print(json.dumps(data, indent=2, allow_nan=False))
    else:
        _write_json(out, data)
        print(f"{summary}; written to {out}")


def _print_curve(result: phd.CalibrationResult | phd.CalibrationError, file=None) -> None:
    file = file or sys.stdout
    print("  ratio   error", file=file)
    for ratio, error in zip(result.ratios, result.errors):
        print(f"  {ratio:5.3f}   {error:.6f}", file=file)


# ---------------------------------------------------------------------------------------- commands

def run_calibrate(args: argparse.Namespace) -> int:
    _check_settings(args)
    args.executor = _executor(args)
    model = open_model(args.model, args.background)
    if args.data is not None:
        cameras = model_views(model, args.data, args.split, views=args.views, downscale=args.downscale,
                              with_images=False, other_capture=args.other_capture).cameras
    elif args.cameras is not None:
        cameras = _scaled(load_cameras(args.cameras, width=args.width, height=args.height), args.downscale)
        check_cameras_see(model, cameras, args.other_capture)
    else:
        cameras = _training_cameras(model, args.downscale)
    try:
        result = calibrated(args, model, cameras, reuse=False)
    except phd.CalibrationError as exc:
        _print_curve(exc, file=sys.stderr)
        raise
    print(f"r_drop = {result.r_drop}  ({result.method}, {result.signal}, epsilon {result.epsilon}, "
          f"step {result.step}, {result.samples} masks, {len(cameras)} views, {model.renderer.num_units} units)")
    _print_curve(result)
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if args.out is not None:
        _write_json(args.out, result.to_dict())
    return 0


def run_uq(args: argparse.Namespace) -> int:
    _check_settings(args)
    args.executor = _executor(args)
    model = open_model(args.model, args.background)
    renderer = model.renderer
    warnings: list[str] = []
    dataset = _views(args, model, warnings)
    calibration_cameras = None
    if args.dropout_ratio is None and not renderer.training_cameras:
        # No stored training poses: calibrate on the dataset's train split instead.
        warnings.append("the model carries no training cameras: calibrated on every frame of the dataset's "
                        "train split, which may include views the model was not trained on")
        calibration_cameras = model_views(model, args.data, "train", downscale=args.downscale,
                                          with_images=False, other_capture=args.other_capture).cameras
    ratio, calibration = _ratio(args, model, calibration_cameras)
    if calibration is not None:
        warnings.extend(calibration["warnings"])

    with progress_bar(args, f"uq {len(dataset.cameras)} views x {args.samples} masks") as progress:
        views = phd.uncertainty(renderer, dataset.cameras, ratio=ratio, samples=args.samples, seed=args.seed,
                                keep_maps=True, executor=args.executor, signal=args.signal, progress=progress)
    vmax = args.vmax if args.vmax is not None else max(v.sigma_max for v in views)
    rows = []
    for i, (view, camera, index) in enumerate(zip(views, dataset.cameras, dataset.indices)):
        row: dict[str, Any] = {"index": index, "sigma_max": view.sigma_max, "sigma_mean": view.sigma_mean}
        assert view.zeta is not None  # measured with keep_maps=True
        if dataset.images is not None:
            render = renderer.render(camera)[0]
            # zeta's colour channels against the error of the colour (premultiplied: alpha's is left out)
            row.update(image_uq_metrics(view.zeta[..., :3], render, dataset.images[i]))
        if not args.no_heatmaps:
            name = f"heatmaps/{args.split}_{index:04d}.png"
            row["heatmap"] = name
            row["heatmap_vmax"] = write_heatmap(args.out / name, view.zeta, vmax if vmax > 0 else None)
        rows.append(row)

    sigma_bar = phd.sigma_max_bar(views)
    report: dict[str, Any] = {
        "model": renderer.describe(), "data": str(dataset.root), "split": args.split,
        "dropout_ratio": ratio, "r_drop": calibration["r_drop"] if calibration else None,
        "calibration": calibration, "signal": args.signal, "samples": args.samples, "seed": args.seed,
        "ddof": 1,
        "sigma_max_bar": sigma_bar,
        "heatmap_scale": None if args.no_heatmaps else "zeta max over channels / heatmap_vmax, clipped to [0, 1]",
        "views": rows, "warnings": warnings,
    }
    if dataset.images is not None:
        report["summary"] = {
            key: mean_defined([r[key] for r in rows])
            for key in ("spearman", "pearson", "ause_rmse", "ause_mse", "ause_mae", "rmse")}
        report["summary"]["spearman_sigma_max_vs_rmse"] = spearman([r["sigma_max"] for r in rows],
                                                                   [r["rmse"] for r in rows])
    _write_json(args.out / "report.json", report)
    print(f"dropout ratio {ratio}, sigma-max-bar {sigma_bar:.6f} over {len(rows)} views of {args.split}; "
          f"report: {args.out / 'report.json'}")
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


def run_rank(args: argparse.Namespace) -> int:
    _check_settings(args)
    if args.export is not None:
        export_convention(args.export, args.export_format)
    args.executor = _executor(args)
    model = open_model(args.model, args.background)
    renderer = model.renderer
    poses = _candidates(args, renderer)                     # at their own size: what a capture rig is told
    candidates = _scaled(poses, args.downscale)             # what is rendered
    captured = None
    if args.captured is not None:
        # Frames without w/h take the candidates' image size: the coverage strategies render them.
        captured = load_cameras(args.captured, width=args.width or poses[0].width,
                                height=args.height or poses[0].height)
    # Targets render at the candidates' size (the service's rule too), whatever their photos' size.
    targets = None if args.targets is None else phd.targets_at_size(_candidates(args, renderer, "targets"), candidates)
    check_rank(renderer, args.strategy, args.top_k, args.coarse, args.refine, targets)
    ratio, calibration = _ratio(args, model)                # every input is known good before calibrating
    # What the captured views saw is kept beside the model (computed once per model and set of poses).
    store = (CapturedStore(ModelCache(args.model), default=renderer.training_cameras)
             if STRATEGIES[args.strategy].uses_visibility else None)
    with progress_bar(args, f"rank {len(candidates)} candidates x {args.samples} masks") as progress:
        ranked = phd.rank_views(renderer, candidates, ratio=ratio, samples=args.samples, seed=args.seed,
                                top_k=args.top_k, strategy=args.strategy, captured=captured, executor=args.executor,
                                coarse=args.coarse, refine=args.refine, signal=args.signal, progress=progress,
                                captured_store=store, targets=targets)
    if store is not None and store.cache.skipped:
        print(f"warning: {store.cache.skipped}", file=sys.stderr)
    convention = renderer.describe().get("camera_format")
    result = {"strategy": args.strategy, "rule": ranked.rule, "signal": args.signal, "dropout_ratio": ratio,
              "calibration": calibration,
              "samples": args.samples, "seed": args.seed, "coarse": args.coarse,
              "candidates": len(candidates), "targets": None if targets is None else len(targets),
              "order": [r.index for r in ranked], "camera_format": convention,
              "ranking": [{**r.to_dict(), "camera": poses[r.index].to_frame(),
                           "source_pose": source_pose(poses[r.index], convention)} for r in ranked]}
    if args.out is not None:
        _write_json(args.out, result)
    if args.export is not None:
        written = export_cameras(args.export, [poses[r.index] for r in ranked],
                                 [candidate_name(r.rank, r.index) for r in ranked], args.export_format)
        print(f"exported {len(ranked)} poses as {written.writes} ({written.name}) to {args.export}",
              file=sys.stderr if args.json else sys.stdout)         # stdout carries only the JSON
    summary = f"ranked {len(candidates)} candidates ({args.strategy}: {ranked.rule}) at dropout ratio {ratio}"
    if args.json:
        print(json.dumps(result, indent=2, allow_nan=False))
    elif args.out is not None:
        print(f"{summary}; first: {result['order'][:5]}; written to {args.out}")
    else:
        rows = len(ranked) if args.top_k is not None else min(TABLE_ROWS, len(ranked))
        print(f"{summary}; capture first (centres and viewing directions in the model's frame):")
        print("\n".join(rank_table(ranked, poses, rows)))
        if rows < len(ranked):
            print(f"... {len(ranked) - rows} more: --top-k N for a batch of N, --json or --out for every candidate")
    return 0


def run_select(args: argparse.Namespace) -> int:
    _check_settings(args)
    args.executor = _executor(args)
    models = {key: open_model(getattr(args, f"model_{key}"), args.background) for key in ("a", "b")}
    warnings: list[str] = []
    if args.cameras is not None:
        cameras = _scaled(load_cameras(args.cameras, split="all", width=args.width, height=args.height),
                          args.downscale)
        images = None
    else:
        dataset = _views(args, models["a"], warnings)
        check_capture(models["b"], args.data if args.data is not None else dataset.root, args.other_capture)
        cameras, images = dataset.cameras, dataset.images
    ratios: dict[str, float] = {}
    calibrations: dict[str, dict[str, Any] | None] = {}
    for key, model in models.items():
        given = getattr(args, f"ratio_{key}")
        ratios[key], calibrations[key] = (given, None) if given is not None else _ratio(args, model)
    with progress_bar(args, f"select over {len(cameras)} views x {args.samples} masks") as progress:
        result = phd.select_models(models["a"].renderer, models["b"].renderer, cameras, ratio_a=ratios["a"],
                                   ratio_b=ratios["b"], samples=args.samples, seed=args.seed, images=images,
                                   rule=args.rule, executor=args.executor, signal=args.signal, progress=progress)
    counts = {key: sum(v.choice == key for v in result.views) for key in ("a", "b")}
    report = {"rule": args.rule, "signal": args.signal, "ratio_a": ratios["a"], "ratio_b": ratios["b"],
              "calibration_a": calibrations["a"],
              "calibration_b": calibrations["b"], "samples": args.samples, "seed": args.seed, "counts": counts,
              **result.to_dict(), "warnings": warnings}
    _emit(args.out, report, f"{len(cameras)} views ({args.rule}): a trusted for {counts['a']}, b for {counts['b']}")
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0
