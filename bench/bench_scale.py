"""How the cost of ranking and calibration grows with the model: 45k to 3M splats.

    python -m bench.bench_scale [--copies 1 6 22 66] [--sh 0 3] [--widths 100 200 400]
                                [--samples 2 16 64] [--candidates 8] [--coarse-candidates 100]

Models: `tiled_model`, copies of the 45,624-splat synthetic donut of bench_speed.py laid
side by side on a grid in the z = 0 plane, 2.0 apart (a donut is about 2.3 across, so
neighbours overlap), as a user's tiled PLY would be: 1, 6, 22 and 66 copies are 45.6k, 274k,
1.0M and 3.0M splats. SH degree 3 adds seeded view-dependent coefficients to the donut's
colour. Candidates: the ring poses of `donut_200` (radius 4.03 around the centre of the
grid, elevation 10-50 degrees) at W x 3W/4 pixels; the camera sees part of the grid, as in a
room-scale capture. Each model is written to a PLY and read back (the load time is that
read). Per cell: seconds per candidate split by stage (project + cull, depth order, SH colour,
fragments, compositing N masks), peak RSS of the process, and calibration on 8 training
views. Results to bench/results/scale.json; --report writes the tables and plot into
docs/performance.md.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench._harness import (
    DOCS,
    DONUT,
    PHD,
    RESULTS,
    ROOT,
    child,
    donut_cameras,
    load_at_start,
    load_average,
    machine,
    svg_plot,
    tiled_model,
    vm,
    write_result,
)
from phd_core.eval.uq import kendall_tau_b
from phd_core.renderers.gs3d import GaussianRenderer, write_ply
from phd_core.scene import Camera
from phd_core.uq.strategies import DEFAULT_STRATEGY

# ----------------------------------------------------------------------------- one model (child)

def stage_times(renderer, camera: Camera, keeps: dict[int, torch.Tensor]) -> dict:
    """Seconds of each stage of `prepare_view` for one camera (the same calls in the same
    order, timed one by one), then of compositing each keep batch [N, G]."""
    from phd_core.renderers.gs3d.kernels import project_splats, splat_fragments, splat_values
    from phd_core.renderers.gs3d.render import DILATION, front_to_back

    model, clock, out = renderer.model, time.perf_counter, {}
    start = clock()
    means2d, conics, opacities, extents, depths, visible = project_splats(
        model.means, model.quats, model.log_scales, model.opacity_logits, camera, renderer.near, DILATION)
    out["project_s"] = clock() - start
    start = clock()
    ids = front_to_back(visible, depths)
    out["order_s"] = clock() - start
    start = clock()
    splat_fragments(means2d[ids], conics[ids], opacities[ids], extents[ids], camera.width, camera.height,
                    renderer.tile)
    out["fragments_s"] = clock() - start
    start = clock()
    splat_values(model.means, model.sh, ids, camera, depths)
    out["colour_s"] = clock() - start
    start = clock()
    view = renderer.prepare(camera)                     # the whole stage 1-3, for the renders below
    out["prepare_s"] = clock() - start
    for n, keep in keeps.items():
        start = clock()
        view.render(keep)
        out[f"composite{n}_s"] = clock() - start
    out["visible"], out["fragments"] = len(view.units), len(view.alpha)
    return out


def measure_model(copies: int, sh: int, widths: list[int], samples: list[int], candidates: int,
                  calibration_views: int, calibration_widths: list[int], ratio: float) -> dict:
    """Everything measured for one model, in this (fresh) process."""
    from phd_core import uq
    from phd_core.renderers import load_model

    with tempfile.TemporaryDirectory() as tmp:
        ply = Path(tmp) / "tiled.ply"
        write_ply(tiled_model(copies, sh), ply)
        gc.collect()
        start = time.perf_counter()
        renderer = load_model(ply)
        out = {"copies": copies, "sh": sh, "splats": renderer.num_units, "ply_mb": round(ply.stat().st_size / 2**20, 1),
               "load_s": round(time.perf_counter() - start, 3), "rss_after_load_mb": rss_mb("VmRSS")}
    warm = donut_cameras(20, 15, 1)[0]
    renderer.prepare(warm).render(torch.ones(2, renderer.num_units, dtype=torch.bool))   # kernels loaded
    keeps = {n: uq.keep_masks(uq.dropout_uniforms(renderer.num_units, n, 0), ratio) for n in samples}
    out["cells"] = []
    for width in widths:
        height = width * 3 // 4
        cameras = donut_cameras(width, height, candidates)
        stages = [stage_times(renderer, camera, keeps) for camera in cameras]
        mean = {key: sum(s[key] for s in stages) / len(stages) for key in stages[0]}
        for n in samples:
            start = time.perf_counter()
            uq.uncertainty(renderer, cameras, ratio=ratio, samples=n)
            per_candidate = (time.perf_counter() - start) / len(cameras)
            out["cells"].append({"width": width, "height": height, "samples": n,
                                 "seconds_per_candidate": round(per_candidate, 4),
                                 **{k: round(mean[k], 4) for k in ("project_s", "order_s", "fragments_s", "colour_s",
                                                                    "prepare_s")},
                                 "composite_s": round(mean[f"composite{n}_s"], 4),
                                 "visible": round(mean["visible"]), "fragments": round(mean["fragments"])})
            print(copies, sh, out["cells"][-1], flush=True)
        if calibration_views and width in calibration_widths:
            training = donut_cameras(width, height, calibration_views, "train")
            start = time.perf_counter()
            try:
                result = uq.calibrate(renderer, training)
                r_drop = result.r_drop
            except uq.CalibrationError:
                r_drop = 0.0
            out.setdefault("calibration", []).append({"width": width, "height": height, "views": len(training),
                                                      "seconds": round(time.perf_counter() - start, 3),
                                                      "r_drop": r_drop})
            print(copies, sh, out["calibration"][-1], flush=True)
    out["peak_rss_mb"] = rss_mb("VmHWM")
    return out


def rss_mb(field: str) -> int:
    """This process's resident set (VmRSS) or its peak (VmHWM), MiB."""
    return round(vm(os.getpid(), field) / 2**20)


