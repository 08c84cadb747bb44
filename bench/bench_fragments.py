"""Stages 2-3 of a splat render (fragments) on a real-size model, this code against an earlier
commit's, in one process, alternating, with the outputs compared (the fragment lists bit for
bit, the alphas to their largest relative difference); and a whole camera (`prepare_view`,
then N masked renders) with either version's fragments.

    .venv/bin/python -m bench.bench_fragments --before 852c250 [--copies 1 22] [--section fragments]

The earlier `gs3d/kernels.py` is read from git and loaded beside the current one (its relative
imports resolve against today's package, which holds for any revision whose kernels import the
same names). Models: the harness's SH-3 tilings of the donut (`tiled_model`, as bench_scale
uses; 22 copies are 1,003,728 splats, 1 is the 45,624-splat donut); cameras: donut_200's ring
poses. Writes bench/results/<section>.json and the table between the `bench:<section>`
markers of docs/performance.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numba
import torch

from bench._harness import DOCS, RESULTS, donut_cameras, module_at, tiled_model, write_doc, write_result
from phd_core.renderers.gs3d import kernels, render
from phd_core.renderers.gs3d.render import DILATION, NEAR_PLANE, front_to_back, prepare_view
from phd_core.renderers.splats import DEFAULT_TILE
from phd_core.uq import dropout_uniforms, keep_masks


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--copies", type=int, nargs="+", default=[22], help="donut copies (22: 1,003,728 splats)")
    p.add_argument("--widths", type=int, nargs="+", default=[200, 400], help="image widths (height 3/4)")
    p.add_argument("--cameras", type=int, default=4)
    p.add_argument("--repeats", type=int, default=3, help="timed calls per camera and version (after one warm-up)")
    p.add_argument("--samples", type=int, default=16, help="masks N of the whole-camera timing")
    p.add_argument("--ratio", type=float, default=0.5, help="dropout ratio of those masks")
    p.add_argument("--section", default="fragments", help="the docs section and results file written")
    args = p.parse_args()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    before = module_at(args.before, "phd_core/renderers/gs3d/kernels.py")
    background = torch.ones(3)
    rows = []
    for copies in args.copies:
        model = tiled_model(copies, 3)
        keep = keep_masks(dropout_uniforms(model.num_splats, args.samples, 0), args.ratio)
        rows += measure(model, keep, background, before, args)
    write_result(RESULTS / f"{args.section}.json", {"before": args.before, "rows": rows})
    command = " ".join(["--before", args.before, "--copies", *map(str, args.copies)]
                       + (["--section", args.section] if args.section != "fragments" else []))
    lines = [f"Command: `.venv/bin/python -m bench.bench_fragments {command}` (SH 3, {args.cameras} ring cameras, "
             f"median of {args.repeats} calls each, one thread, both versions alternating in one process; the "
             "fragment lists are identical bit for bit, the alphas differ by at most the relative amount given). "
             f"Whole camera: `prepare_view` and one render of N = {args.samples} masks at ratio {args.ratio}, with "
             "either version's fragments.", "",
             "| splats | size | fragments | alpha rel. diff | fragments before s | now s | speed-up | "
             "whole camera before s | now s | speed-up |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['splats']:,} | {r['size']} | {r['fragments']:,} | {r['alpha_rel_diff']:.1e} | "
              f"{r['before_s']:.3f} | {r['now_s']:.3f} | {r['before_s'] / r['now_s']:.2f}x | "
              f"{r['camera_before_s']:.3f} | {r['camera_now_s']:.3f} | "
              f"{r['camera_before_s'] / r['camera_now_s']:.2f}x |" for r in rows]
    write_doc(DOCS / "performance.md", "\n".join(lines), section=args.section)


def measure(model, keep: torch.Tensor, background: torch.Tensor, before, args: argparse.Namespace) -> list[dict]:
    """One model's rows (one per width): both versions' fragment and whole-camera seconds."""

    def whole_camera(module, camera) -> float:
        """Seconds of prepare_view plus one render of the N masks, with `module`'s fragments."""
        render.splat_fragments = module.splat_fragments
        try:
            started = time.perf_counter()
            prepare_view(model, camera, background).render(keep)
            return time.perf_counter() - started
        finally:
            render.splat_fragments = kernels.splat_fragments

    rows = []
    for width in args.widths:
        height = width * 3 // 4
        seconds: dict[str, list[float]] = {"before": [], "now": [], "camera_before": [], "camera_now": []}
        alpha_diff = 0.0
        for camera in donut_cameras(width, height, args.cameras):
            means2d, conics, opacities, extents, depths, visible = kernels.project_splats(
                model.means, model.quats, model.log_scales, model.opacity_logits, camera, NEAR_PLANE, DILATION)
            ids = front_to_back(visible, depths)
            inputs = (means2d[ids], conics[ids], opacities[ids], extents[ids], width, height, DEFAULT_TILE)
            outputs = {}
            for repeat in range(1 + args.repeats):
                for name, module in (("before", before), ("now", kernels)):
                    started = time.perf_counter()
                    outputs[name] = module.splat_fragments(*inputs)
                    if repeat:
                        seconds[name].append(time.perf_counter() - started)
            (old_ptr, old_alpha, old_index), (new_ptr, new_alpha, new_index) = (outputs[k][:3]
                                                                                for k in ("before", "now"))
            assert torch.equal(old_ptr, new_ptr) and torch.equal(old_index, new_index), "the fragments differ"
            alpha_diff = max(alpha_diff, float(((new_alpha.double() - old_alpha.double()).abs()
                                                / old_alpha.double()).max()) if len(old_alpha) else 0.0)
            for repeat in range(1 + args.repeats):
                for name, module in (("camera_before", before), ("camera_now", kernels)):
                    took = whole_camera(module, camera)
                    if repeat:
                        seconds[name].append(took)
        row = {"splats": model.num_splats, "size": f"{width}x{height}", "fragments": len(outputs["now"][1]),
               "alpha_rel_diff": alpha_diff,
               **{f"{name}_s": statistics.median(values) for name, values in seconds.items()}}
        rows.append(row)
        print(row, flush=True)
    return rows


if __name__ == "__main__":
    main()
