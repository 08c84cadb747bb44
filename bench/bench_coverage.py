"""The coverage selection of the visibility strategies at real size: today's against a git
revision's, on the same evidence, with the orders and scores compared exactly.

    .venv/bin/python -m bench.bench_coverage --before 44f7c96 [--copies 1 22] [--candidates 30]

Once the views are rendered, a visibility strategy picks greedily: every pick is counted as
captured and lowers the novelty of what every other candidate sees, so ordering C candidates
updates C candidates C times over their elements (up to 4 per pixel each). Per model: the
tiled SH-3 donut of `tiled_model` (1 copy: 45,624 splats; 22: 1,003,728), the donut_200 ring
poses at W x 3W/4 as candidates and 6 training poses as captured views, N = 8 masks at ratio
0.5; then `coverage_select` of both versions (k = 1, 5 and every candidate; each strategy
variant), one thread, alternating, best of `--repeats`. Writes bench/results/coverage.json and
the table between the `bench:coverage` markers of docs/performance.md.
"""

from __future__ import annotations

import argparse
import time

import torch

from bench._harness import DOCS, RESULTS, donut_cameras, machine, module_at, tiled_model, write_doc, write_result
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.uq.rank import candidate_evidence
from phd_core.uq.strategies import visibility

VARIANTS = {"visibility_sigma_fvs": {"fragility": True, "spread": True},
            "visibility_sigma": {"fragility": True}, "visibility": {"fragility": False}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--copies", type=int, nargs="+", default=[1, 22])
    p.add_argument("--width", type=int, default=200, help="candidate width (height 3/4)")
    p.add_argument("--candidates", type=int, default=30)
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(1)
    before = module_at(args.before, "phd_core/uq/strategies/visibility.py")
    rows = []
    for copies in args.copies:
        renderer = GaussianRenderer(tiled_model(copies, 3))
        height = args.width * 3 // 4
        evidence, _ = candidate_evidence(renderer, donut_cameras(args.width, height, args.candidates), ratio=0.5,
                                         samples=8, captured=donut_cameras(args.width, height, 6, "train"),
                                         visibility=True)
        elements = sum(len(v.elements) for v in evidence.candidate_views or [])
        for name, options in VARIANTS.items():
            for k in sorted({1, 5, args.candidates}):
                seconds: dict[str, float] = {}
                picks = {}
                for _ in range(args.repeats):
                    for version, module in (("before", before), ("now", visibility)):
                        started = time.perf_counter()
                        picks[version] = module.coverage_select(evidence, k, **options)
                        seconds[version] = min(seconds.get(version, float("inf")), time.perf_counter() - started)
                same = (picks["before"].order == picks["now"].order and picks["before"].scores == picks["now"].scores)
                rows.append({"splats": renderer.num_units, "size": f"{args.width}x{height}",
                             "candidates": args.candidates, "elements": elements, "strategy": name, "k": k,
                             "before_s": seconds["before"], "now_s": seconds["now"], "identical": same})
                print(rows[-1], flush=True)
    write_result(RESULTS / "coverage.json", {"machine": machine(), "before": args.before, "rows": rows})
    lines = [f"Command: `.venv/bin/python -m bench.bench_coverage --before {args.before} --copies "
             f"{' '.join(map(str, args.copies))} --candidates {args.candidates}` (one thread, both versions "
             f"alternating on the same evidence, best of {args.repeats}; \"identical\": the same order and the same "
             "scores bit for bit). Elements: the candidates' listed splats, summed.", "",
             "| splats | size | candidates | elements | strategy | k | before s | now s | speed-up | identical |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['splats']:,} | {r['size']} | {r['candidates']} | {r['elements']:,} | {r['strategy']} | {r['k']} | "
              f"{r['before_s']:.3f} | {r['now_s']:.3f} | {r['before_s'] / r['now_s']:.2f}x | "
              f"{'yes' if r['identical'] else 'NO'} |" for r in rows]
    write_doc(DOCS / "performance.md", "\n".join(lines), section="coverage")


if __name__ == "__main__":
    main()
