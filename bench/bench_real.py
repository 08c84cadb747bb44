"""Every real capture through the CLI, the Python client and the web page: train, render the
test split, rank next views.

The four captures in ../shared/data/real/ (COLMAP models as their authors published them,
photos downscaled to 240 px: PINHOLE photos smaller than their camera, SIMPLE_RADIAL shared
and per photo, OPENCV), loaded at half that (120 px), and cup_colmap (SIMPLE_PINHOLE, 800x600
photos, downscaled 5x to 160x120), each with fixed settings, as a user types them:

    phd train  --data CAPTURE --views <every train view> --downscale D --iterations N --out M.ply
    phd render --model M.ply --data CAPTURE --split test --out DIR      (test PSNR: DIR/metrics.json)
    phd rank   --model M.ply --candidates orbit:64 --top-k 5 --out rank.json
    phd candidates frames --data CAPTURE --split test --out frames.json
    phd rank   --model M.ply --candidates frames.json --out rank_frames.json

Each command runs in a child process (wall, user and system seconds, peak RSS), one capture
after the other. `--through` adds the service's other doors (default: all three): M.ply and
its sidecar go through one `phd serve` (a child process, with an API key) by the Python client
and by the page in headless Chromium (tests/support/doors.py), each uploading, calibrating with
the defaults and ranking orbit:64 (top 5) and frames.json at `phd rank`'s defaults. A door's
r_drop and rankings are compared with the CLI's (the page's ring, at the page's own elevation,
with the same request through the client), and on the page the 3D view's training cameras and
frusta, the plot's marks and every heat map's size are checked. The table goes to
docs/formats.md ("Every real capture through the CLI, the client and the page").

    PHD_CACHE_DIR=$(mktemp -d) nice -n 10 .venv/bin/python -m bench.bench_real --out bench/results/real.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

from bench import _harness
from phd_core.data import split_size
from tests.support.browser import chromium
from tests.support.doors import through_client, through_page
from tests.support.fixtures import SvcProcess

# capture -> downscale: the longer side at 120-160 px (a few minutes of training each on 2 shared cores)
CAPTURES = {"flask_desk": 2.0, "imac_chair": 2.0, "meeting_room_a": 2.0, "drone_flight1": 2.0, "cup_colmap": 5.0}
DOORS = ("cli", "client", "page")
KEY = "bench-real-key"


def run_capture(name: str, iterations: int, model: Path, frames: Path) -> dict:
    """The CLI door: train, render the test split, rank orbit:64 and the test frames."""
    data, downscale = _harness.capture_path(name), CAPTURES[name]
    phd = _harness.PHD
    renders, ranking = model.with_name(f"{name}_test"), model.with_name(f"{name}_rank.json")
    frames_ranking = model.with_name(f"{name}_frames_rank.json")
    views = split_size(data, "train")
    steps = {
        "train": _harness.child([*phd, "train", "--data", str(data), "--views", str(views), "--downscale",
                                 str(downscale), "--iterations", str(iterations), "--out", str(model), "--quiet"]),
        "render": _harness.child([*phd, "render", "--model", str(model), "--data", str(data), "--split", "test",
                                  "--out", str(renders), "--quiet"]),
        "rank": _harness.child([*phd, "rank", "--model", str(model), "--candidates", "orbit:64", "--top-k", "5",
                                "--out", str(ranking), "--quiet"]),
        "frames": _harness.child([*phd, "candidates", "frames", "--data", str(data), "--split", "test",
                                  "--out", str(frames)]),
        "rank_frames": _harness.child([*phd, "rank", "--model", str(model), "--candidates", str(frames),
                                       "--out", str(frames_ranking), "--quiet"]),
    }
    metrics = json.loads((renders / "metrics.json").read_text())
    sidecar = json.loads(model.with_suffix(".json").read_text())
    sizes = sorted({(c["w"], c["h"]) for c in sidecar["training_cameras"]})
    return {"capture": name, "downscale": downscale, "train_views": views, "iterations": iterations,
            "test_views": len(metrics["views"]), "test_psnr": round(metrics["psnr"], 2),
            "test_ssim": round(metrics["ssim"], 4), "splats": sidecar["num_splats"],
            "training_sizes": [f"{w}x{h}" for w, h in (sizes[0], sizes[-1])],
            "cli": {"orbit": cli_ranking(ranking), "frames": cli_ranking(frames_ranking)}, "steps": steps}


def cli_ranking(path: Path) -> dict:
    """A `phd rank --out` file as the doors' rankings are kept (tests/support/doors.py `ranked`)."""
    ranked = json.loads(path.read_text())
    return {"order": ranked["order"], "scores": [view["score"] for view in ranked["ranking"]],
            "dropout_ratio": ranked["dropout_ratio"]}


