"""The visibility pass at real size: the compiled `fragment_visibility` against its torch twin.

The visibility strategies (the default `visibility_sigma_fvs` among them) run one visibility
pass per candidate and per captured view. Its sums over the fragments were torch cumulative sums holding ~9
float64 arrays per fragment; at 1M splats and 200x150 px (7M fragments) that is ~0.9 GB per
view, and the service refused such ranks under a 4 GiB budget. For each model and size, one
child process per version prepares a view, then runs the pass (the renderer's per-fragment
element ids, then the sums) three times: median seconds, and the peak RSS
the passes add over the prepared view (VmHWM, reset by /proc/self/clear_refs just before them).
Both versions' sums are compared in the parent.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_visibility [--copies 1 22] [--sizes 200 400]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import torch

from bench._harness import DOCS, RESULTS, donut_cameras, machine, reset_peak, tiled_model, vm, write_doc, write_result
from phd_core.allocator import bounded_heap
from phd_core.renderers import visibility as vis_module
from phd_core.renderers.gs3d import GaussianRenderer

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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--copies", type=int, nargs="+", default=[1, 22])
    p.add_argument("--sizes", type=int, nargs="+", default=[200, 400])
    p.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(int(args.child[0]), int(args.child[1]), args.child[2])))
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
