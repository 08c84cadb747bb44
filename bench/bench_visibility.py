"""The visibility pass at real size: the compiled `fragment_visibility` against its torch twin;
and (`--cost`) what a candidate's visibility adds to its N masked renders, before and now.

The visibility strategies (the default `visibility_sigma_fvs` among them) run one visibility
pass per candidate and per captured view. Its sums over the fragments were torch cumulative sums holding ~9
float64 arrays per fragment; at 1M splats and 200x150 px (7M fragments) that is ~0.9 GB per
view, and the service refused such ranks under a 4 GiB budget. For each model and size, one
child process per version prepares a view, then runs the pass (the renderer's per-fragment
element ids, then the sums) three times: median seconds, and the peak RSS
the passes add over the prepared view (VmHWM, reset by /proc/self/clear_refs just before them).
Both versions' sums are compared in the parent.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_visibility [--copies 1 22] [--sizes 200 400]

`--cost` (issue 34: a candidate's visibility from the view its masked renders use): per family,
one child process per version (`--before`: a `git archive` of that revision's phd_core, with
this checkout's bench beside it) runs `measure_views` on each candidate, as a rank does: its N
masked renders and zeta, with and without the visibility pass (zeta's channel max per element);
the CPU seconds of each candidate (time.process_time, one thread), median over the candidates
after one unmeasured warm-up candidate. Both versions' Visibility are compared bit for bit.
- 2dgs: the 45,624-splat SH-3 donut of `tiled_model` as surfels (its two tangential scales),
  donut_200's test poses at 100x100, N = 16;
- nerf: bench_default_cost's NeRF (positional encoding, every cell occupied), lego_200's test
  poses at 100x100, N = 32.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_visibility --cost --before main [--families 2dgs nerf]
        [--count 2dgs=12 nerf=4]
    .venv/bin/python -m bench.bench_visibility --cost --report bench/results/visibility_cost.json   (the table)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench._harness import (
    DATA,
    DOCS,
    LEGO,
    RESULTS,
    ROOT,
    donut_cameras,
    load_average,
    machine,
    reset_peak,
    tiled_model,
    vm,
    write_doc,
    write_result,
)
from phd_core.allocator import bounded_heap
from phd_core.data import load_blender
from phd_core.renderers import visibility as vis_module
from phd_core.renderers.gs2d import SurfelModel, SurfelRenderer
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField
from phd_core.uq.sampling import dropout_uniforms, keep_masks
from phd_core.uq.uncertainty import measure_views

VERSIONS = {"compiled": vis_module.fragment_visibility, "torch twin": vis_module.fragment_visibility_reference}


def child(copies: int, size: int, version: str) -> dict:
    """Prepare one ring view of the tiled model, then time the pass with `version`'s sums."""
    torch.set_num_threads(1)
    bounded_heap()                                                     # the service's malloc settings
    renderer = GaussianRenderer(tiled_model(copies, 3))
    camera = donut_cameras(size, size * 3 // 4, 1)[0]
    view = renderer.prepare(camera)
    sums_of = VERSIONS[version]

    def visibility_pass() -> vis_module.FragmentSums:
        row_ptr, alpha, index, units, _, _ = renderer.fragment_rows(view)
        return sums_of(row_ptr, alpha, index, units, renderer.num_units)
    sums_of(torch.tensor([0, 2]), torch.tensor([0.5, 0.5]), torch.tensor([0, 1]), torch.tensor([0, 1]), 2)  # compile
    base = reset_peak(os.getpid())                                     # VmHWM starts again from VmRSS
    seconds = []
    for _ in range(3):
        start = time.perf_counter()
        sums = visibility_pass()
        seconds.append(time.perf_counter() - start)
    return {"seconds": statistics.median(seconds), "added_mb": (vm(os.getpid(), "VmHWM") - base) / 2**20,
            "fragments": int(view.row_ptr[-1]), "splats": renderer.num_units,
            "weight_sum": float(sums.weight.sum())}


# --cost: family -> (model, candidates of count at 100x100, masks N)
COST_SAMPLES = {"2dgs": 16, "nerf": 32}
COST_COUNT = {"2dgs": 12, "nerf": 4}
COST_RATIO = 0.5


def cost_scene(family: str, count: int):
    """The family's renderer and its count + 1 candidates (the first one is the warm-up)."""
    if family == "2dgs":
        donut = tiled_model(1, 3)
        renderer = SurfelRenderer(SurfelModel(donut.means, donut.log_scales[:, :2].contiguous(), donut.quats,
                                              donut.opacity_logits, donut.sh))
        return renderer, donut_cameras(100, 100, count + 1)
    config = NeRFConfig(encoding="pe", width=64, samples=64, bounds=[[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]],
                        near=2.0, far=6.0)                     # bench_default_cost's nerf scene
    cameras = load_blender(LEGO, "test", with_images=False).cameras[:count + 1]
    return NeRFRenderer(RadianceField(config, seed=0)), [c.resized(100, 100) for c in cameras]


def cost_child(family: str, count: int) -> dict:
    """Per candidate: CPU seconds of measure_views without and with the visibility, and a digest
    of the Visibility (ids, weight, footprint, valued, empty, in_box)."""
    torch.set_num_threads(1)                  # malloc as `phd rank` has it (bench/__init__.py)
    renderer, cameras = cost_scene(family, count)
    keep = keep_masks(dropout_uniforms(renderer.num_units, COST_SAMPLES[family], 0), COST_RATIO)
    rows = []
    for i, camera in enumerate(cameras):
        row = {}
        for label, visible in (("renders", False), ("renders + visibility", True)):
            start = time.process_time()
            view = measure_views([camera], renderer, keep, ddof=1, keep_maps=False, dtype=torch.float64,
                                 keep_visibility=visible)[0]
            row[label] = time.process_time() - start
        vis = view.visibility
        digest = hashlib.sha256()
        for t in (vis.elements, vis.weight, vis.footprint, vis.valued):
            digest.update(t.contiguous().numpy().tobytes())
        digest.update(repr((vis.empty, vis.in_box, view.sigma_max)).encode())
        row["digest"] = digest.hexdigest()
        if i:                                                              # the first one warms up
            rows.append(row)
    return {"units": renderer.num_units, "rows": rows, "where": str(Path(vis_module.__file__).parents[2])}


def cost(args: argparse.Namespace) -> None:
    """Run `cost_child` for each family by the code at `--before` and by this checkout."""
    counts = {**COST_COUNT, **dict((k, int(v)) for k, v in (item.split("=") for item in args.count))}
    results = {"machine": machine(omp_num_threads=os.environ.get("OMP_NUM_THREADS")), "before": args.before,
               "families": {}}
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"                   # its phd_core, this bench; ../shared for the data
        before.mkdir()
        archive = subprocess.run(["git", "archive", args.before, "phd_core"], cwd=ROOT, check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(before)], input=archive, check=True)
        shutil.copytree(ROOT / "bench", before / "bench", ignore=shutil.ignore_patterns("results", "__pycache__"))
        (Path(tmp) / "shared").symlink_to(DATA.parent)
        for family in args.families:
            runs = {}
            for version, code in (("before", before), ("now", ROOT)):
                out = subprocess.run([sys.executable, "-m", "bench.bench_visibility", "--cost-child", family,
                                      str(counts[family])], cwd=code, check=True, capture_output=True,
                                     text=True).stdout
                runs[version] = {**json.loads(out.strip().splitlines()[-1]), "load": load_average()}
                print(family, version, runs[version], flush=True)
            results["families"][family] = {"count": counts[family], "samples": COST_SAMPLES[family], "runs": runs}
    results["command"] = ("OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_visibility --cost --before "
                          + args.before + " --families " + " ".join(args.families) + " --count "
                          + " ".join(f"{k}={v}" for k, v in counts.items() if k in args.families))
    write_result(RESULTS / "visibility_cost.json", results)
    write_doc(DOCS / "performance.md", cost_report(results), "visibility-cost")


