"""Photos in, a model out: `phd capture` on real photos, each capture compared with the COLMAP
model its authors published beside the photos.

Per input (cup_colmap's 77 photos at each of --sizes px on the longer side, and the photos of
every capture in ../shared/data/real/, stored at 240 px), `phd capture` runs in a child
process as a user runs it. Reported: seconds per stage (from its phd_capture.json), the share
of the photos registered, and how well the recovered camera centres agree with the published
model's after the best similarity (Umeyama in float64, tests/support/alignment.py: the RMS
residual over the RMS spread of the centres; ~1 for centres that do not correspond).

Then the trained model's test PSNR through each capture. Both captures are cut to the photos
both register and named as the photo files are, so that the test split (every 8th name,
sorted) holds the same photos in both; each is trained with `phd train --views V --downscale
(its width / --train-width) --iterations I --seed S` and scored with `phd render --split test`
against its own images: ours undistorted by COLMAP's image_undistorter in `phd capture`, the
published ones as the project's reader loads them (real/'s distorted cameras undistorted by
pycolmap, flask_desk's cameras scaled to its smaller photos).

Last, the user's path on cup_colmap at the first size, each step a `phd` command timed by the
wall clock: capture -> train -> `phd rank --candidates orbit:64 --top-k 5` (which calibrates
first).

    nice -n 10 .venv/bin/python -m bench.bench_sfm --out bench/results/sfm.json --doc
    .venv/bin/python -m bench.bench_sfm --table --doc     # the table again from bench/results/sfm.json
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from bench import _harness
from phd_core.data import load_dataset
from phd_core.process.capture import REPORT
from phd_core.process.photos import list_photos
from tests.support.alignment import relative_residual

CUP = _harness.DATA / "cup_colmap"
REAL = _harness.DATA / "real"


def phd(*argv) -> dict:
    """`phd ARGV` in a child: its wall and CPU seconds and the load average around it, or the
    error it stopped with."""
    before = _harness.load_average()
    try:
        timing = _harness.child(_harness.PHD + [str(a) for a in argv])
    except RuntimeError as exc:
        said = re.search(r"phd \w+: error: .*", str(exc))
        return {"error": said.group(0) if said else str(exc)[-300:], "load": before}
    return {**timing, "load": before, "load_after": _harness.load_average()}


def published_centres(folder: Path) -> dict[str, np.ndarray]:
    """Camera centre of every image of a COLMAP model, by image name (pycolmap reads it)."""
    model = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    return {image.name: image.projection_center() for image in model.images.values() if image.has_pose}


def capture(photos: Path, out: Path, published: Path, max_size: int) -> dict:
    """`phd capture` on `photos`, and its agreement with the `published` capture of them."""
    run = phd("capture", photos, "--out", out, "--max-size", max_size, "--quiet")
    if "error" in run:
        return {"run": run, "photos": len(list_photos([photos])[0])}
    report = json.loads((out / REPORT).read_text())
    ours = published_centres(out)
    theirs = published_centres(published)
    photo_of = {name: Path(origin).name for name, origin in report["origins"].items()}
    common = [name for name in sorted(ours) if photo_of[name] in theirs]
    residual = relative_residual(np.array([ours[n] for n in common]), np.array([theirs[photo_of[n]] for n in common]))
    size = load_dataset(out, "all", views=1, with_images=False).cameras[0]
    registered = len(report["registered"])
    return {"run": run, "photos": report["inputs"], "registered": registered,
            "share": round(registered / report["inputs"], 3), "matcher": report["matcher"],
            "seconds": report["seconds"], "points": report["points"],
            "reprojection_error_px": report["reprojection_error"], "undistorted_size": [size.width, size.height],
            "centres_compared": len(common), "centre_residual": round(residual, 4), "photo_of": photo_of}


def cut(folder: Path, names: dict[str, str], out: Path) -> Path:
    """The COLMAP capture `folder` with only the images `names` holds, each renamed to its
    value (its images copied: the reader refuses links that lead outside the folder)."""
    model = pycolmap.Reconstruction(str(folder / "sparse" / "0"))
    for image in list(model.images.values()):
        if image.name in names:
            model.images[image.image_id].name = names[image.name]
        else:
            model.deregister_frame(image.frame_id)
    (out / "sparse" / "0").mkdir(parents=True)
    model.write(str(out / "sparse" / "0"))
    (out / "images").mkdir()
    for old, new in names.items():
        shutil.copyfile(folder / "images" / old, out / "images" / new)
    return out


def train_and_score(data: Path, run: Path, args: argparse.Namespace, seed: int) -> dict:
    """`phd train` then `phd render --split test` on `data`: PSNR, SSIM and seconds."""
    width = load_dataset(data, "test", views=1, with_images=False).cameras[0].width
    model = run / "model.ply"
    trained = phd("train", "--data", data, "--views", args.views, "--downscale", width / args.train_width,
                  "--iterations", args.iterations, "--seed", seed, "--out", model, "--quiet")
    if "error" in trained:
        return {"train": trained}
    rendered = phd("render", "--model", model, "--data", data, "--split", "test", "--out", run / "test", "--quiet")
    if "error" in rendered:
        return {"train": trained, "render": rendered}
    metrics = json.loads((run / "test" / "metrics.json").read_text())
    return {"train": trained, "render": rendered, "psnr": round(metrics["psnr"], 2),
            "ssim": round(metrics["ssim"], 4), "test_views": len(metrics["views"])}


def compare(row: dict, ours: Path, published: Path, work: Path, args: argparse.Namespace) -> None:
    """Train and score our capture and the published one, both cut to the photos both
    register (row["scores"], by seed)."""
    theirs = set(published_centres(published))
    registered = set(json.loads((ours / REPORT).read_text())["registered"])
    names = {name: photo for name, photo in row["photo_of"].items() if name in registered and photo in theirs}
    row["common"] = len(names)
    ours_cut = cut(ours, names, work / "ours")
    theirs_cut = cut(published, {photo: photo for photo in names.values()}, work / "theirs")
    row["scores"] = {seed: {"ours": train_and_score(ours_cut, work / f"ours_run{seed}", args, seed),
                            "theirs": train_and_score(theirs_cut, work / f"theirs_run{seed}", args, seed)}
                     for seed in args.seeds}


def user_path(out: Path, work: Path, args: argparse.Namespace) -> dict:
    """capture (already timed) -> train -> rank on our capture as it was written."""
    width = load_dataset(out, "test", views=1, with_images=False).cameras[0].width
    model = work / "path" / "model.ply"
    trained = phd("train", "--data", out, "--views", args.views, "--downscale", width / args.train_width,
                  "--iterations", args.iterations, "--out", model, "--quiet")
    ranked = phd("rank", "--model", model, "--candidates", "orbit:64", "--top-k", 5, "--quiet")
    return {"train": trained, "rank": ranked}


def table(result: dict) -> str:
    """The markdown table of a result file."""
    lines = ["| input | photos | registered | matcher | features | matching | mapping | undistortion | all stages "
             "| load at start | centres vs published | test PSNR ours / published (views) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in result["captures"]:
        if "registered" not in row:
            reason = row["run"]["error"].split(": error: ", 1)[-1].split(":")[0]
            lines.append(f"| {row['input']} | {row['photos']} | refused ({reason}) |" + " |" * 9)
            continue
        s = row["seconds"]
        scores = [score for score in row.get("scores", {}).values()]
        psnr = "; ".join(f"{_psnr(score.get('ours'))} / {_psnr(score.get('theirs'))}" for score in scores)
        views = scores[0]["ours"].get("test_views", "") if scores else ""
        lines.append(f"| {row['input']} | {row['photos']} | {row['registered']} ({row['share']:.0%}) | "
                     f"{row['matcher']} | {s['features']:.0f} s | {s['matching']:.0f} s | {s['mapping']:.0f} s | "
                     f"{s['undistortion']:.0f} s | {sum(s.values()):.0f} s | {row['run']['load'][0]:.1f} | "
                     f"{row['centre_residual']:.3f} ({row['centres_compared']}) | {psnr} ({views}) |")
    return "\n".join(lines)


def path_line(result: dict) -> str:
    """The user's path, as a sentence of wall-clock seconds."""
    path = result["path"]
    steps = ", ".join(f"`phd {step}` {path[step]['wall_s']:.0f} s (load average {path[step]['load'][0]:.1f})"
                      for step in ("capture", "train", "rank") if "wall_s" in path[step])
    return f"The path on {result['captures'][0]['input']}: {steps}."


