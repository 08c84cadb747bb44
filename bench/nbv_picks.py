"""What of a run's picks goes with its final PSNR on a capture (a diagnosis of bench_nbv's stored runs).

For every stored run of a scene and its holdout folds (`cup_colmap`, `cup_colmap@1`, ...), measures
of where its captured views stand, by camera centre (scene units):
- test_nn: the mean over the test views of the distance to the nearest captured view;
- test_near: the mean over the test views of how many captured views stand within NEAR (at most 3);
- target_nn, target_near: the same over the target views the strategies are told (the train frames);
- spacing: the mean distance from a captured view to the nearest other one.
Each measure and the final PSNR are taken less their mean over the runs of the same fold and seed
(so the seed's start and the fold's test views drop out), then correlated over the runs, and
test_near once test_nn is accounted for (partial correlation). A
measure over the test views shows what the benchmark rewards; the same over the targets, what a
strategy told only the targets could aim at. Then each strategy's mean of each measure.

    .venv/bin/python -m bench.nbv_picks --scene cup_colmap
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from bench import bench_nbv
from bench._harness import DATA, RESULTS

NEAR = 1.0          # scene units: about two steps of the cup_colmap path (0.49 between neighbours)
MEASURES = ["test_nn", "test_near", "target_nn", "target_near", "spacing"]


def centres(args: argparse.Namespace, scene: str, split: str) -> np.ndarray:
    """[V, 3] camera centres of a split of a scene or fold, as the benchmark loads it."""
    cameras = bench_nbv.load_split(args, scene, split, with_images=False).cameras
    return torch.stack([c.center for c in cameras]).numpy()


def measures(train: np.ndarray, test: np.ndarray, chosen: list[int]) -> list[float]:
    """MEASURES of one run's captured views `chosen` (indices into `train`)."""
    picked = train[chosen]                                                   # [P, 3]
    to_test = np.linalg.norm(test[:, None] - picked[None], axis=2)           # [T, P]
    to_target = np.linalg.norm(train[:, None] - picked[None], axis=2)        # [V, P]
    between = np.linalg.norm(picked[:, None] - picked[None], axis=2)         # [P, P]
    np.fill_diagonal(between, np.inf)
    return [to_test.min(1).mean(), (to_test < NEAR).sum(1).clip(max=3).mean(),
            to_target.min(1).mean(), (to_target < NEAR).sum(1).clip(max=3).mean(), between.min(1).mean()]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="cup_colmap")
    p.add_argument("--results", type=Path, default=RESULTS / "nbv")
    p.add_argument("--resolution", type=int, default=50)
    args = p.parse_args()
    args.data = DATA
    rows, groups, names, finals = [], [], [], []
    for path in sorted(args.results.glob(f"{args.scene}*.json")):
        task = json.loads(path.read_text())
        if bench_nbv.scene_fold(task["scene"])[0] != args.scene:
            continue
        train, test = centres(args, task["scene"], "train"), centres(args, task["scene"], "test")
        for name, run in task["runs"].items():
            rows.append(measures(train, test, run["chosen"]))
            groups.append((task["scene"], task["seed"]))
            names.append(name)
            finals.append(run["psnr"][-1])
    x, y = np.array(rows), np.array(finals)                                  # [R, M], [R]
    group = np.unique(np.array([f"{s}-{k}" for s, k in groups]), return_inverse=True)[1]
    within_x = x - np.stack([x[group == g].mean(0) for g in group])
    within_y = y - np.array([y[group == g].mean() for g in group])
    print(f"{len(y)} runs in {group.max() + 1} (fold, seed) groups of {args.scene}")
    for m, measure in enumerate(MEASURES):
        print(f"{measure:12s} correlation with final PSNR within a (fold, seed): "
              f"{np.corrcoef(within_x[:, m], within_y)[0, 1]:+.2f}")
    # test_near once test_nn is accounted for: both less their least-squares fit on test_nn
    fit = np.c_[within_x[:, 0], np.ones(len(y))]
    rest_y = within_y - fit @ np.linalg.lstsq(fit, within_y, rcond=None)[0]
    rest_near = within_x[:, 1] - fit @ np.linalg.lstsq(fit, within_x[:, 1], rcond=None)[0]
    print(f"test_near given test_nn (partial correlation): {np.corrcoef(rest_near, rest_y)[0, 1]:+.2f}")
    print("\nmeans per strategy (runs): " + " ".join(MEASURES))
    for name in sorted(set(names), key=lambda n: -names.count(n)):
        mine = np.array([n == name for n in names])
        if mine.sum() >= 5:
            print(f"{name:40s} ({mine.sum():3d}) " + " ".join(f"{v:.2f}" for v in x[mine].mean(0)))


if __name__ == "__main__":
    main()