def door(run: Callable[[], dict]) -> dict:
    """What a door returned, or the error it stopped with (the other doors and captures still run)."""
    try:
        return run()
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}"[:600]}


def agreement(door_ranking: dict, reference: dict) -> str:
    """'identical' (order and scores to the bit), 'same order' (the largest relative score
    difference), or both orders."""
    if door_ranking["order"] != reference["order"]:
        return f"order {door_ranking['order'][:8]} against {reference['order'][:8]}"
    if door_ranking["scores"] == reference["scores"]:
        return "identical"
    worst = max(abs(a - b) / max(abs(b), 1e-30) for a, b in zip(door_ranking["scores"], reference["scores"]))
    return f"same order, scores within {worst:.1e}"


def check(row: dict, name: str) -> None:
    """A door's rankings against the CLI's (row[name]["agreement"]), and what it got wrong
    (row[name]["problems"]): another r_drop or order, a heat map or (page) a view or plot
    that does not show what was ranked."""
    result, cli = row[name], row["cli"]
    if "error" in result:
        return
    # The page ranks a ring at its own elevation field: the same request through the client is its reference.
    ring = cli["orbit"] if name == "client" else result["orbit_through_client"]
    result["agreement"] = {"orbit": agreement(result["orbit"], ring),
                           "frames": agreement(result["frames"], cli["frames"])}
    problems = [f"{what}: {said}" for what, said in result["agreement"].items() if said.startswith("order")]
    if result["r_drop"] != cli["frames"]["dropout_ratio"]:
        problems.append(f"r_drop {result['r_drop']} against the CLI's {cli['frames']['dropout_ratio']}")
    if name == "client" and result["training_cameras"] != row["train_views"]:
        problems.append(f"{result['training_cameras']} training cameras uploaded of {row['train_views']}")
    if name == "client" and result["heatmap_size"] != result["frame_size"]:
        problems.append(f"heat map {result['heatmap_size']} for a {result['frame_size']} frame")
    if name == "page":
        problems += page_problems(result, row["train_views"])
    result["problems"] = problems


def page_problems(result: dict, training: int) -> list[str]:
    """What the page showed that differs from what it ranked: its training cameras in the 3D
    view and the plot, a frustum and a dot per ranked pose, heat maps at their frames' sizes,
    and any error in the browser's console."""
    problems = []
    for what in ("orbit", "frames"):
        shown, count = result[what], len(result[what]["order"])
        if shown["view"]["training"] != training or shown["plot"]["training"] != training:
            problems.append(f"{what}: {shown['view']['training']} training cameras in the 3D view, "
                            f"{shown['plot']['training']} in the plot, of {training}")
        if shown["view"]["frusta"] != count or shown["plot"]["candidates"] != count:
            problems.append(f"{what}: {shown['view']['frusta']} frusta, {shown['plot']['candidates']} dots "
                            f"for {count} ranked")
        if shown["heatmap_sizes"] != shown["frame_sizes"]:
            problems.append(f"{what}: heat maps not at their frames' sizes")
    return problems + [f"console: {message[:200]}" for message in result["console_errors"]]


