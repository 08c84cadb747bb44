"""Stages 2-3 of a splat render (fragments) on a real-size model, this code against an earlier
commit's, in one process, alternating, with the outputs compared bit for bit; and a whole
camera (`prepare_view`, then N masked renders) with either version's fragments.

    .venv/bin/python -m bench.bench_fragments --before 852c250

The earlier `gs3d/kernels.py` is read from git and loaded beside the current one (its relative
imports resolve against today's package, which holds for any revision whose kernels import the
same names). Model: the harness's 1,003,728-splat SH-3 tiling of the donut (`tiled_model`, as
bench_scale uses); cameras: donut_200's ring poses. Writes bench/results/fragments.json and
the table between the `bench:fragments` markers of docs/performance.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numba
import torch

from bench._harness import DOCS, RESULTS, ROOT, donut_cameras, tiled_model, write_doc, write_result
from phd_core.renderers.gs3d import kernels, render
from phd_core.renderers.gs3d.render import DILATION, NEAR_PLANE, front_to_back, prepare_view
from phd_core.renderers.splats import DEFAULT_TILE
from phd_core.uq import dropout_uniforms, keep_masks


def kernels_at(revision: str):
    """`phd_core.renderers.gs3d.kernels` as it was at `revision`, as a module of today's package."""
    source = subprocess.run(["git", "show", f"{revision}:phd_core/renderers/gs3d/kernels.py"], cwd=ROOT,
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "kernels_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("phd_core.renderers.gs3d.kernels_before", path)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "phd_core.renderers.gs3d"
    spec.loader.exec_module(module)
    return module


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--copies", type=int, default=22, help="donut copies (22: 1,003,728 splats)")
    p.add_argument("--widths", type=int, nargs="+", default=[200, 400], help="image widths (height 3/4)")
    p.add_argument("--cameras", type=int, default=4)
    p.add_argument("--repeats", type=int, default=3, help="timed calls per camera and version (after one warm-up)")
    p.add_argument("--samples", type=int, default=16, help="masks N of the whole-camera timing")
    p.add_argument("--ratio", type=float, default=0.5, help="dropout ratio of those masks")
    args = p.parse_args()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    before = kernels_at(args.before)
    model = tiled_model(args.copies, 3)
    keep = keep_masks(dropout_uniforms(model.num_splats, args.samples, 0), args.ratio)
    background = torch.ones(3)

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
            for old, new in zip(outputs["before"][:3], outputs["now"][:3]):
                assert torch.equal(old, new), "the fragments differ"
            for repeat in range(1 + args.repeats):
                for name, module in (("camera_before", before), ("camera_now", kernels)):
                    took = whole_camera(module, camera)
                    if repeat:
                        seconds[name].append(took)
        row = {"size": f"{width}x{height}", "fragments": len(outputs["now"][1]),
               **{f"{name}_s": statistics.median(values) for name, values in seconds.items()}}
        rows.append(row)
        print(row, flush=True)
    write_result(RESULTS / "fragments.json", {"before": args.before, "splats": model.num_splats, "rows": rows})
    lines = [f"Command: `.venv/bin/python -m bench.bench_fragments --before {args.before}` ({model.num_splats:,} "
             f"splats, SH 3, {args.cameras} ring cameras, median of {args.repeats} calls each, one thread, both "
             "versions alternating in one process; the fragments are identical bit for bit). Whole camera: "
             f"`prepare_view` and one render of N = {args.samples} masks at ratio {args.ratio}, with either "
             "version's fragments.", "",
             "| size | fragments | fragments before s | now s | speed-up | whole camera before s | now s | speed-up |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['size']} | {r['fragments']:,} | {r['before_s']:.3f} | {r['now_s']:.3f} | "
              f"{r['before_s'] / r['now_s']:.2f}x | {r['camera_before_s']:.3f} | {r['camera_now_s']:.3f} | "
              f"{r['camera_before_s'] / r['camera_now_s']:.2f}x |" for r in rows]
    write_doc(DOCS / "performance.md", "\n".join(lines), section="fragments")


if __name__ == "__main__":
    main()