# ----------------------------------------------------------------------------- the target

def phd_rank(ply: Path, candidates: Path, out: Path, width: int, height: int, samples: int, ratio: float,
             pythonpath: str | None = None, strategy: str | None = None) -> dict:
    """`phd rank` of the candidates in a child process: wall, user, system seconds, peak RSS;
    with `pythonpath`, the phd_core found there (an older checkout) instead of this one; with
    `strategy`, that strategy instead of the checkout's default."""
    env = {"PYTHONPATH": pythonpath} if pythonpath else None
    chosen = ["--strategy", strategy] if strategy else []
    return child(PHD + ["rank", "--model", str(ply), "--candidates", str(candidates), "--width", str(width),
                        "--height", str(height), "--samples", str(samples), "--dropout-ratio", str(ratio),
                        *chosen, "--out", str(out)], env, Path(pythonpath) if pythonpath else ROOT)


BASELINE_STRATEGY = "fvs_sigma_floor"   # the default strategy of the code before issue 24 (a0bdc7c)


def rank_target(copies: int, sh: int, candidates: int, width: int, samples: int, ratio: float,
                baseline: str | None) -> dict:
    """The issue's case: `phd rank` of `candidates` ring poses at width x 3/4 width, N = samples,
    on the tiled model, whole process (load included): before (the checkout at `baseline`, its
    default strategy), now with that same strategy (the same work), and now with today's default."""
    with tempfile.TemporaryDirectory() as tmp:
        ply = Path(tmp) / "tiled.ply"
        write_ply(tiled_model(copies, sh), ply)
        frames = json.loads((DONUT / "transforms_test.json").read_text())
        frames["frames"] = frames["frames"][:candidates]
        poses = Path(tmp) / "candidates.json"
        poses.write_text(json.dumps(frames))
        height = width * 3 // 4
        out = {"copies": copies, "sh": sh, "candidates": candidates, "width": width, "height": height,
               "samples": samples, "ratio": ratio}
        runs = [("now", None, BASELINE_STRATEGY), ("now, default strategy", None, None)]
        if baseline is not None:
            runs.insert(0, ("before", baseline, None))
        for name, path, strategy in runs:
            out[name] = phd_rank(ply, poses, Path(tmp) / "ranking.json", width, height, samples, ratio, path, strategy)
            out[name]["strategy"] = strategy or (BASELINE_STRATEGY if path else DEFAULT_STRATEGY)
            out[name]["order"] = json.loads((Path(tmp) / "ranking.json").read_text())["order"]
            print("rank target", name, {k: v for k, v in out[name].items() if k != "order"}, flush=True)
        if baseline is not None:
            out["same_order"] = out["before"]["order"] == out["now"]["order"]
    return out