def _psnr(score: dict | None) -> str:
    if score is None:
        return "n/a"
    return f"{score['psnr']:.2f} dB" if "psnr" in score else "failed"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="800,400", help="cup_colmap's photos at these --max-size values (px)")
    parser.add_argument("--real", default=",".join(p.name for p in sorted(REAL.iterdir()) if (p / "images").is_dir()),
                        help="captures in ../shared/data/real/ (comma-separated; '' for none)")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--train-width", type=int, default=80, help="training and test images this many px wide")
    parser.add_argument("--seeds", default="0", help="training seeds, comma-separated")
    parser.add_argument("--out", type=Path, default=_harness.RESULTS / "sfm.json")
    parser.add_argument("--doc", action="store_true", help="write the table into docs/formats.md")
    parser.add_argument("--table", action="store_true", help="only print (and with --doc write) the table of --out")
    args = parser.parse_args()
    if args.table:
        report(json.loads(args.out.read_text()), args.doc)
        return
    args.seeds = [int(s) for s in args.seeds.split(",")]
    work = Path(tempfile.mkdtemp(prefix="bench_sfm."))
    # (label, photos, the published capture of them, --max-size)
    inputs = [(f"cup_colmap, {size} px", CUP / "images", CUP, int(size)) for size in args.sizes.split(",") if size]
    inputs += [(f"real/{name}, 240 px", REAL / name / "images", REAL / name, 1600)
               for name in args.real.split(",") if name]
    result: dict[str, Any] = {"command": _harness.command(), "machine": _harness.machine(), "settings": {
        "views": args.views, "iterations": args.iterations, "train_width": args.train_width, "seeds": args.seeds},
        "captures": []}
    for i, (label, photos, published, size) in enumerate(inputs):
        out = work / f"capture{i}"
        row = {"input": label, **capture(photos, out, published, size)}
        if "registered" in row:
            compare(row, out, published, work / f"compare{i}", args)
            if i == 0:
                result["path"] = {"capture": row["run"], **user_path(out, work, args)}
        row.pop("photo_of", None)
        result["captures"].append(row)
        print(json.dumps(row), flush=True)
        _harness.write_result(args.out, result)
    result["machine"]["load_average_at_end"] = _harness.load_average()
    _harness.write_result(args.out, result)
    report(result, args.doc)
    shutil.rmtree(work)


def report(result: dict, doc: bool) -> None:
    """Print the table of a result, and write it into docs/formats.md when `doc`."""
    text = table(result) + ("\n\n" + path_line(result) if "path" in result else "")
    print(text)
    if doc:
        _harness.write_doc(_harness.DOCS / "formats.md", text, section="sfm")


if __name__ == "__main__":
    main()
