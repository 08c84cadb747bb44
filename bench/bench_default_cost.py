"""What the default strategy costs against the paper's rule (issue 34): `phd rank`, whole process.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_default_cost --before main [--only donut nerf 1m ...]
        [--count C] [--runs "before default" "now sigma_max" ...] [--out FILE]
    .venv/bin/python -m bench.bench_default_cost --before main --report FILE...   (the docs' table)

Per scene, `phd rank` in a child process (start-up and load included) of the scene's candidates,
by the code at `--before` (a `git archive` of its phd_core and phd_cli) and by this checkout:
with `sigma_max` (the paper's rule) and with the default strategy (`visibility_sigma_fvs`), the
latter twice now: with no stored coverage ("cold": the captured views are rendered and stored
beside the model) and again ("warm": they are read). Scenes, each with its 100 training cameras
as the captured set (from a sidecar or the checkpoint):

- donut: the 45,624-splat SH-3 donut of `tiled_model`, donut_200's cameras, 60 ring
  candidates at 100x100, N = 16;
- nerf: a positional-encoding NeRF (all cells occupied: every sample evaluated) with
  lego_200's training cameras, 30 test poses at 100x100, N = 32;
- 1m: 22 tiled copies (1,003,728 splats SH 3), donut_200's cameras, 100 candidates at
  200x150, N = 16; 1m-uncaptured: the same without training cameras (issue 24's case).

Both orders are compared (the same candidates in the same order). Writes
bench/results/default_cost.json and the table between the `bench:default-cost` markers of
docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from bench import _harness as harness
from bench._harness import (
    DOCS,
    PHD,
    RESULTS,
    ROOT,
    child,
    load_average,
    machine,
    tiled_model,
    write_doc,
    write_result,
)
from phd_core.data import load_blender
from phd_core.renderers.gs3d import SIDECAR_FORMAT, sidecar_path, write_ply
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField, save_nerf

SCENES = {   # name: (candidate source, candidates, width, height, samples)
    "donut": (harness.DONUT, 60, 100, 100, 16),
    "nerf": (harness.LEGO, 30, 100, 100, 32),
    "1m": (harness.DONUT, 100, 200, 150, 16),
    "1m-uncaptured": (harness.DONUT, 100, 200, 150, 16),
}
RATIO = 0.5
RUNS = {  # label: (strategy, by the code before)
    "before sigma_max": ("sigma_max", True), "before default": ("visibility_sigma_fvs", True),
    "now sigma_max": ("sigma_max", False), "now default, cold": ("visibility_sigma_fvs", False),
    "now default, warm": ("visibility_sigma_fvs", False)}


def scene_model(name: str, folder: Path) -> Path:
    """The scene's model file, with its training cameras (none for 1m-uncaptured)."""
    if name == "nerf":
        config = NeRFConfig(encoding="pe", width=64, samples=64, bounds=[[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]],
                            near=2.0, far=6.0)
        path = folder / "lego.nerf"
        save_nerf(NeRFRenderer(RadianceField(config, seed=0)), path,
                  training_cameras=load_blender(harness.LEGO, "train", with_images=False).cameras)
        return path
    path = folder / f"{name}.ply"
    write_ply(tiled_model(1 if name == "donut" else 22, 3), path)
    if name != "1m-uncaptured":
        train = load_blender(harness.DONUT, "train", with_images=False).cameras
        sidecar_path(path).write_text(json.dumps({"format": SIDECAR_FORMAT, "background": [1.0, 1.0, 1.0],
                                                  "training_cameras": [c.to_frame() for c in train]}))
    return path


def rank(model: Path, poses: Path, out: Path, width: int, height: int, samples: int, strategy: str,
         code: Path | None) -> dict:
    """`phd rank` in a child: with `code`, the phd_core and phd_cli found there."""
    run = child(PHD + ["rank", "--model", str(model), "--candidates", str(poses), "--width", str(width),
                       "--height", str(height), "--samples", str(samples), "--dropout-ratio", str(RATIO),
                       "--strategy", strategy, "--out", str(out)], None, code or ROOT)
    run["order"] = json.loads(out.read_text())["order"]
    run["scores"] = [r["score"] for r in json.loads(out.read_text())["ranking"]]
    return run


def invocation() -> str:
    """This run's command line, to type again (the thread setting and the priority included)."""
    threads = os.environ.get("OMP_NUM_THREADS")
    return " ".join([*([f"OMP_NUM_THREADS={threads}"] if threads else []), f"nice -n {os.nice(0)}",
                     ".venv/bin/python -m bench.bench_default_cost", shlex.join(sys.argv[1:])])