def cost_report(results: dict) -> str:
    """The docs' table of a `--cost` run."""
    command = results["command"]
    loads = [run["load"][0] for family in results["families"].values() for run in family["runs"].values()]
    lines = [f"Command: `{command}` (one thread; CPU seconds per candidate, median over the candidates after a "
             f"warm-up one; 100x100; 2 cores shared with other work: 1-minute load {min(loads):.1f}-{max(loads):.1f}, "
             "so compare within a family). \"visibility adds\": the median over the candidates of each one's "
             "time with the visibility over its time without, minus 1; "
             "\"same Visibility\": every candidate's Visibility (ids, sums, empty light) and sigma_max now equal "
             "the code before's, bit for bit.", "",
             "| family | units | candidates | N | run | masked renders s | renders + visibility s | visibility adds | "
             "same Visibility |", "|---|---|---|---|---|---|---|---|---|"]
    for family, found in results["families"].items():
        before_rows = found["runs"]["before"]["rows"]
        for version, run in found["runs"].items():
            renders = statistics.median(r["renders"] for r in run["rows"])
            both = statistics.median(r["renders + visibility"] for r in run["rows"])
            added = statistics.median(r["renders + visibility"] / r["renders"] - 1 for r in run["rows"])
            same = "" if version == "before" else (
                "yes" if [r["digest"] for r in run["rows"]] == [r["digest"] for r in before_rows] else "NO")
            lines.append(f"| {family} | {run['units']:,} | {found['count']} | {found['samples']} | {version} | "
                         f"{renders:.3f} | {both:.3f} | {added:+.1%} | {same} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--copies", type=int, nargs="+", default=[1, 22])
    p.add_argument("--sizes", type=int, nargs="+", default=[200, 400])
    p.add_argument("--cost", action="store_true", help="a candidate's visibility against its masked renders")
    p.add_argument("--before", default="main", help="with --cost: the git revision to compare with")
    p.add_argument("--families", nargs="+", default=list(COST_SAMPLES), choices=list(COST_SAMPLES))
    p.add_argument("--count", nargs="*", default=[], metavar="FAMILY=C", help="with --cost: candidates per family")
    p.add_argument("--report", type=Path, metavar="RESULTS", help="with --cost: only write the docs' table from these")
    p.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    p.add_argument("--cost-child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(int(args.child[0]), int(args.child[1]), args.child[2])))
        return
    if args.cost_child:
        print(json.dumps(cost_child(args.cost_child[0], int(args.cost_child[1]))))
        return
    if args.cost and args.report:
        write_doc(DOCS / "performance.md", cost_report(json.loads(args.report.read_text())), "visibility-cost")
        return
    if args.cost:
        cost(args)
        return
    rows = []
    for copies in args.copies:
        for size in args.sizes:
            runs = {}
            for version in VERSIONS:
                out = subprocess.run([sys.executable, "-m", "bench.bench_visibility", "--child", str(copies), str(size),
                                      version], check=True, capture_output=True, text=True).stdout
                runs[version] = json.loads(out.strip().splitlines()[-1])
            rows.append({"copies": copies, "size": size, **{k: runs["compiled"][k] for k in ("splats", "fragments")},
                         "runs": runs})
            print(rows[-1], flush=True)
    write_result(RESULTS / "visibility.json", {"machine": machine(), "rows": rows})
    lines = [f"Command: `OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_visibility --copies "
             f"{' '.join(map(str, args.copies))} --sizes {' '.join(map(str, args.sizes))}` (one thread, one ring pose "
             "of the tiled SH-3 donut model, median of 3 passes; memory: the peak RSS the passes add over the "
             "prepared view, each version in its own process under the service's malloc settings).", "",
             "| splats | size | fragments | torch twin s | compiled s | speed-up | torch twin MB | compiled MB | "
             "weights agree |", "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        slow, fast = row["runs"]["torch twin"], row["runs"]["compiled"]
        agree = abs(slow["weight_sum"] - fast["weight_sum"]) <= 1e-9 * max(1.0, abs(slow["weight_sum"]))
        lines.append(f"| {row['splats']:,} | {row['size']}x{row['size'] * 3 // 4} | {row['fragments']:,} | "
                     f"{slow['seconds']:.3f} | {fast['seconds']:.3f} | {slow['seconds'] / fast['seconds']:.1f}x | "
                     f"{slow['added_mb']:,.0f} | {fast['added_mb']:,.0f} | {'yes' if agree else 'NO'} |")
    write_doc(DOCS / "performance.md", "\n".join(lines), "visibility")


if __name__ == "__main__":
    main()
