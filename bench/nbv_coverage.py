"""How much of what the test views see the captured views see, on the real family (issue 47).

The real family's benchmark (bench_nbv.py --family real) stops at 10 views. Whether its curves can rise
depends on whether 10 views see what the test views show. This measures it without training anything, from
the capture's SfM points and the views each stored run chose: a view sees a point in its frame, in front of
it and not hidden by nearer points (`nbv_experiments.seen_points`); for each test view, the share of the
points it sees that at least one and at least two captured views see, averaged over the test views, the
stored runs and seeds. Beside it, the stored test PSNR per round and what an image of one flat colour (the
mean of the candidate photos) scores on the test views: the floor a model must rise above. Then, for a
capture given with --grow, the same coverage for farthest-view sampling at more views: how many views that
capture needs to be seen as the others are at 10. Last, how many of the SfM points the captured photos could
have triangulated (the point's track holds two of them): what a capture of only those photos would know of
the points, against the whole reconstruction's points that `sfm_coverage` is given.

    PHD_CACHE_DIR=<a directory> OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python -m bench.nbv_coverage
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import pycolmap
import torch

from bench import nbv_experiments
from bench._harness import REAL_CAPTURES, RESULTS, capture_path, write_doc, write_result
from bench.bench_nbv import DOC, initial_views, load_split
from phd_core.data.colmap import find_model
from phd_core.eval import psnr

STORED = RESULTS / "nbv_real_4views"    # the real family's runs from 4 views for every capture, before --cover
SHOWN = ("random", "fvs", "visibility_sigma_fvs")     # the runs whose chosen views are measured


def coverage(seen_captured: torch.Tensor, seen_test: torch.Tensor) -> tuple[float, float]:
    """(share seen by >= 1, by >= 2 captured views) of each test view's points, averaged over the test views.
    seen_captured: [V, P] bool, the captured views; seen_test: [T, P] bool."""
    views = seen_captured.double().sum(0)                                           # [P]
    return (statistics.fmean(float((views[m] >= 1).double().mean()) for m in seen_test),
            statistics.fmean(float((views[m] >= 2).double().mean()) for m in seen_test))


def photo_tracks(capture: Path, names: list[str]) -> list[set[int]]:
    """[P] for each SfM point of `capture`, the photos of its track, as indices into `names` (others dropped)."""
    model = find_model(capture)
    assert model is not None
    reconstruction = pycolmap.Reconstruction(str(model))
    index = {image_id: names.index(image.name) for image_id, image in reconstruction.images.items()
             if image.name in names}
    return [{index[e.image_id] for e in point.track.elements if e.image_id in index}
            for point in reconstruction.points3D.values()]


def triangulated(tracks: list[set[int]], chosen: list[int]) -> float:
    """The share of the points whose track holds at least two of the photos `chosen`."""
    taken = set(chosen)
    return sum(len(track & taken) >= 2 for track in tracks) / len(tracks)


def measure(scene: str, grow: list[int]) -> dict:
    args = argparse.Namespace(family="real", data=Path("/nonexistent"), resolution=50,
                              captures={scene: capture_path(scene)})
    train, test = load_split(args, scene, "train"), load_split(args, scene, "test")
    assert train.points is not None and train.images is not None and test.images is not None
    points = train.points.double()                                                  # [P, 3]
    seen = torch.stack([nbv_experiments.seen_points(c, points) for c in train.cameras])    # [V, P]
    seen_test = torch.stack([nbv_experiments.seen_points(c, points) for c in test.cameras])  # [T, P]
    tasks = [json.loads(p.read_text()) for p in sorted(STORED.glob(f"{scene}-*.json"))]
    kept = tasks[0]["protocol"]
    rounds = kept["rounds"]
    counts = [kept["initial"] + kept["per_round"] * r for r in range(rounds + 1)]        # views per round
    runs = [t["runs"][n] for t in tasks for n in SHOWN if n in t["runs"]]
    covered = [[coverage(seen[run["chosen"][:n]], seen_test) for run in runs] for n in counts]
    mean_colour = torch.stack([im[..., :3].reshape(-1, 3).mean(0) for im in train.images]).mean(0)   # [3]
    flat = statistics.fmean(psnr(mean_colour.expand_as(im[..., :3]).clone(), im[..., :3]) for im in test.images)
    assert train.names is not None
    tracks = photo_tracks(capture_path(scene), list(train.names))
    grown = {n: [coverage(seen[initial_views(train.cameras, n, t["seed"])], seen_test) for t in tasks]
             for n in grow if n < len(train.cameras)}
    return {"scene": scene, "points": len(points), "candidates": len(train.cameras), "test_views": len(test.cameras),
            "seen_per_view": float(seen.double().mean()), "flat_psnr": flat, "views": counts, "runs": len(runs),
            "coverage": [[statistics.fmean(c[i] for c in at) for i in (0, 1)] for at in covered],
            "triangulated": [statistics.fmean(triangulated(tracks, run["chosen"][:n]) for run in runs) for n in counts],
            "psnr": {n: [statistics.fmean(t["runs"][n]["psnr"][r] for t in tasks) for r in range(rounds + 1)]
                     for n in SHOWN},
            "fvs_coverage": {n: [statistics.fmean(c[i] for c in at) for i in (0, 1)] for n, at in grown.items()}}


def markdown(results: list[dict], command: str) -> str:
    counts = results[0]["views"]
    lines = [f"Command: `{command}`. Coverage: for each test view, the share of the SfM points it sees (in frame, in "
             "front, not hidden by nearer points: `bench.nbv_experiments.seen_points`) that at least one / at least "
             f"two captured views see, averaged over the test views and the stored runs of {', '.join(SHOWN)} "
             "(3 seeds each); PSNR: their stored test PSNR per round, the mean over those runs; flat: one colour "
             "(the candidate photos' mean) on every test view.", "",
             "| capture | SfM points | a view sees | flat PSNR | " + " | ".join(f"{n} views: covered, PSNR"
                                                                      for n in counts) + " |",
             "|---|---|---|---|" + "---|" * len(counts)]
    for r in results:
        psnrs = [statistics.fmean(r["psnr"][n][i] for n in SHOWN) for i in range(len(counts))]
        lines.append(f"| {r['scene']} | {r['points']} | {100 * r['seen_per_view']:.0f} % | {r['flat_psnr']:.2f} | "
                     + " | ".join(f"{100 * a:.0f} % / {100 * b:.0f} %, {p:.2f} dB"
                                  for (a, b), p in zip(r["coverage"], psnrs)) + " |")
    for r in results:
        if r["fvs_coverage"]:
            lines += ["", f"{r['scene']} with more views (farthest-view sampling from each seed's first view, seeds "
                      "0-2): covered by one / by two captured views", "",
                      "| views | " + " | ".join(map(str, r["fvs_coverage"])) + " |",
                      "|---|" + "---|" * len(r["fvs_coverage"]),
                      "| covered | " + " | ".join(f"{100 * a:.0f} % / {100 * b:.0f} %"
                                                  for a, b in r["fvs_coverage"].values()) + " |"]
    lines += ["", "The SfM points the captured photos could have triangulated (a track holding two of them), of the "
              "whole reconstruction's, over the same runs: what a capture of only those photos would know of its "
              "points",
              "",
              "| capture | " + " | ".join(f"{n} views" for n in counts) + " |", "|---|" + "---|" * len(counts)]
    lines += [f"| {r['scene']} | " + " | ".join(f"{100 * t:.1f} %" for t in r["triangulated"]) + " |" for r in results]
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(REAL_CAPTURES))
    p.add_argument("--grow", nargs="+", default=["meeting_room_a"], help="captures measured at more views too")
    p.add_argument("--views", type=int, nargs="+", default=[10, 20, 30, 40, 60])
    args = p.parse_args()
    results = [measure(s, args.views if s in args.grow else []) for s in args.scenes]
    write_result(RESULTS / "nbv_real_coverage.json", results)
    write_doc(DOC, markdown(results, "PHD_CACHE_DIR=<a directory> OMP_NUM_THREADS=1 nice -n 19 .venv/bin/python -m "
                            "bench.nbv_coverage"), section="nbv_real_coverage")
    print(markdown(results, "bench.nbv_coverage"))


if __name__ == "__main__":
    main()
