"""What the default strategy costs against the paper's rule (issue 34): `phd rank`, whole process.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_default_cost --before main [--only donut nerf 1m ...]

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
import subprocess
import tempfile
from pathlib import Path

from bench._harness import (
    DOCS,
    DONUT,
    LEGO,
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
    "donut": (DONUT, 60, 100, 100, 16),
    "nerf": (LEGO, 30, 100, 100, 32),
    "1m": (DONUT, 100, 200, 150, 16),
    "1m-uncaptured": (DONUT, 100, 200, 150, 16),
}
RATIO = 0.5


def scene_model(name: str, folder: Path) -> Path:
    """The scene's model file, with its training cameras (none for 1m-uncaptured)."""
    if name == "nerf":
        config = NeRFConfig(encoding="pe", width=64, samples=64, bounds=[[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]],
                            near=2.0, far=6.0)
        path = folder / "lego.nerf"
        save_nerf(NeRFRenderer(RadianceField(config, seed=0)), path,
                  training_cameras=load_blender(LEGO, "train", with_images=False).cameras)
        return path
    path = folder / f"{name}.ply"
    write_ply(tiled_model(1 if name == "donut" else 22, 3), path)
    if name != "1m-uncaptured":
        train = load_blender(DONUT, "train", with_images=False).cameras
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--only", nargs="*", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--report", action="store_true", help="only write the docs' table from the results file")
    args = p.parse_args()
    if args.report:
        write_doc(DOCS / "performance.md", report(json.loads((RESULTS / "default_cost.json").read_text())),
                  section="default-cost")
        return
    results = {"machine": machine(omp_num_threads=os.environ.get("OMP_NUM_THREADS")), "before": args.before,
               "scenes": {}}
    if (RESULTS / "default_cost.json").exists():      # scenes measured in earlier runs stay
        results["scenes"] = json.loads((RESULTS / "default_cost.json").read_text())["scenes"]
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        before.mkdir()
        archive = subprocess.run(["git", "archive", args.before, "phd_core", "phd_cli"], cwd=ROOT, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
        for name in args.only:
            source, count, width, height, samples = SCENES[name]
            folder = Path(tmp) / name
            folder.mkdir()
            model = scene_model(name, folder)
            frames = json.loads((source / "transforms_test.json").read_text())
            frames["frames"] = frames["frames"][:count]
            poses = folder / "candidates.json"
            poses.write_text(json.dumps(frames))
            runs = {}
            for label, strategy, code in (("before sigma_max", "sigma_max", before),
                                          ("before default", "visibility_sigma_fvs", before),
                                          ("now sigma_max", "sigma_max", None),
                                          ("now default, cold", "visibility_sigma_fvs", None),
                                          ("now default, warm", "visibility_sigma_fvs", None)):
                runs[label] = rank(model, poses, folder / "ranking.json", width, height, samples, strategy, code)
                runs[label]["load"] = load_average()
                print(name, label, {k: v for k, v in runs[label].items() if k not in ("order", "scores")}, flush=True)
            results["scenes"][name] = {"candidates": count, "size": f"{width}x{height}", "samples": samples,
                                       "runs": runs}
            write_result(RESULTS / "default_cost.json", results)
    write_doc(DOCS / "performance.md", report(results), section="default-cost")


def report(results: dict) -> str:
    threads = results["machine"].get("omp_num_threads") or "torch's default"
    lines = [f"Command: `OMP_NUM_THREADS={results['machine'].get('omp_num_threads') or ''} nice -n 10 .venv/bin/python "
             f"-m bench.bench_default_cost --before {results['before']}` (`phd rank` in a child process each, start-up "
             f"and load included, {threads} threads; "
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
            paper = runs[f"{code} sigma_max"]
            ratio = (f"{cpu(run) / cpu(paper):.2f}x ({run['wall_s'] / paper['wall_s']:.2f}x)"
                     if "default" in label else "")
            same = ""
            if label.startswith("now default"):
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
