"""The coverage selection of the visibility strategies at real size: today's against a git
revision's, on the same evidence, with the orders and scores compared exactly.

    .venv/bin/python -m bench.bench_coverage --before main [--copies 1 22] [--candidates 30 100]
                                             [--captured 100] [--strategies visibility_sigma_fvs]

Once the views are rendered, a visibility strategy picks greedily: every pick is counted as
captured and lowers the novelty of what every other candidate sees. Per model: the tiled SH-3
donut of `tiled_model` (1 copy: 45,624 splats; 22: 1,003,728); as candidates, the donut_200
ring poses at W x 3W/4 (up to 100; more: hemisphere poses at the same distance); as captured
views, `--captured` training poses of donut_200 at the same size; N = 8 masks at ratio 0.5.
Then `coverage_select` of both versions (k = 5 and every candidate), one thread, alternating,
best of `--repeats`, counting the candidate sums each computes ("updates": a candidate's value
summed over its elements after a capture changed it). Writes bench/results/coverage.json and
the table between the `bench:coverage` markers of docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from bench._harness import DOCS, RESULTS, donut_cameras, machine, module_at, tiled_model, write_doc, write_result
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.uq.candidates import hemisphere_cameras
from phd_core.uq.rank import candidate_evidence
from phd_core.uq.strategies import visibility

VARIANTS = {"visibility_sigma_fvs": {"fragility": True, "spread": True},
            "visibility_sigma": {"fragility": True}, "visibility": {"fragility": False}}


def counted(module, k: int, evidence, options: dict) -> tuple[object, int]:
    """module.coverage_select(evidence, k) and the candidate sums it computed."""
    original, sums = module.Coverage._sum, [0]

    def counting(self, c: int) -> float:
        sums[0] += bool(getattr(self, "changed", None) is None or self.changed[c])   # before: every call sums
        return original(self, c)

    module.Coverage._sum = counting
    try:
        return module.coverage_select(evidence, k, **options), sums[0]
    finally:
        module.Coverage._sum = original


def candidate_poses(count: int, width: int, height: int):
    """The donut_200 ring poses (at most 100), else hemisphere poses at their distance."""
    if count <= 100:
        return donut_cameras(width, height, count)
    return [c.resized(width, height) for c in hemisphere_cameras(count, radius=4.03, width=width, height=width,
                                                                  min_elevation=0.17, max_elevation=0.87)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--copies", type=int, nargs="+", default=[1, 22])
    p.add_argument("--width", type=int, default=200, help="candidate width (height 3/4)")
    p.add_argument("--candidates", type=int, nargs="+", default=[30])
    p.add_argument("--captured", type=int, default=6, help="donut_200 training poses counted as captured")
    p.add_argument("--strategies", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--section", default="coverage", help="the docs' section (and results file) to write")
    args = p.parse_args()
    torch.set_num_threads(1)
    before = module_at(args.before, "phd_core/uq/strategies/visibility.py")
    rows = []
    height = args.width * 3 // 4
    for copies in args.copies:
        renderer = GaussianRenderer(tiled_model(copies, 3))
        for count in args.candidates:
            evidence, _ = candidate_evidence(renderer, candidate_poses(count, args.width, height), ratio=0.5,
                                             samples=8, captured=donut_cameras(args.width, height, args.captured,
                                                                               "train"), visibility=True)
            elements = sum(len(v.elements) for v in evidence.candidate_views or [])
            for name in args.strategies:
                for k in sorted({5, count}):
                    seconds: dict[str, float] = {}
                    picks, updates = {}, {}
                    for _ in range(args.repeats):
                        for version, module in (("before", before), ("now", visibility)):
                            started = time.process_time()
                            picks[version], updates[version] = counted(module, k, evidence, VARIANTS[name])
                            seconds[version] = min(seconds.get(version, float("inf")), time.process_time() - started)
                    same = (picks["before"].order == picks["now"].order
                            and picks["before"].scores == picks["now"].scores)
                    rows.append({"splats": renderer.num_units, "size": f"{args.width}x{height}", "candidates": count,
                                 "captured": args.captured, "elements": elements, "strategy": name, "k": k,
                                 "before_s": seconds["before"], "now_s": seconds["now"],
                                 "before_updates": updates["before"], "now_updates": updates["now"],
                                 "identical": same})
                    print(rows[-1], flush=True)
    write_result(RESULTS / f"{args.section.replace('-', '_')}.json", {"machine": machine(), "before": args.before,
                                                                      "rows": rows})
    lines = [f"Command: `nice -n {os.nice(0)} .venv/bin/python -m bench.bench_coverage --before {args.before} --copies "
             f"{' '.join(map(str, args.copies))} --candidates {' '.join(map(str, args.candidates))} --captured "
             f"{args.captured} --width {args.width} --strategies {' '.join(args.strategies)} --section {args.section} "
             f"--repeats {args.repeats}` "
             "(CPU seconds on one thread, both versions alternating on "
             f"the same evidence, best of {args.repeats}; \"identical\": the same order and the same scores bit for "
             "bit; updates: candidate sums computed). Elements: the candidates' listed splats, summed.", "",
             "| splats | size | candidates | captured | elements | strategy | k | before s | now s | speed-up "
             "| updates before | now | identical |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['splats']:,} | {r['size']} | {r['candidates']} | {r['captured']} | {r['elements']:,} | "
              f"{r['strategy']} | {r['k']} | {r['before_s']:.3f} | {r['now_s']:.3f} | "
              f"{r['before_s'] / r['now_s']:.2f}x | {r['before_updates']:,} | {r['now_updates']:,} | "
              f"{'yes' if r['identical'] else 'NO'} |" for r in rows]
    write_doc(DOCS / "performance.md", "\n".join(lines), section=args.section)


if __name__ == "__main__":
    main()
