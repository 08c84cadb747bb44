"""Ensemble selection benchmark: per held-out view, which of two models to trust.

Two 3DGS models of one scene trained on disjoint view sets ("random": two random disjoint
sets drawn by the seed; "demo": the demo's evenly spaced set and the same shifted by 3),
each calibrated on its own training poses. For every selection rule of
`phd_core.uq.select_models`: mean PSNR of model a, model b, the selection and the
per-view oracle, and E_ME (the paper's mean over views of SSIM(selected) / max SSIM).
Writes bench/results/select.json and the table between the `bench:select` markers of
docs/nbv.md.

    .venv/bin/python -m bench.bench_select
"""

from __future__ import annotations

import argparse
import random
from pathlib import Path

import torch

from bench._harness import DATA, DOCS, RESULTS, train, write_doc, write_result
from phd_core import uq as phd
from phd_core.data import load_blender, select_views

DOC = DOCS / "nbv.md"
RESULT = RESULTS / "select.json"
# (scene, views per model, image size, iterations, how the two view sets are drawn, test views)
CASES = [("lego_200", 16, 100, 500, "demo", 100), ("lego_200", 8, 50, 600, "random", 40),
         ("lego_200", 16, 50, 600, "random", 40), ("donut_200", 8, 50, 600, "random", 40),
         ("donut_200", 16, 50, 600, "random", 40), ("chain_200", 8, 50, 600, "random", 40),
         ("chain_200", 16, 50, 600, "random", 40)]


def view_sets(total: int, count: int, how: str, seed: int) -> tuple[list[int], list[int]]:
    if how == "demo":
        a = select_views(total, count)
        return a, [(i + 3) % total for i in a]
    order = list(range(total))
    random.Random(seed).shuffle(order)
    return sorted(order[:count]), sorted(order[count:2 * count])


def run_case(scene: str, views: int, size: int, iterations: int, how: str, test_views: int, seed: int,
             samples: int) -> dict:
    full = load_blender(DATA / scene, "train", with_images=False).cameras[0].width
    train_data = load_blender(DATA / scene, "train", downscale=full / size)
    test = load_blender(DATA / scene, "test", downscale=full / size, views=test_views)
    sets = view_sets(len(train_data.cameras), views, how, seed)
    models = [train(train_data, indices, iterations, seed) for indices in sets]
    ratios = [phd.calibrate(m, m.training_cameras).r_drop for m in models]
    row = {"scene": scene, "views": views, "size": size, "iterations": iterations, "sets": how,
           "units": [m.num_units for m in models], "r_drop": ratios, "rules": {}}
    for rule in phd.SELECTION_RULES:
        result = phd.select_models(*models, test.cameras, ratio_a=ratios[0], ratio_b=ratios[1], samples=samples,
                                   seed=seed, images=test.images, rule=rule)
        row["rules"][rule] = result.metrics
        print(scene, views, size, how, rule, {k: round(v, 3) if isinstance(v, float) else v
                                              for k, v in result.metrics.items()}, flush=True)
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["Command: `.venv/bin/python -m bench.bench_select`. PSNR is the mean over the test views of the "
             "per-view PSNR; oracle = the better model per view; E_ME = mean over views of SSIM(selected) / "
             "max(SSIM(a), SSIM(b)) (1 = always the better model).", "",
             "| scene | views per model | size | sets | rule | PSNR a | PSNR b | selected | oracle | E_ME | "
             "chosen a / b |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for rule, m in row["rules"].items():
            label = f"**{rule}** (default)" if rule == phd.DEFAULT_SELECTION_RULE else rule
            lines.append(f"| {row['scene']} | {row['views']} | {row['size']} px | {row['sets']} | {label} | "
                         f"{m['psnr_a']:.2f} | {m['psnr_b']:.2f} | {m['psnr_selected']:.2f} | "
                         f"{m['psnr_oracle']:.2f} | {m['e_me']:.4f} | {m['choices_a']} / {m['choices_b']} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=phd.DEFAULT_SAMPLES)
    p.add_argument("--out", type=Path, default=RESULT)
    p.add_argument("--doc", type=Path, default=DOC)
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = [run_case(*case, seed=args.seed, samples=args.samples) for case in CASES]
    write_result(args.out, {"seed": args.seed, "samples": args.samples, "cases": rows})
    write_doc(args.doc, markdown(rows), section="select")
    print(f"wrote {args.doc}")


if __name__ == "__main__":
    main()