# ----------------------------------------------------------------------------- profile

def profile(copies: int, sh: int, width: int, samples: int, cameras: int, ratio: float, top: int = 10) -> dict:
    """cProfile of `prepare` + a render of `samples` masks for `cameras` ring poses: the
    functions with the most CPU time of their own (both threads), in seconds per camera."""
    import cProfile
    import pstats

    from phd_core import uq

    renderer = GaussianRenderer(tiled_model(copies, sh))
    poses = donut_cameras(width, width * 3 // 4, cameras + 1)
    keep = uq.keep_masks(uq.dropout_uniforms(renderer.num_units, samples, 0), ratio)
    renderer.prepare(poses[0]).render(keep)                                      # kernels loaded
    profiler = cProfile.Profile(time.process_time)       # CPU seconds: the machine may be shared
    start, cpu = time.perf_counter(), time.process_time()
    profiler.enable()
    for camera in poses[1:]:
        renderer.prepare(camera).render(keep)
    profiler.disable()
    wall, cpu = (time.perf_counter() - start) / cameras, (time.process_time() - cpu) / cameras
    stats = pstats.Stats(profiler).stats                   # {(file, line, name): (cc, nc, tottime, cumtime, callers)}
    rows = sorted(((f"{Path(f).parent.name}/{Path(f).name}:{name}" if line else name, v[2] / cameras)
                   for (f, line, name), v in stats.items()), key=lambda x: -x[1])[:top]
    return {"copies": copies, "sh": sh, "splats": renderer.num_units, "width": width, "height": width * 3 // 4,
            "samples": samples, "cameras": cameras, "seconds_per_camera": round(wall, 3),
            "cpu_seconds_per_camera": round(cpu, 3),
            "top": [(name, round(sec, 4)) for name, sec in rows]}


# ----------------------------------------------------------------------------- coarse to fine

def agreement(full: list[int], other: list[int], ks: tuple[int, ...] = (1, 5, 10)) -> dict:
    """How far the order `other` agrees with `full` (candidate indices, best first): the share
    of full's top k that other's top k holds, and Kendall's tau-b of the two rank positions."""
    position = {i: r for r, i in enumerate(other)}
    out = {f"top{k}_overlap": len(set(full[:k]) & set(other[:k])) / k for k in ks}
    out["kendall_tau"] = kendall_tau_b(list(range(len(full))), [position[i] for i in full])
    return out


def coarse_trade(copies: int, sh: int, candidates: int, width: int, samples: int, ratio: float,
                 scales: list[float], refines: list[int], strategies: list[str]) -> dict:
    """Rank `candidates` ring poses at full size, then coarse to fine at each scale and number
    re-scored: seconds and agreement with the full-size order, per strategy (the captured
    poses are 16 training poses of donut_200)."""
    from phd_core import uq

    renderer = GaussianRenderer(tiled_model(copies, sh))
    renderer.training_cameras = donut_cameras(width, width * 3 // 4, 16, "train")
    cameras = donut_cameras(width, width * 3 // 4, candidates)
    renderer.prepare(cameras[0].resized(20, 15)).render()                       # kernels loaded
    out = {"copies": copies, "sh": sh, "splats": renderer.num_units, "candidates": len(cameras), "width": width,
           "height": width * 3 // 4, "samples": samples, "ratio": ratio, "rows": []}
    for strategy in strategies:
        def rank(**coarse):
            start = time.process_time()                    # CPU seconds: the machine may be shared
            order = [v.index for v in uq.rank_views(renderer, cameras, ratio=ratio, samples=samples,
                                                    strategy=strategy, **coarse)]
            return order, time.process_time() - start
        full, full_s = rank()
        out["rows"].append({"strategy": strategy, "coarse": None, "refine": None, "seconds": round(full_s, 2)})
        print(out["rows"][-1], flush=True)
        for scale in scales:
            for refine in refines:
                order, seconds = rank(coarse=scale, refine=refine)
                out["rows"].append({"strategy": strategy, "coarse": scale, "refine": refine,
                                    "seconds": round(seconds, 2), "speed_up": round(full_s / seconds, 2),
                                    **{k: round(v, 3) for k, v in agreement(full, order).items()}})
                print(out["rows"][-1], flush=True)
    return out


# ----------------------------------------------------------------------------- driver

def in_child(kind: str, baseline: str | None = None, **kwargs) -> dict:
    """Run `measure_model`, `coarse_trade` or `profile` (kind) in a fresh process, so its peak
    RSS and its memory are its own; returns what it returned. With `baseline`, a directory
    holding an older phd_core, that one is imported."""
    # The bench package always comes from this checkout (a baseline holds phd_core and phd_cli only).
    code = (f"import sys, json, bench.bench_scale as b; "
            f"print('RESULT ' + json.dumps(b.{kind}(**json.loads(sys.argv[1]))))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([baseline, str(ROOT)])} if baseline else None
    proc = subprocess.run([sys.executable, "-c", code, json.dumps(kwargs)], cwd=baseline or ROOT, env=env,
                          capture_output=True, text=True)
    sys.stdout.write(proc.stdout.replace("RESULT ", "result ")[-3000:])
    if proc.returncode != 0:
        raise RuntimeError(f"{kind}({kwargs}) failed: {proc.stderr[-3000:]}")
    return json.loads(next(line for line in proc.stdout.splitlines() if line.startswith("RESULT "))[7:])


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--copies", type=int, nargs="*", default=[1, 6, 22, 66], help="donut copies per model")
    parser.add_argument("--sh", type=int, nargs="+", default=[0, 3], help="SH degrees")
    parser.add_argument("--widths", type=int, nargs="+", default=[100, 200, 400], help="candidate widths (height 3/4)")
    parser.add_argument("--samples", type=int, nargs="+", default=[2, 16, 64], help="masks N")
    parser.add_argument("--candidates", type=int, default=6, help="ring poses timed per cell")
    parser.add_argument("--calibration-views", type=int, default=8, help="training views calibrated on (0: skip)")
    parser.add_argument("--calibration-widths", type=int, nargs="+", default=[100, 200],
                        help="calibrate at these of --widths")
    parser.add_argument("--ratio", type=float, default=0.5, help="dropout ratio of the timed renders")
    parser.add_argument("--target", type=int, nargs="*", default=None, metavar="COPIES",
                        help="also the issue's case: `phd rank` of 100 candidates, SH 3, 200x150, N = 16, on models "
                             "of COPIES donuts (default 22: 1M splats)")
    parser.add_argument("--baseline", default=None, metavar="DIR",
                        help="with --target: a directory holding an older phd_core (e.g. `git archive main phd_core "
                             "phd_cli | tar -x -C DIR`), run as 'before'")
    parser.add_argument("--coarse", action="store_true", help="also the coarse-to-fine trade (1M splats SH 3)")
    parser.add_argument("--profile", action="store_true",
                        help="also cProfile prepare + render (N = 16) of 4 cameras, 1M splats SH 3, 200x150 "
                             "(and of --baseline's code)")
    parser.add_argument("--profile-name", default="now", help="the profile's label in the JSON and the docs")
    parser.add_argument("--coarse-scales", type=float, nargs="+", default=[0.5, 0.25])
    parser.add_argument("--coarse-refines", type=int, nargs="+", default=[10, 20])
    parser.add_argument("--coarse-candidates", type=int, default=100)
    parser.add_argument("--coarse-strategies", nargs="+", default=["sigma_max", DEFAULT_STRATEGY])
    parser.add_argument("--target-candidates", type=int, default=100)
    parser.add_argument("--json", type=Path, default=RESULTS / "scale.json")
    parser.add_argument("--out", type=Path, default=DOCS / "performance.md")
    parser.add_argument("--report-only", action="store_true", help="rewrite the docs from --json")
    parser.add_argument("--note", help="how and on which code the run was made (kept in the JSON, shown in the docs)")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    results = json.loads(args.json.read_text()) if args.json.exists() else {}
    if args.note:
        results["note"] = args.note
    if args.report_only:
        if args.note:
            write_result(args.json, results)
        write_report(args.out, results)
        return
    results["machine"] = machine()
    command = "python -m bench.bench_scale " + " ".join(sys.argv[1:])
    results["commands"] = [c for c in results.get("commands", []) if c != command] + [command]
    models = results.setdefault("models", {})
    for copies in args.copies:
        for sh in args.sh:
            models[f"{copies}x_sh{sh}"] = in_child(
                "measure_model", copies=copies, sh=sh, widths=args.widths, samples=args.samples,
                candidates=args.candidates, calibration_views=args.calibration_views,
                calibration_widths=args.calibration_widths, ratio=args.ratio)
            write_result(args.json, results)                # a partial run keeps what it measured
    for copies in ([22] if args.target == [] else args.target or []):
        results.setdefault("targets", {})[str(copies)] = rank_target(copies, 3, args.target_candidates, 200, 16,
                                                                     args.ratio, args.baseline)
        write_result(args.json, results)
    if args.profile:
        runs = ({args.profile_name: None} if args.baseline is None
                else {"before": args.baseline, args.profile_name: None})
        results.setdefault("profile", {}).update(
            {name: in_child("profile", baseline=path, copies=22, sh=3, width=200, samples=16, cameras=4,
                            ratio=args.ratio) for name, path in runs.items()})
        write_result(args.json, results)
    if args.coarse:
        results["coarse"] = in_child("coarse_trade", copies=22, sh=3, candidates=args.coarse_candidates, width=200,
                                     samples=16, ratio=args.ratio, scales=args.coarse_scales,
                                     refines=args.coarse_refines, strategies=args.coarse_strategies)
    results["machine"]["load_average_at_end"] = load_average()
    write_result(args.json, results)
    write_report(args.out, results)
    print(f"written {args.json} and {args.out}")



# ----------------------------------------------------------------------------- report

SECTION = "## Scale: 45k to 3M splats"
STAGE_COLUMNS = ("project + cull s | depth order s | SH colour s | fragments s | composite N = 16 s | visible splats | "
                 "fragments")
SECTION_END = "<!-- end of bench/bench_scale.py's section -->"


def write_report(path: Path, results: dict) -> None:
    """Replace this benchmark's section of `path` (appended at the end the first time) and draw
    docs/scale_time.svg."""
    old = path.read_text() if path.exists() else ""
    if SECTION in old:
        head, rest = old.split(SECTION, 1)
        tail = rest.split(SECTION_END, 1)[1] if SECTION_END in rest else ""
    else:
        head, tail = old.rstrip() + "\n\n", ""
    path.write_text(head + report(results) + tail)
    cells = [(m["splats"], m["sh"], c) for m in results.get("models", {}).values() for c in m["cells"]]
    series = {}
    for splats, sh, c in sorted(cells, key=lambda x: x[0]):
        if c["samples"] == 16:
            series.setdefault(f"SH {sh}, {c['width']} px", []).append(
                (round(splats / 1000), c["seconds_per_candidate"]))
    svg_plot(path.parent / "scale_time.svg", series, "thousand splats (log)", "s per candidate, N = 16", log_y=True)


OLD_NOTE = ("**The machine was shared with a long benchmark holding both cores and this one ran at nice 19**, so "
            "absolute times are pessimistic (a 45k-splat camera that prepares in 0.025 s on the idle machine of the "
            "tables above took 0.1-0.2 s here); compare within this section.")


def command_now(recorded: str) -> str:
    """A recorded command as it is typed now (runs before bench/_harness.py started the file as a script)."""
    return recorded.replace("python bench/" + "bench_scale.py", "python -m bench.bench_scale", 1)


def report(r: dict) -> str:
    m = r["machine"]
    models = sorted(r.get("models", {}).values(), key=lambda x: (x["splats"], x["sh"]))
    load = [f"| {x['splats']:,} | {x['sh']} | {x['ply_mb']:.0f} | {x['load_s']:.2f} | {x['rss_after_load_mb']:,} | "
            f"{x['peak_rss_mb']:,} |" for x in models]
    samples = sorted({c["samples"] for x in models for c in x["cells"]})
    rows = []
    for x in models:
        for width in sorted({c["width"] for c in x["cells"]}):
            cells = {c["samples"]: c for c in x["cells"] if c["width"] == width}
            c = next(iter(cells.values()))
            mid = cells.get(16, c)
            rows.append(f"| {x['splats']:,} | {x['sh']} | {width}x{c['height']} | "
                        + " | ".join(f"{cells[n]['seconds_per_candidate']:.3f}" if n in cells else "" for n in samples)
                        + f" | {c['project_s']:.3f} | {c['order_s']:.3f} | {c['colour_s']:.3f} | "
                          f"{c['fragments_s']:.3f} | {mid['composite_s']:.3f} | {c['visible']:,} | "
                          f"{c['fragments']:,} |")
    calibration = [f"| {x['splats']:,} | {x['sh']} | {c['width']}x{c['height']} | {c['views']} | {c['seconds']:.2f} | "
                   f"{c['r_drop']} |" for x in models for c in x.get("calibration", [])]
    text = f"""{SECTION}

Measured by `bench/bench_scale.py` (issue 24); raw numbers in `bench/results/scale.json`. Commands
(one after another, each adding to the JSON; the baseline directory holds `git archive a0bdc7c
phd_core phd_cli`, the code before issue 24):

{chr(10).join('    ' + command_now(c).replace('python ', '.venv/bin/python ', 1) for c in r['commands'])}

Machine: {m['cpus']} cores, {m['platform']}, Python {m['python']}, torch {m['torch']}; load average
{load_at_start(m)} at the start and {m.get('load_average_at_end')} at the end. {r.get('note', OLD_NOTE)}

Models (`tiled_model` in the benchmark): copies of the 45,624-splat synthetic donut side by side
on a grid 2.0 apart (a donut is 2.3 across, so neighbours overlap), SH 3 with seeded higher
coefficients; candidates: the donut_200 ring poses at W x 3W/4, which see part of the grid (the
visible and fragment counts below). Each model is written as a PLY and loaded by `load_model`
in a fresh process; peak RSS is that process's, over every cell of its row group.

What a camera costs, and what issue 24 changed. Stage 1 (`kernels.project_splats`) already
culled before anything else and is unchanged: a splat is dropped when its centre is behind the
near plane, when 255 x opacity <= 1 (it can never reach alpha 1/255), or when the box of its
alpha >= 1/255 ellipse misses the image; that box is opacity-aware (half-sizes
sqrt(2 ln(255 opacity) cov_xx) and sqrt(2 ln(255 opacity) cov_yy), not 3 sigma), so faint
splats get small boxes. Only the survivors are sorted, coloured and rasterised. Changed:

- SH colour was already evaluated for the survivors only, but in torch: a [V, 16, 3] gather and
  some 30 small ops, each a parallel region that waits for both threads. On this shared machine
  that was half of a 1M-splat SH-3 camera's wall time (an early cProfile: 1.0 of 2.3 s), though
  only about 15 % of its CPU time (the profile below).
  It is compiled now (`kernels.splat_values`, float64, one visible splat per step), with
  `render.splat_colors` (`splats.eval_sh`) as its tested twin at 1e-5.
- Fragments: the alpha of every tile/splat pair at each pixel of its tile is compiled
  (`kernels._pair_alpha`) into a [pairs, 16] array that a second kernel (`_gather`) scans.
  Fusing the two (count each pixel's fragments, then write each alpha into its slot, no
  [pairs, 16] array) was tried and measured: it cost 0.50 CPU s per camera against 0.34 for
  the two kernels (1M splats, 200x150, one thread, the same 5.1M fragments, three rounds), as
  every pair is evaluated twice; so the two kernels stay. Since then the first lists the pairs
  splat by splat and leaves the exp to one vectorised call ("Fragments listed splat by splat"
  below: 1.4-1.5x on this stage at 1M splats); the note above says which code each table ran.

What is left grows with the fragments: every visible splat at every pixel where its alpha
reaches 1/255, hidden ones included. They cannot be cut at `prepare`: a keep-mask may drop
the splats in front, and a prepared view serves any masks. Nor did evaluating them lazily pay
(each alpha computed inside the compositing pass, down to where a pixel's last mask stops;
"Tried: alphas inside the compositing pass" below): 16 masks at ratio 0.5 still composite
about half of a 1M-splat view's fragments and 91 % of the 45k donut's.

![seconds per candidate against splats](scale_time.svg)

{missing_note(models)}
### Load and memory

| splats | SH | PLY MB | load s | RSS after load MB | peak RSS MB |
|---|---|---|---|---|---|
{chr(10).join(load)}

### Seconds per candidate

Whole candidate (`uq.uncertainty` over the candidates: prepare, N masked renders, zeta) for each N,
then the mask-independent stages of `prepare_view` one by one and compositing N = 16, mean over
the candidates.

| splats | SH | size | {' | '.join(f'N = {n} s' for n in samples)} | {STAGE_COLUMNS} |
|---|---|---|{'---|' * len(samples)}---|---|---|---|---|---|---|
{chr(10).join(rows)}

### Calibration

`uq.calibrate` (defaults) on training poses of donut_200 at the size given.

| splats | SH | size | views | seconds | r_drop |
|---|---|---|---|---|---|
{chr(10).join(calibration)}
"""
    if "profile" in r:
        text += profile_report(r["profile"])
    for t in sorted(r.get("targets", {}).values(), key=lambda t: -t["copies"]):
        text += target_report(t)
    if "coarse" in r:
        text += coarse_report(r["coarse"])
    return text + "\n" + SECTION_END + "\n"


def missing_note(models: list[dict]) -> str:
    """A line naming the default grid's models this run did not measure."""
    done = {(x["copies"], x["sh"]) for x in models}
    missing = [f"{copies * 45_624:,} splats SH {sh}" for copies in (1, 6, 22, 66) for sh in (0, 3)
               if (copies, sh) not in done]
    return f"\nNot measured in this run: {', '.join(missing)}.\n" if missing else ""


def target_report(t: dict) -> str:
    runs = [(name, t[name]) for name in ("before", "now", "now, default strategy") if name in t]
    rows = [f"| {name} | {x.get('strategy', BASELINE_STRATEGY)} | {x['wall_s']:.1f} | {x['user_s']:.1f} | "
            f"{x['system_s']:.1f} | {(x['user_s'] + x['system_s']) / 2:.1f} | {x['peak_rss_mb']:,} |"
            for name, x in runs]
    same = ""
    if "same_order" in t:
        same = (f"\nBefore and now (the same strategy) ranked the candidates "
                f"{'identically' if t['same_order'] else 'NOT identically'}.\n")
    return f"""
### The issue's case: `phd rank`, {t['candidates']} candidates, {t['copies'] * 45_624:,} splats SH {t['sh']}

{t['width']}x{t['height']}, N = {t['samples']}, --dropout-ratio {t['ratio']}, whole process (start-up and load
included); "before" is the code before issue 24 (the merge base, run from a `git archive` of it)
with its default strategy, "now" this code with that same strategy (the same work), and "now,
default strategy" with today's default, which adds a visibility pass per view and the coverage
selection; all in the same run. Target: < 30 s for 100 candidates. On a shared machine the CPU
seconds are the fairer figure.

| code | strategy | wall s | user s | system s | CPU s / 2 cores | peak RSS MB |
|---|---|---|---|---|---|---|
{chr(10).join(rows)}
{same}"""


def profile_report(runs: dict) -> str:
    first = next(iter(runs.values()))
    size = f"{first['width']}x{first['height']}"
    parts = []
    for name, x in runs.items():
        rows = "\n".join(f"| `{fn}` | {sec:.3f} |" for fn, sec in x["top"])
        parts.append(f"**{name}**: {x['cpu_seconds_per_camera']:.2f} CPU s per camera ({x['seconds_per_camera']:.2f} s "
                     f"wall) under cProfile\n\n| function | CPU s per camera (own time) |\n|---|---|\n{rows}\n")
    return f"""
### Where a camera's time goes: {first['splats']:,} splats SH {first['sh']}, {size}, N = {first['samples']}

cProfile of `prepare` and one render of N masks for {first['cameras']} ring poses (`profile` in the
benchmark; "before" is the code before issue 24, from a `git archive` of it). The runs were
minutes apart on a machine whose load changed (the wall times say how much): compare CPU seconds.

""" + "\n".join(parts)


def coarse_report(c: dict) -> str:
    best = max((x for x in c["rows"] if x["coarse"] is not None), key=lambda x: x["speed_up"], default=None)
    verdict = ("no setting was measured" if best is None else
               f"the best setting measured here, scale {best['coarse']} with {best['refine']} re-scored, ran at "
               f"{best['speed_up']:.2f}x the speed of full size (CPU) and kept {best['top5_overlap']:.0%} of its top 5")
    rows = []
    for x in c["rows"]:
        if x["coarse"] is None:
            rows.append(f"| {x['strategy']} | full size only | | {x['seconds']:.1f} | 1.00x | | | | |")
        else:
            tau = "" if x["kendall_tau"] is None else f"{x['kendall_tau']:.2f}"
            rows.append(f"| {x['strategy']} | {x['coarse']} | {x['refine']} | {x['seconds']:.1f} | "
                        f"{x['speed_up']:.2f}x | "
                        f"{x['top1_overlap']:.2f} | {x['top5_overlap']:.2f} | {x['top10_overlap']:.2f} | {tau} |")
    return f"""
### Coarse to fine

`rank_views(..., coarse=scale, refine=m)` (`phd rank --coarse --refine`, REST `coarse`, `refine`):
every candidate ranked at `scale` times its size, the best m again at full size. {c['candidates']}
ring candidates at {c['width']}x{c['height']}, N = {c['samples']}, {c['splats']:,} splats SH {c['sh']}; agreement
with the full-size ranking of the same strategy: the share of its top k found in the top k, and
Kendall's tau-b of the two orders over all candidates.

| strategy | coarse scale | re-scored m | CPU s | speed-up | top-1 | top-5 | top-10 | Kendall tau |
|---|---|---|---|---|---|---|---|---|
{chr(10).join(rows)}

Coarse to fine stays off by default: {verdict}. A coarse render saves only what grows with the
pixels (fragments, compositing); projection, depth order and SH colour of every visible splat
cost the same at any size, and the re-scored candidates are prepared a second time.
"""


if __name__ == "__main__":
    main()
