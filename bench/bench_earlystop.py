"""A view of the full model charged for its visible fragments (issue 34, item 5): renders with
every fragment listed (the code before, `--before`'s fragment kernel) against renders whose
lists end where the pixels are spent (`prepare_view(cut=True)`), in one process, alternating,
CPU seconds on one thread, with the images compared bit for bit.

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_earlystop --before main [--copies 1 22]

Per model (the harness's SH-3 tilings of the donut: 22 copies are 1,003,728 splats, 1 is the
45,624-splat donut; donut_200's ring poses at 200x150):
- the unmasked render (`GaussianRenderer.render_full(camera)`, what `phd render` and a
  calibration reference do): before, a complete view composited with keep None; now, the cut view;
- N masks at a ratio (a candidate's renders): a complete view (before and now) against a view
  cut for those masks (the kernel can; the renderer does not use it, this row says why);
- `uq.calibrate` on 8 training poses: `--before`'s calibrate.py and fragment kernel against
  this code (references from the first pass's views), with the local executor (one view a
  chunk) and with all views in one chunk.
Writes bench/results/early-stop.json and the table between the `bench:early-stop` markers of
docs/performance.md.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any, Callable

import numba
import torch

from bench._harness import (
    DOCS,
    RESULTS,
    donut_cameras,
    load_average,
    machine,
    module_at,
    tiled_model,
    write_doc,
    write_result,
)
from phd_core import uq
from phd_core.executors.local import LocalExecutor
from phd_core.renderers.gs3d import GaussianRenderer, kernels, render
from phd_core.renderers.gs3d.render import prepare_view
from phd_core.uq import dropout_uniforms, keep_masks


class OneChunk(LocalExecutor):
    """Every view in one chunk (as a remote executor's chunks hold several)."""

    def split(self, items):
        return [list(items)]


def cpu(fn: Callable[[], Any]) -> tuple[float, Any]:
    started = time.process_time()
    out = fn()
    return time.process_time() - started, out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--before", required=True, help="the git revision to compare with")
    p.add_argument("--copies", type=int, nargs="+", default=[1, 22], help="donut copies (22: 1,003,728 splats)")
    p.add_argument("--width", type=int, default=200, help="image width (height 3/4)")
    p.add_argument("--cameras", type=int, default=4, help="ring cameras per render row")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per camera and version (after one warm-up)")
    p.add_argument("--samples", type=int, default=16, help="masks N of the masked row")
    p.add_argument("--ratio", type=float, default=0.5, help="dropout ratio of those masks")
    p.add_argument("--views", type=int, default=8, help="training poses of the calibration")
    p.add_argument("--calibration-repeats", type=int, default=2,
                   help="timed calibrations per version and executor (after one warm-up), the best reported")
    args = p.parse_args()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    old_kernels = module_at(args.before, "phd_core/renderers/gs3d/kernels.py")
    old_calibrate = module_at(args.before, "phd_core/uq/calibrate.py")
    record: dict[str, Any] = {"before": args.before, "machine": machine(), "rows": []}
    for copies in args.copies:
        model = tiled_model(copies, 3)
        row = measure(model, old_kernels, old_calibrate, args)
        record["rows"].append(row)
        print(row, flush=True)
    record["load_average_end"] = load_average()
    write_result(RESULTS / "early-stop.json", record)
    write_doc(DOCS / "performance.md", table(record, args), section="early-stop")


def before_fragments(old_kernels):
    """`--before`'s fragment kernel in `render.prepare_view`'s call (it lists every fragment)."""
    return lambda *inputs, cut_for=None: old_kernels.splat_fragments(*inputs[:7])


def measure(model, old_kernels, old_calibrate, args: argparse.Namespace) -> dict[str, Any]:
    height = args.width * 3 // 4
    background = torch.ones(3)
    renderer = GaussianRenderer(model)
    keep = keep_masks(dropout_uniforms(model.num_splats, args.samples, 0), args.ratio)
    seconds: dict[str, list[float]] = {k: [] for k in ("plain_before", "plain_now", "masked_complete",
                                                       "masked_cut")}
    counts = {"complete": 0, "cut": 0, "cut_masked": 0}
    identical = True
    for camera in donut_cameras(args.width, height, args.cameras):
        per_camera: dict[str, list[float]] = {k: [] for k in seconds}
        for repeat in range(1 + args.repeats):
            render.splat_fragments = before_fragments(old_kernels)
            try:
                took_before, before = cpu(lambda: prepare_view(model, camera, background).render_full(None))
                took_masked, masked = cpu(lambda: prepare_view(model, camera, background).render_full(keep))
            finally:
                render.splat_fragments = kernels.splat_fragments
            took_now, now = cpu(lambda: renderer.render_full(camera))
            took_cut, cut = cpu(lambda: prepare_view(model, camera, background, cut=True, keep=keep).render_full(keep))
            if repeat:
                for name, took in (("plain_before", took_before), ("plain_now", took_now),
                                   ("masked_complete", took_masked), ("masked_cut", took_cut)):
                    per_camera[name].append(took)
        identical &= all(torch.equal(getattr(before, k), getattr(now, k)) and torch.equal(getattr(masked, k),
                                                                                         getattr(cut, k))
                         for k in ("rgb", "alpha", "depth"))
        counts["complete"] += len(prepare_view(model, camera, background).alpha)
        counts["cut"] += len(prepare_view(model, camera, background, cut=True).alpha)
        counts["cut_masked"] += len(prepare_view(model, camera, background, cut=True, keep=keep).alpha)
        for name, values in per_camera.items():
            seconds[name].append(statistics.median(values))
    row: dict[str, Any] = {"splats": model.num_splats, "size": f"{args.width}x{height}", "cameras": args.cameras,
                           "fragments_per_camera": {k: v // args.cameras for k, v in counts.items()},
                           "identical_images": identical,
                           **{f"{k}_s": statistics.mean(v) for k, v in seconds.items()}}
    training = donut_cameras(args.width, height, args.views, split="train")
    for executor_name, executor in (("local", LocalExecutor()), ("one chunk", OneChunk())):
        calls: dict[str, list[float]] = {"before": [], "now": []}
        for repeat in range(1 + args.calibration_repeats):
            render.splat_fragments = before_fragments(old_kernels)
            try:
                took_before, result_before = cpu(lambda: old_calibrate.calibrate(renderer, training,
                                                                                 executor=executor))
            finally:
                render.splat_fragments = kernels.splat_fragments
            took_now, result_now = cpu(lambda: uq.calibrate(renderer, training, executor=executor))
            if repeat:
                calls["before"].append(took_before)
                calls["now"].append(took_now)
        row[f"calibrate_{executor_name}"] = {"before_s": min(calls["before"]), "now_s": min(calls["now"]),
                                             "calls": calls, "r_drop": result_now.r_drop,
                                             "same_result": (result_before.r_drop, result_before.errors)
                                             == (result_now.r_drop, result_now.errors)}
    return row


def table(record: dict[str, Any], args: argparse.Namespace) -> str:
    copies = " ".join(str(c) for c in args.copies)
    lines = [f"Command: `OMP_NUM_THREADS=1 .venv/bin/python -m bench.bench_earlystop --before {args.before} "
             f"--copies {copies}` (SH 3, {args.cameras} ring cameras of donut_200, CPU seconds on one thread, "
             f"the median of {args.repeats} calls per camera averaged over the cameras, both versions alternating "
             f"in one process; 1-minute load {record['machine']['load_average'][0]} at the start, "
             f"{record['load_average_end'][0]} at the end). \"unmasked\": `render_full(camera)`, before with every "
             f"fragment listed, now with the lists cut where each pixel is spent. \"N = {args.samples} masks\": "
             f"ratio {args.ratio}, a complete view against one cut for those masks. Images: the same bit for bit "
             "in every row. Fragments: per camera.", "",
             "| splats | size | fragments listed | unmasked: fragments cut | before s | now s | speed-up | "
             f"N = {args.samples} masks: fragments cut | complete s | cut s | cut / complete |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in record["rows"]:
        f = r["fragments_per_camera"]
        lines.append(f"| {r['splats']:,} | {r['size']} | {f['complete']:,} | {f['cut']:,} | {r['plain_before_s']:.3f} "
                     f"| {r['plain_now_s']:.3f} | {r['plain_before_s'] / r['plain_now_s']:.2f}x | {f['cut_masked']:,} "
                     f"| {r['masked_complete_s']:.3f} | {r['masked_cut_s']:.3f} | "
                     f"{r['masked_cut_s'] / r['masked_complete_s']:.2f}x |")
    lines += ["", f"`uq.calibrate` (defaults: 4 masks a ratio) on {args.views} training poses of donut_200, CPU "
              f"seconds, the best of {args.calibration_repeats} calls after one warm-up, the versions alternating; "
              "\"same result\": r_drop and the error curve equal bit for bit. Now each view's reference comes from "
              "the view its first pass prepares for its masks, so a view the cache cannot keep is prepared once a pass "
              "and no longer once more for its reference (local executor: one view a chunk, each with 1/views of the "
              "256 MB cache; one chunk: all views share it).", "",
              "| splats | executor | before s | now s | speed-up | r_drop | same result |",
              "|---|---|---|---|---|---|---|"]
    for r in record["rows"]:
        for name in ("local", "one chunk"):
            c = r[f"calibrate_{name}"]
            lines.append(f"| {r['splats']:,} | {name} | {c['before_s']:.2f} | {c['now_s']:.2f} | "
                         f"{c['before_s'] / c['now_s']:.2f}x | {c['r_drop']} | {'yes' if c['same_result'] else 'no'} |")
    if not all(r["identical_images"] for r in record["rows"]):
        lines.append("\n**Some images differed** (see bench/results/early-stop.json).")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
