"""Every real capture through the CLI: train, render the test split, rank next views.

The four captures in ../shared/data/real/ (COLMAP models as their authors published them,
photos downscaled to 240 px: PINHOLE photos smaller than their camera, SIMPLE_RADIAL shared
and per photo, OPENCV), loaded at half that (120 px), and cup_colmap (SIMPLE_PINHOLE, 800x600
photos, downscaled 5x to 160x120), each with fixed settings, as a user types them:

    phd train  --data CAPTURE --views <every train view> --downscale D --iterations N --out M.ply
    phd render --model M.ply --data CAPTURE --split test --out DIR      (test PSNR: DIR/metrics.json)
    phd rank   --model M.ply --candidates orbit:64 --top-k 5 --out rank.json

Each command runs in a child process (wall, user and system seconds, peak RSS), one capture
after the other; the table goes to docs/formats.md ("Every real capture through the CLI").

    nice -n 5 .venv/bin/python -m bench.bench_real --out bench/results/real.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from bench import _harness
from phd_core.data import split_size

# capture -> downscale: the longer side at 120-160 px (a few minutes of training each on 2 shared cores)
CAPTURES = {"flask_desk": 2.0, "imac_chair": 2.0, "meeting_room_a": 2.0, "drone_flight1": 2.0, "cup_colmap": 5.0}


def capture_path(name: str) -> Path:
    return _harness.DATA / name if name == "cup_colmap" else _harness.DATA / "real" / name


def run_capture(name: str, iterations: int, work: Path) -> dict:
    data, downscale = capture_path(name), CAPTURES[name]
    phd = _harness.PHD
    model, renders, ranking = work / f"{name}.ply", work / f"{name}_test", work / f"{name}_rank.json"
    views = split_size(data, "train")
    steps = {
        "train": _harness.child([*phd, "train", "--data", str(data), "--views", str(views), "--downscale",
                                 str(downscale), "--iterations", str(iterations), "--out", str(model), "--quiet"]),
        "render": _harness.child([*phd, "render", "--model", str(model), "--data", str(data), "--split", "test",
                                  "--out", str(renders), "--quiet"]),
        "rank": _harness.child([*phd, "rank", "--model", str(model), "--candidates", "orbit:64", "--top-k", "5",
                                "--out", str(ranking), "--quiet"]),
    }
    metrics = json.loads((renders / "metrics.json").read_text())
    ranked = json.loads(ranking.read_text())
    sidecar = json.loads(model.with_suffix(".json").read_text())
    sizes = sorted({(c["w"], c["h"]) for c in sidecar["training_cameras"]})
    return {"capture": name, "downscale": downscale, "train_views": views, "iterations": iterations,
            "test_views": len(metrics["views"]), "test_psnr": round(metrics["psnr"], 2),
            "test_ssim": round(metrics["ssim"], 4), "splats": sidecar["num_splats"],
            "training_sizes": [f"{w}x{h}" for w, h in (sizes[0], sizes[-1])],
            "dropout_ratio": ranked["dropout_ratio"], "first_ranked": ranked["order"][:5], "steps": steps}


def table(result: dict) -> str:
    rows = ["| capture | camera model | training views (size) | test views | test PSNR | test SSIM | splats | "
            "train / render / rank wall s |", "|---|---|---|---|---|---|---|---|"]
    for row in result["captures"]:
        low, high = row["training_sizes"]
        size = low if low == high else f"{low} to {high}"
        steps = " / ".join(f"{row['steps'][k]['wall_s']:.0f}" for k in ("train", "render", "rank"))
        rows.append(f"| {row['capture']} | {MODELS[row['capture']]} | {row['train_views']} ({size}) | "
                    f"{row['test_views']} | {row['test_psnr']:.2f} dB | {row['test_ssim']:.3f} | {row['splats']:,} | "
                    f"{steps} |")
    machine = result["machine"]
    return "\n".join(rows) + (
        f"\n\n{result['iterations']} iterations each; {_harness.machine_text(machine)}, load average "
        f"{machine['load_average']} at the start and {result['load_average_at_end']} at the end (the "
        f"machine shared with other work: wall times are not comparable across rows). Command:\n\n"
        f"    nice -n 5 .venv/bin/{result['command']}")


MODELS = {"flask_desk": "PINHOLE (946x532 camera, 240x135 photos)", "imac_chair": "SIMPLE_RADIAL, shared",
          "meeting_room_a": "SIMPLE_RADIAL, one per photo", "drone_flight1": "OPENCV, shared",
          "cup_colmap": "SIMPLE_PINHOLE, one per photo"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", default=",".join(CAPTURES))
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--out", type=Path, default=_harness.RESULTS / "real.json")
    parser.add_argument("--doc", type=Path, default=_harness.DOCS / "formats.md")
    args = parser.parse_args()
    result = {"command": _harness.command(), "machine": _harness.machine(), "iterations": args.iterations,
              "captures": []}
    work = Path(tempfile.mkdtemp(prefix="bench_real_"))
    try:
        for name in args.captures.split(","):
            row = run_capture(name, args.iterations, work)
            print(json.dumps(row), flush=True)
            result["captures"].append(row)
            _harness.write_result(args.out, result)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["load_average_at_end"] = _harness.load_average()
    _harness.write_result(args.out, result)
    _harness.write_doc(args.doc, table(result), "real")


if __name__ == "__main__":
    main()
