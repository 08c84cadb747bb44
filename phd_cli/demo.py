"""`phd demo`: the README's main job, end to end, on the bundled lego_200 scene.

1. Train (or reuse from the output folder) two 3DGS models on disjoint 16-view sets of
   the train split at 100x100.
2. Start the service on a free 127.0.0.1 port and, through the Python client: upload
   both models with their training cameras, calibrate them, rank 100 held-out candidate
   views (test split) for model A, and choose per view between A and B.
3. Check the answers against the ground truth: each candidate's true RMSE (model A's
   render against the test image), the Spearman correlation between sigma_max and RMSE,
   and the PSNR of A, B, the selection and the per-view oracle.
4. Write report.json, heat maps and renders of the top 5 into the output folder.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from phd_core.errors import InputError
from phd_core.renderers import DEFAULT_FAMILY, FAMILIES

from .report import add_progress_args, bars_on

DEFAULT_OUT = Path("phd-demo")
DOWNSCALE = 2            # lego_200 is 200x200: 100x100 renders
TRAIN_VIEWS = 16
CANDIDATES = 100
TOP = 5
# 500 steps train a 16-view model to about 24-25 dB at 100x100 in about a minute on 2 cores
# (600 steps: 25.0 dB in 137 s on a loaded machine); --iterations 0 takes the trainer's
# default (2000 steps, 27.7 dB). Trained models are cached in the output folder.
DEMO_ITERATIONS = 500
DEMO_SAMPLES = 8


def default_data() -> Path:
    import phd_core

    return (Path(phd_core.__file__).resolve().parents[1] / ".." / "shared" / "data" / "lego_200").resolve()


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo", help="train, serve, rank and select on the bundled lego scene (a few minutes)",
        description=f"Train (or reuse) two models of the default family ({DEFAULT_FAMILY}) on disjoint 16-view sets "
                    "of lego_200 at 100x100, start "
                    "the service, then through the Python client calibrate, rank 100 held-out views "
                    "(top 5 printed next to their true RMSE) and select per view between the two models. "
                    "Writes report.json and heat maps into --out.")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default ./phd-demo); "
                        "trained models are cached here and reused when the settings match")
    parser.add_argument("--data", type=Path, default=None, help="Blender-layout scene (default: the bundled "
                        "lego_200 in ../shared/data)")
    parser.add_argument("--iterations", type=int, default=DEMO_ITERATIONS,
                        help=f"training iterations per model (default {DEMO_ITERATIONS}, to finish in minutes; "
                             "0 = the trainer's default)")
    parser.add_argument("--samples", type=int, default=DEMO_SAMPLES,
                        help=f"dropout samples N per view (default {DEMO_SAMPLES})")
    parser.add_argument("--candidates", type=int, default=CANDIDATES,
                        help=f"held-out candidate views to rank (default {CANDIDATES})")
    parser.add_argument("--retrain", action="store_true", help="train even when a cached model matches")
    add_progress_args(parser)
    parser.set_defaults(func=run)


# ----------------------------------------------------------------------------- steps

def _train(data: Path, views: list[int], iterations: int | None, out: Path, retrain: bool, name: str,
           bars: bool) -> Path:
    """Train a model of the default family on `views` of the train split, or reuse a
    cached one whose sidecar (written by the trainer) records the same scene, views and
    iterations (with the trainer's default iterations, None, it always trains)."""
    from phd_core.renderers.splats import read_sidecar

    family = FAMILIES[DEFAULT_FAMILY]
    model = out / "models" / f"{name}{family.extension}"
    if not retrain and iterations is not None and model.is_file():
        try:
            sidecar = read_sidecar(model) or {}
        except InputError:
            sidecar = {}
        settings = sidecar.get("settings") or {}
        if (sidecar.get("dataset") == str(data) and sidecar.get("view_indices") == views
                and sidecar.get("downscale") == DOWNSCALE and settings.get("iterations") == iterations
                and settings.get("seed") == 0):
            print(f"  {name}: reusing {model} ({sidecar.get('num_splats')} splats, "
                  f"trained in {sidecar.get('train_seconds')} s)")
            return model
    model.parent.mkdir(parents=True, exist_ok=True)
    print(f"  {name}: training {iterations or 'the default'} iterations on train views {views} ...", flush=True)
    family.train(data, views=views, downscale=DOWNSCALE, iterations=iterations, seed=0, out=model, progress=bars)
    return model


def _progress(label: str, bars: bool):
    """A job-progress callback that redraws one line: '  label  42.0%' (None: bars are off, as on a
    stdout that is not a terminal, where each redraw would stay in the file)."""
    if not bars:
        return None

    def show(fraction: float) -> None:
        print(f"\r  {label} {100 * fraction:5.1f}%", end="\n" if fraction >= 1 else "", flush=True)
    return show


def _true_errors(model_path: Path, cameras, images) -> tuple[list[float], list[float], list[float], list]:
    """Per view RMSE, PSNR and SSIM of the model's full render against the ground truth, and the renders."""
    from phd_core.eval import psnr, rmse, ssim
    from phd_core.renderers import load_model

    renderer = load_model(model_path)
    renders = [renderer.render(camera)[0] for camera in cameras]
    return ([rmse(r, t) for r, t in zip(renders, images)], [psnr(r, t) for r, t in zip(renders, images)],
            [float(ssim(r, t)) for r, t in zip(renders, images)], renders)


def run(args: argparse.Namespace) -> int:
    import base64

    from client import Calibration, PHDClient, RankResult, SelectResult
    from phd_core.data import load_blender, select_views, split_size
    from phd_core.eval import ensemble_efficiency, spearman
    from phd_core.io import write_bytes_atomic, write_json_atomic, write_png
    from service.runner import BackgroundServer
    from service.settings import Settings

    data = (args.data or default_data()).resolve()
    if not (data / "transforms_train.json").is_file():
        raise InputError("data", f"no Blender scene at {data} (expected transforms_train.json); give --data")
    if args.samples < 2:
        raise InputError("samples", f"must be at least 2, got {args.samples}")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 2)
        clock = now

    # Two disjoint 16-view training sets: evenly spaced frames, and the same shifted by 3.
    train_total, test_total = split_size(data, "train"), split_size(data, "test")
    views_a = select_views(train_total, TRAIN_VIEWS)
    views_b = [(i + 3) % train_total for i in views_a]
    if set(views_a) & set(views_b):
        raise InputError("data", f"the train split ({train_total} frames) is too small for two disjoint view sets")
    candidates_idx = select_views(test_total, min(args.candidates, test_total))
    print(f"phd demo: scene {data}, output {out}")
    print("1/5 models")
    iterations = args.iterations or None
    bars = bars_on(args)
    model_a = _train(data, views_a, iterations, out, args.retrain, "model_a", bars)
    model_b = _train(data, views_b, iterations, out, args.retrain, "model_b", bars)
    lap("train_or_reuse")

    train_a = load_blender(data, "train", downscale=DOWNSCALE, views=views_a, with_images=False).cameras
    train_b = load_blender(data, "train", downscale=DOWNSCALE, views=views_b, with_images=False).cameras
    test = load_blender(data, "test", downscale=DOWNSCALE, views=candidates_idx)
    with tempfile.TemporaryDirectory(prefix="phd-demo-service-") as service_dir, \
            BackgroundServer(Settings(data_dir=Path(service_dir),
                                      max_candidates=max(1000, len(test.cameras)))) as server:
        print(f"2/5 service on {server.url} (data in a temporary folder)")
        with PHDClient(server.url) as phd:
            info_a = phd.upload_model(model_a, cameras=train_a, name="lego A")
            info_b = phd.upload_model(model_b, cameras=train_b, name="lego B")
            print(f"  uploaded A: {info_a.num_units} splats, B: {info_b.num_units} splats")
            lap("service_upload")
            print("3/5 calibrate (Algorithm 1 on the 16 training poses)", flush=True)
            cal_a = phd.calibrate(info_a.id, run_async=True, progress=_progress("A", bars))
            cal_b = phd.calibrate(info_b.id, run_async=True, progress=_progress("B", bars))
            assert isinstance(cal_a, Calibration) and isinstance(cal_b, Calibration)  # wait=True: the results
            print(f"  r_drop A = {cal_a.r_drop}, B = {cal_b.r_drop}")
            lap("calibrate")
            print(f"4/5 rank {len(test.cameras)} held-out views (test split), N = {args.samples}", flush=True)
            ranking = phd.rank(info_a.id, test.cameras, samples=args.samples, run_async=True,
                               progress=_progress("rank", bars))
            assert isinstance(ranking, RankResult)
            lap("rank")
            top = ranking.views[:TOP]
            maps = phd.rank(info_a.id, [test.cameras[v.index] for v in top], samples=args.samples,
                            heatmaps="base64")
            assert isinstance(maps, RankResult)
            lap("heatmaps")
            print("5/5 select between A and B per view", flush=True)
            selection = phd.select(info_a.id, info_b.id, test.cameras, samples=args.samples, run_async=True,
                                   progress=_progress("select", bars))
            assert isinstance(selection, SelectResult)
            lap("select")

    rmse_a, psnr_a, ssim_a, renders_a = _true_errors(model_a, test.cameras, test.images)
    _, psnr_b, ssim_b, _ = _true_errors(model_b, test.cameras, test.images)
    lap("ground_truth")

    by_view = {v.index: v for v in ranking.views}
    rmse_rank = {i: r for r, i in enumerate(sorted(range(len(rmse_a)), key=lambda i: -rmse_a[i]), 1)}
    rho = spearman([by_view[i].sigma_max for i in range(len(rmse_a))], rmse_a)
    rho_score = spearman([by_view[i].score for i in range(len(rmse_a))], rmse_a)
    text = lambda value: "undefined" if value is None else f"{value:.3f}"  # noqa: E731
    print(f"\nTop {TOP} candidates to capture next with {ranking.strategy} (of {len(test.cameras)}; over all, "
          f"Spearman(score, RMSE) = {text(rho_score)}, Spearman(sigma_max, RMSE) = {text(rho)}):")
    print(f"  {'rank':>4}  {'test view':>9}  {'score':>9}  {'sigma_max':>9}  {'true RMSE':>9}  {'RMSE rank':>9}")
    heat_dir = out / "heatmaps"
    heat_dir.mkdir(exist_ok=True)
    top_rows = []
    heatmap_of = {v.index: v for v in maps.views}          # maps.views index into the top list
    for k, view in enumerate(top):
        mapped = heatmap_of[k]
        frame = candidates_idx[view.index]
        print(f"  {view.rank:>4}  {frame:>9}  {view.score:9.4f}  {view.sigma_max:9.4f}  {rmse_a[view.index]:9.4f}  "
              f"{rmse_rank[view.index]:>9}")
        stem = f"rank{view.rank}_test{frame:03d}"
        assert mapped.heatmap_png is not None           # asked for with heatmaps="base64"
        write_bytes_atomic(heat_dir / f"{stem}_zeta.png", base64.b64decode(mapped.heatmap_png))
        write_png(heat_dir / f"{stem}_render.png", renders_a[view.index])
        assert test.images is not None                  # load_blender reads the images by default
        write_png(heat_dir / f"{stem}_truth.png", test.images[view.index])
        top_rows.append({"rank": view.rank, "test_view": frame, "score": view.score, "sigma_max": view.sigma_max,
                         "rmse": rmse_a[view.index], "rmse_rank": rmse_rank[view.index],
                         "heatmap": f"heatmaps/{stem}_zeta.png"})

    chosen = [psnr_a[v.index] if v.choice == "a" else psnr_b[v.index] for v in selection.views]
    chosen_ssim = [ssim_a[v.index] if v.choice == "a" else ssim_b[v.index] for v in selection.views]
    mean = lambda xs: sum(xs) / len(xs)  # noqa: E731
    summary = {"psnr_a": mean(psnr_a), "psnr_b": mean(psnr_b), "psnr_selected": mean(chosen),
               "psnr_oracle": mean([max(a, b) for a, b in zip(psnr_a, psnr_b)]),
               "e_me": ensemble_efficiency(chosen_ssim, ssim_a, ssim_b), "rule": selection.rule,
               "choices": selection.counts,
               "choice_matches_higher_psnr": mean([(v.choice == "a") == (psnr_a[v.index] >= psnr_b[v.index])
                                                   for v in selection.views])}
    print(f"\nEnsemble selection over {len(selection.views)} views: A chosen {selection.counts['a']}x, "
          f"B {selection.counts['b']}x; mean PSNR A {summary['psnr_a']:.2f}, B {summary['psnr_b']:.2f}, "
          f"selected {summary['psnr_selected']:.2f} (oracle {summary['psnr_oracle']:.2f}) dB; rule "
          f"{selection.rule}, E_ME {text(summary['e_me'])}")

    report = {
        "data": str(data), "downscale": DOWNSCALE, "samples": args.samples, "iterations": args.iterations,
        "train_views": {"a": views_a, "b": views_b}, "candidate_test_views": candidates_idx,
        "models": {"a": info_a.model_dump(mode="json"), "b": info_b.model_dump(mode="json")},
        "calibration": {"a": cal_a.model_dump(mode="json"), "b": cal_b.model_dump(mode="json")},
        "strategy": ranking.strategy, "spearman_score_rmse": rho_score, "spearman_sigma_max_rmse": rho,
        "top": top_rows,
        "ranking": [{"rank": v.rank, "test_view": candidates_idx[v.index], "score": v.score, "sigma_max": v.sigma_max,
                     "sigma_mean": v.sigma_mean, "rmse": rmse_a[v.index]} for v in ranking.views],
        "selection": {**summary, "views": [{"test_view": candidates_idx[v.index], "choice": v.choice,
                                            "score_a": v.score_a, "score_b": v.score_b,
                                            "psnr_a": psnr_a[v.index], "psnr_b": psnr_b[v.index]}
                                           for v in selection.views]},
        "timings_s": timings,
    }
    write_json_atomic(out / "report.json", report)
    total = sum(timings.values())
    print("\nTimes (s): " + ", ".join(f"{k} {v}" for k, v in timings.items()) + f"; total {total:.1f}")
    print(f"Output folder: {out}  (report.json, heatmaps/)")
    print("\nNext, with your own model or these:\n" + "\n".join(next_steps(model_a)))
    return 0


def next_steps(model: Path, port: int = 8000) -> list[str]:
    """The three commands after the demo: the service, its page, the Python client on `model`."""
    url = f"http://127.0.0.1:{port}"
    client = (f"from client import PHDClient; phd = PHDClient('{url}'); m = phd.upload_model('{model}'); "
              "phd.calibrate(m.id); print([(v.rank, v.index, round(v.score, 4)) for v in "
              "phd.rank(m.id, candidates='orbit:32', top_k=5).views])")
    return [f"  phd serve --port {port}        # the service (leave it running)",
            f"  {url}/ui/        # the page: upload {model.name} with {model.with_suffix('.json').name}, "
            "calibrate, rank",
            f'  python -c "{client}"        # the Python client: the 5 poses to capture next']