def table(result: dict) -> str:
    rows = ["| capture | camera model | training views (size) | test views | test PSNR | test SSIM | splats | "
            "CLI: train / render / rank / frames rank s | client | page | rankings against the CLI's |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in result["captures"]:
        low, high = row["training_sizes"]
        size = low if low == high else f"{low} to {high}"
        steps = " / ".join(f"{row['steps'][k]['wall_s']:.0f}" for k in ("train", "render", "rank", "rank_frames"))
        doors = [door_cell(row.get(name)) for name in ("client", "page")]
        rows.append(f"| {row['capture']} | {MODELS[row['capture']]} | {row['train_views']} ({size}) | "
                    f"{row['test_views']} | {row['test_psnr']:.2f} dB | {row['test_ssim']:.3f} | {row['splats']:,} | "
                    f"{steps} | {doors[0]} | {doors[1]} | {agreement_cell(row)} |")
    machine = result["machine"]
    return "\n".join(rows) + (
        f"\n\n{result['iterations']} iterations each; {_harness.machine_text(machine)}, load average "
        f"{machine['load_average']} at the start and {result['load_average_at_end']} at the end (the "
        f"machine shared with other work: wall times are not comparable across rows). Command:\n\n"
        f"    PHD_CACHE_DIR=$(mktemp -d) nice -n 10 .venv/bin/{result['command']}")


def door_cell(result: dict | None) -> str:
    """'ok, 41 s' (upload to the last ranking), the problems found, the error, or '' (not taken)."""
    if result is None:
        return ""
    if "error" in result:
        return f"error: {result['error']}"
    seconds = f"{sum(result['seconds'].values()):.0f} s"
    return f"ok, {seconds}" if not result["problems"] else f"{seconds}; " + "; ".join(result["problems"])


def agreement_cell(row: dict) -> str:
    """How the doors' rankings (orbit, frames) agree with the CLI's, door by door."""
    parts = []
    for name in ("client", "page"):
        if name in row and "agreement" in row[name]:
            said = row[name]["agreement"]
            same = said["orbit"] == said["frames"]
            parts.append(f"{name}: " + (said["orbit"] if same else f"orbit {said['orbit']}, frames {said['frames']}"))
    return "; ".join(parts)


MODELS = {"flask_desk": "PINHOLE (946x532 camera, 240x135 photos)", "imac_chair": "SIMPLE_RADIAL, shared",
          "meeting_room_a": "SIMPLE_RADIAL, one per photo", "drone_flight1": "OPENCV, shared",
          "cup_colmap": "SIMPLE_PINHOLE, one per photo"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", default=",".join(CAPTURES))
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--through", default=",".join(DOORS),
                        help="the doors, comma-separated: cli (always: it trains the model), client, page")
    parser.add_argument("--out", type=Path, default=_harness.RESULTS / "real.json")
    parser.add_argument("--doc", type=Path, default=_harness.DOCS / "formats.md")
    args = parser.parse_args()
    doors = args.through.split(",")
    if "cli" not in doors or not set(doors) <= set(DOORS):
        parser.error(f"--through: some of {', '.join(DOORS)}, cli among them")
    result: dict[str, Any] = {"command": _harness.command(), "machine": _harness.machine(),
                              "iterations": args.iterations, "through": doors, "captures": []}
    work = Path(tempfile.mkdtemp(prefix="bench_real_"))
    server = driver = None
    try:
        if "client" in doors or "page" in doors:
            cache = {"PHD_CACHE_DIR": os.environ["PHD_CACHE_DIR"]} if "PHD_CACHE_DIR" in os.environ else {}
            server = SvcProcess(work / "served", start_timeout=120, PHD_API_KEY=KEY, **cache)
        if "page" in doors:
            driver = chromium(work / "chromium")
        for name in args.captures.split(","):
            model, frames = work / f"{name}.ply", work / f"{name}_frames.json"
            row = run_capture(name, args.iterations, model, frames)
            if server is not None and "client" in doors:
                row["client"] = door(lambda: through_client(server.url, KEY, model, frames))
                check(row, "client")
            if server is not None and driver is not None:
                row["page"] = door(lambda: through_page(driver, server.url, KEY, model, frames))
                check(row, "page")
            print(json.dumps(row), flush=True)
            result["captures"].append(row)
            _harness.write_result(args.out, result)
    finally:
        if driver is not None:
            driver.quit()
        if server is not None:
            server.kill()
        shutil.rmtree(work, ignore_errors=True)
    result["load_average_at_end"] = _harness.load_average()
    _harness.write_result(args.out, result)
    _harness.write_doc(args.doc, table(result), "real")


if __name__ == "__main__":
    main()
