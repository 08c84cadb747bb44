"""The capture loop through the service and the client (issue 49): photos in, a model trained,
the next views out, the photos of those views added, round after round; with the default's picks
against random and farthest-view (FVS) picks, and warm-started training against a cold start.

A run is one loop on one scene and seed, through a real uvicorn server (`service.runner`) and
`PHDClient`'s `Capture`:

- round 0: a capture from the first photos (4 to train on, the test photos held out: they take
  part in structure-from-motion, never in training), trained, its next views asked;
- each later round: the photos of the views asked for are added (registered into the capture),
  the capture trained again (warm-started from the last model unless the run is cold), the next
  views asked again; `--rounds` rounds of `--per-round` views.

The "camera" that takes the asked photo: on the generated scene (`bench.loop_scene`) the
ground-truth model rendered at the asked pose; on a real capture (cup_colmap) its own photo
nearest the asked pose. The asked poses are in the capture's frame; the similarity between the
first photos' registered cameras and the poses they were taken at (Umeyama) maps them to the
scene's. The candidates are the same for every strategy: on the generated scene 48 poses on
three rings around it (elevations 15, 25, 35 degrees), on cup_colmap its photos that are neither
test photos nor taken, both given to the service as cameras in the capture's frame.

Test PSNR per round is the service's own (`TrainSummary.test_psnr`, its renders of the held-out
photos), so the table measures what a user of the loop sees. Training steps grow with the views
(`--iterations-per-view`) so that a round's model is trained as well as the last one's.

    PHD_CACHE_DIR=$(mktemp -d) OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_loop \\
        --family generated --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from bench._harness import DATA, DOCS, RESULTS, command, fmt, machine, machine_text, write_doc, write_result
from bench.bench_nbv import BOOTSTRAP, bootstrap_interval
from bench.loop_scene import GeneratedScene, NearestFrame, Similarity, fit_similarity
from client import JobFailedError, PHDClient, RankResult, TrainResult
from phd_core.data import load_dataset
from phd_core.scene import Camera, camera_from_frame
from phd_core.uq.strategies import DEFAULT_STRATEGY
from service.runner import BackgroundServer
from service.settings import Settings

RUNS = {                      # name: (strategy, warm start)
    "default": (DEFAULT_STRATEGY, True),
    "default-cold": (DEFAULT_STRATEGY, False),
    "random": ("random", True),
    "fvs": ("fvs", True),
}
CUP = DATA / "cup_colmap"
DOC = DOCS / "service.md"


@dataclass
class Scene:
    """One loop's world: the first photos, the test photos among them, the candidates (world
    poses), and the camera that takes the photo of a world pose."""

    photos: Path                                   # folder of the first photos
    test: list[str]
    world: dict[str, np.ndarray]                   # c2w [4, 4] of each first photo, the scene's frame
    candidates: list[Camera]                       # world poses
    take: Callable[[np.ndarray, Path], Path]       # (world c2w, folder) -> the photo written there
    sfm: dict[str, object]


def generated(seed: int, root: Path) -> Scene:
    """The painted scene (`GeneratedScene(surface=True)`): a ring of 16 photos first (what registers
    for it, bench/loop_scene.py), every 4th to train on and the 12 between them the test photos; the
    candidates three rings of 16 at 15, 25 and 35 degrees up, between the first ring's poses."""
    scene = GeneratedScene(seed, surface=True)
    first = scene.ring(16)
    names = [f"view_{k:02d}.png" for k in range(len(first))]
    scene.write_photos(first, root / "first", names)
    candidates = [c for elevation in (15, 25, 35) for c in scene.ring(16, elevation=elevation, phase=0.25)]
    taken = [0]

    def take(c2w: np.ndarray, folder: Path) -> Path:
        taken[0] += 1
        camera = first[0]
        asked = Camera(c2w=torch.from_numpy(c2w), fx=camera.fx, fy=camera.fy, cx=camera.cx,
                       cy=camera.cy, width=camera.width, height=camera.height)
        return scene.write_photos([asked], folder, [f"asked_{taken[0]:02d}.png"])[0]

    return Scene(root / "first", [n for k, n in enumerate(names) if k % 4],
                 {n: c.c2w.double().numpy() for n, c in zip(names, first)}, candidates, take,
                 {"min_registered": 4, "camera_model": "SIMPLE_PINHOLE"})