def warm_up(folder: Path, before: Path) -> None:
    """A small rank by both versions with both strategies, so neither pays numba's compilation
    (its cache sits beside each version's code) in the runs measured."""
    model = folder / "warm.ply"
    write_ply(tiled_model(1, 3).subset(slice(0, 2000)), model)
    train = load_blender(harness.DONUT, "train", with_images=False).cameras[:3]
    sidecar_path(model).write_text(json.dumps({"format": SIDECAR_FORMAT, "background": [1.0, 1.0, 1.0],
                                               "training_cameras": [c.to_frame() for c in train]}))
    poses = folder / "warm-candidates.json"
    frames = json.loads((harness.DONUT / "transforms_test.json").read_text())
    poses.write_text(json.dumps({**frames, "frames": frames["frames"][:3]}))
    for code in (before, None):
        for strategy in ("sigma_max", "visibility_sigma_fvs"):
            rank(model, poses, folder / "warm-ranking.json", 20, 20, 4, strategy, code)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--only", nargs="*", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--count", type=int, help="candidates per scene instead of the scene's own number")
    p.add_argument("--runs", nargs="*", default=list(RUNS), choices=list(RUNS))
    p.add_argument("--out", type=Path, default=RESULTS / "default_cost.json", help="results file (adds to it)")
    p.add_argument("--report", nargs="*", type=Path, metavar="RESULTS",
                   help="only write the docs' table from these results files")
    p.add_argument("--section", default="default-cost", help="the docs' section the report replaces")
    args = p.parse_args()
    if args.report is not None:
        write_doc(DOCS / "performance.md", "\n\n".join(report(json.loads(path.read_text()))
                                                         for path in args.report), section=args.section)
        return
    results = {"machine": machine(omp_num_threads=os.environ.get("OMP_NUM_THREADS")), "before": args.before,
               "command": invocation(), "scenes": {}}
    if args.out.exists():      # scenes measured in earlier runs stay
        results["scenes"] = json.loads(args.out.read_text())["scenes"]
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        before.mkdir()
        archive = subprocess.run(["git", "archive", args.before, "phd_core", "phd_cli"], cwd=ROOT, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
        warm_up(Path(tmp), before)
        for name in args.only:
            source, count, width, height, samples = SCENES[name]
            count = args.count or count
            folder = Path(tmp) / name
            folder.mkdir()
            model = scene_model(name, folder)
            frames = json.loads((source / "transforms_test.json").read_text())
            frames["frames"] = frames["frames"][:count]
            poses = folder / "candidates.json"
            poses.write_text(json.dumps(frames))
            runs = {}
            for label in args.runs:
                strategy, old = RUNS[label]
                if label.endswith("cold"):     # nothing stored by an earlier run
                    shutil.rmtree(model.with_name(model.name + ".phd-cache"), ignore_errors=True)
                runs[label] = rank(model, poses, folder / "ranking.json", width, height, samples, strategy,
                                   before if old else None)
                runs[label]["load"] = load_average()
                print(name, label, {k: v for k, v in runs[label].items() if k not in ("order", "scores")}, flush=True)
            results["scenes"][name] = {"candidates": count, "size": f"{width}x{height}", "samples": samples,
                                       "runs": runs}
            write_result(args.out, results)


def report(results: dict) -> str:
    threads = "one thread" if results["machine"].get("omp_num_threads") == "1" else "torch's default threads (2)"
    ran = results.get("command", "python -m bench.bench_default_cost --before main --only donut nerf")
    lines = [f"Command: `{ran}` (`phd rank` in a child process each, start-up and load included, "
             f"{threads}; "
             f"{machine_note(results)}). \"default / sigma_max\": the ratio of the two strategies' CPU seconds "
             "(and wall seconds) by the same code; \"same picks\": the default's order and scores now equal the "
             "code before's, bit for bit.", "",
             "| scene | candidates | size | N | run | wall s | CPU s | peak RSS MB | default / sigma_max CPU (wall) "
             "| same picks |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, scene in results["scenes"].items():
        runs = scene["runs"]
        for label, run in runs.items():
            code = label.split()[0]
            paper = runs.get(f"{code} sigma_max")
            ratio = (f"{cpu(run) / cpu(paper):.2f}x ({run['wall_s'] / paper['wall_s']:.2f}x)"
                     if "default" in label and paper else "")
            same = ""
            if label.startswith("now default") and "before default" in runs:
                before = runs["before default"]
                same = "yes" if run["order"] == before["order"] and run["scores"] == before["scores"] else "NO"
            lines.append(f"| {name} | {scene['candidates']} | {scene['size']} | {scene['samples']} | {label} | "
                         f"{run['wall_s']:.1f} | {cpu(run):.1f} | {run['peak_rss_mb']:,} | "
                         f"{ratio} | {same} |")
    return "\n".join(lines)


def cpu(run: dict) -> float:
    return run["user_s"] + run["system_s"]


def machine_note(results: dict) -> str:
    loads = [run["load"][0] for scene in results["scenes"].values() for run in scene["runs"].values()]
    return (f"{results['machine'].get('cpus', '?')} cores shared with other work: 1-minute load "
            f"{min(loads):.1f}-{max(loads):.1f} during the runs, so compare within a scene")


if __name__ == "__main__":
    main()