def real(seed: int, root: Path) -> Scene:
    """cup_colmap's photos 18-41 (one continuous walk: photos farther apart than about three places
    share too little at 300-400 px for structure-from-motion to register them): every 4th a test
    photo, 4 of the others (spread, placed by the seed) the first to train on, the rest the
    candidates."""
    data = load_dataset(CUP, "all", with_images=False)
    assert data.names is not None
    frames = NearestFrame(CUP)
    walk = [data.names.index(f"{n}.jpg") for n in range(18, 42)]
    test = walk[::4]
    rest = [i for i in walk if i not in test]
    first = [rest[(seed + k * len(rest) // 4) % len(rest)] for k in range(4)]
    (root / "first").mkdir(parents=True)
    for i in test + first:
        shutil.copy(frames.paths[i], root / "first" / frames.names[i])
    frames.taken.update(set(range(len(frames.names))) - set(rest) | set(first))

    def take(c2w: np.ndarray, folder: Path) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        index = frames.nearest(c2w)
        return Path(shutil.copy(frames.paths[index], folder / frames.names[index]))

    return Scene(root / "first", [data.names[i] for i in test],
                 {data.names[i]: data.cameras[i].c2w.double().numpy() for i in test + first},
                 [data.cameras[i].resized(400, 300) for i in rest if i not in first], take, {"min_registered": 4})


def to_capture(similarity: Similarity, camera: Camera) -> dict:
    """A world camera as a transforms frame in the capture's frame (the similarity inverted)."""
    c2w = camera.c2w.double().numpy()
    out = np.eye(4)
    out[:3, :3] = similarity.rotation.T @ c2w[:3, :3]
    out[:3, 3] = similarity.rotation.T @ (c2w[:3, 3] - similarity.translation) / similarity.scale
    frame = camera.to_frame()
    frame["transform_matrix"] = out.tolist()
    return frame


def run_loop(phd: PHDClient, scene: Scene, root: Path, *, strategy: str, warm: bool, seed: int, rounds: int,
             per_round: int, iterations_per_view: int, downscale: float, samples: int) -> dict:
    """One loop (module docstring); per round: views, PSNR, sigma-max-bar, seconds per stage."""
    capture = phd.create_capture(scene.photos, test=scene.test, **scene.sfm)
    first = capture.info.rounds[0]
    names = first.registered                      # the order of `captured`
    ours = np.array([camera_from_frame(f).c2w.double().numpy()[:3, 3] for f in first.captured])
    similarity = fit_similarity(ours, np.array([scene.world[n][:3, 3] for n in names]))
    chosen: list[int] = []
    latest: list[dict] = []          # the poses the last round asked for
    out = []
    for number in range(rounds + 1):
        if number:
            folder = root / f"round{number}"
            for frame in latest:
                scene.take(similarity.c2w(np.array(frame["transform_matrix"])), folder)
            try:
                capture.add_photos(folder)
            except JobFailedError as failed:         # none registered: the round trains on what it has
                print(f"  round {number}: {failed}", flush=True)
                capture.refresh()
        views = capture.info.num_photos - len(capture.info.test_photos)
        trained = capture.train(iterations=iterations_per_view * views, downscale=downscale, seed=seed,
                                warm_start=warm, samples=samples)
        assert isinstance(trained, TrainResult)            # waited for
        summary = trained.summary
        left = [i for i in range(len(scene.candidates)) if i not in chosen]
        started = time.perf_counter()
        ranked = capture.next_views(per_round, cameras=[to_capture(similarity, scene.candidates[i]) for i in left],
                                    strategy=strategy, seed=seed + number, samples=samples, downscale=downscale)
        rank_seconds = time.perf_counter() - started
        assert isinstance(ranked, RankResult)
        chosen += [left[v.index] for v in ranked.views]
        latest = [v.camera for v in ranked.views if v.camera is not None]
        entry = capture.info.rounds[-1]
        added = len(entry.registered) if entry.round == number else 0        # 0: none of the round's registered
        out.append({"round": number, "views": views, "registered": added,
                    "not_registered": entry.not_registered, "psnr": summary.test_psnr,
                    "sigma_max_bar": summary.sigma_max_bar, "r_drop": summary.r_drop, "splats": summary.num_units,
                    "seconds": {"sfm": entry.sfm_seconds, "train": summary.seconds, "rank": round(rank_seconds, 2)}})
        print(f"  round {number}: {views} views, PSNR {summary.test_psnr}, train {summary.seconds:.1f} s", flush=True)
    phd.delete_capture(capture.id)
    return {"rounds": out, "test_photos": len(scene.test)}


# ----------------------------------------------------------------------------- report

def final_differences(results: dict[str, dict], name: str, baseline: str) -> dict | None:
    """Final PSNR of `name` minus `baseline`'s, paired by seed; bootstrap over the seeds."""
    by_seed = {seed: [runs[name]["rounds"][-1]["psnr"] - runs[baseline]["rounds"][-1]["psnr"]]
               for seed, runs in results.items() if name in runs and baseline in runs}
    if len(by_seed) < 2:
        return None
    low, high = bootstrap_interval(by_seed)
    diffs = [d[0] for d in by_seed.values()]
    return {"mean": statistics.fmean(diffs), "low": low, "high": high, "wins": sum(d > 0 for d in diffs),
            "pairs": len(diffs)}


def markdown(family: str, results: dict[str, dict], record: dict) -> str:
    seeds = sorted(results)
    rounds = max(len(r["rounds"]) for runs in results.values() for r in runs.values())
    lines = [f"Family `{family}`, seeds {', '.join(map(str, seeds))}; {machine_text(record)}. Command: "
             f"`{record['command']}`.", "",
             "Test PSNR (dB) on the held-out photos after each round, mean over the seeds (the views trained on "
             "in brackets):", "",
             "| run | " + " | ".join(f"round {r}" for r in range(rounds)) + " |",
             "|---|" + "---|" * rounds]
    for name in RUNS:
        per_round = [[runs[name]["rounds"][r] for runs in results.values() if name in runs] for r in range(rounds)]
        if not per_round[0]:
            continue
        cells = [f"{statistics.fmean(e['psnr'] for e in entries):.2f} ({entries[0]['views']})" for entries in per_round]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", f"Final PSNR differences paired by seed ({BOOTSTRAP} bootstrap resamples of the seeds; with 3 "
              "seeds the interval is coarse):", "", "| | mean dB | 95 % interval | seeds ahead |", "|---|---|---|---|"]
    for name, baseline in (("default", "random"), ("default", "fvs"), ("default", "default-cold")):
        found = final_differences(results, name, baseline)
        if found:
            lines.append(f"| {name} - {baseline} | {found['mean']:+.2f} | [{found['low']:+.2f}, {found['high']:+.2f}] "
                         f"| {found['wins']} of {found['pairs']} |")
    lines += ["", "Seconds per round, mean over the seeds and rounds (structure-from-motion, training, ranking), "
              "and the splats of the last model:", "", "| run | SfM | train | rank | splats |", "|---|---|---|---|---|"]
    for name in RUNS:
        entries = [e for runs in results.values() if name in runs for e in runs[name]["rounds"]]
        if entries:
            lines.append(f"| {name} | {statistics.fmean(e['seconds']['sfm'] for e in entries):.1f} | "
                         f"{statistics.fmean(e['seconds']['train'] for e in entries):.1f} | "
                         f"{statistics.fmean(e['seconds']['rank'] for e in entries):.1f} | "
                         f"{fmt(statistics.fmean(e['splats'] for e in entries), 0)} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--family", choices=("generated", "real"), default="generated")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--per-round", type=int, default=2)
    p.add_argument("--iterations-per-view", type=int, default=300)
    p.add_argument("--downscale", type=float, default=2.0, help="train and test at 1/downscale of the photos")
    p.add_argument("--samples", type=int, default=16)
    p.add_argument("--results", type=Path, default=RESULTS / "loop")
    p.add_argument("--report", action="store_true", help="only rewrite the doc from the stored results")
    args = p.parse_args()
    path = args.results / f"{args.family}.json"
    stored = json.loads(path.read_text()) if path.is_file() else {"results": {}}
    results: dict[str, dict] = stored["results"]
    record = stored.get("record") or {**machine(), "command": command()}
    if not args.report:
        record = {**machine(), "command": command()}
        with tempfile.TemporaryDirectory(prefix="phd-loop-") as tmp, BackgroundServer(Settings(
                data_dir=Path(tmp) / "data", capture_max_size=400, max_image_size=400)) as server, \
                PHDClient(server.url, timeout=600) as phd:
            for seed in args.seeds:
                for name in args.runs:
                    strategy, warm = RUNS[name]
                    print(f"{args.family} seed {seed} {name}", flush=True)
                    root = Path(tmp) / f"{seed}-{name}"
                    scene = (generated if args.family == "generated" else real)(seed, root)
                    results.setdefault(str(seed), {})[name] = run_loop(
                        phd, scene, root, strategy=strategy, warm=warm, seed=seed, rounds=args.rounds,
                        per_round=args.per_round, iterations_per_view=args.iterations_per_view,
                        downscale=args.downscale, samples=args.samples)
                    write_result(path, {"record": record, "results": results})
    if args.results == RESULTS / "loop":            # a trial's results elsewhere stay out of the doc
        write_doc(DOC, markdown(args.family, results, record), f"loop_{args.family}")


if __name__ == "__main__":
    main()
