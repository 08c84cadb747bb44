"""3DGS and 2DGS on lego_200 at 100x100: training quality and time, render time, batched keep-masks.

    python -m bench.bench_gaussians [--iterations 5000] [--skip-train] [--model 2dgs] [--views 16]

Trains with 100 and with 16 training views, scores 25 evenly spaced test views (PSNR,
SSIM), times single renders at 100x100 and 200x200, and compares one batched render of
N keep-masks with N separate renders (same process, same model, so the ratio is fair).
Models go to runs/lego{100,16}/model.ply (2DGS: runs/lego{100,16}_2dgs/model.ply); numbers to
bench/results/gaussians.json (or --out).
"""

from __future__ import annotations

import argparse
import importlib
import json
import time
from pathlib import Path

import torch

from bench._harness import DATA, RESULTS, ROOT, machine, timed, write_result
from phd_core.data import load_blender
from phd_core.eval import psnr, ssim
from phd_core.renderers import FAMILIES, load_model

LEGO = DATA / "lego_200"


def evaluate(model_path: Path, test) -> dict:
    renderer = load_model(model_path)
    images, truth = torch.cat([renderer.render(c) for c in test.cameras]), torch.stack(test.images)
    return {"psnr": round(psnr(images, truth), 2), "ssim": round(float(ssim(images, truth).mean()), 4),
            "splats": renderer.num_units}


def speed(model_path: Path, masks: int) -> dict:
    renderer = load_model(model_path)
    test = load_blender(LEGO, "test", downscale=1, views=[0], with_images=False)
    out = {}
    for size in (100, 200):
        cam = test.cameras[0].resized(size, size)
        keep = torch.rand(masks, renderer.num_units, generator=torch.Generator().manual_seed(0)) >= 0.2
        single = timed(lambda: renderer.render(cam), 3).best
        batched = timed(lambda: renderer.render(cam, keep), 3).best
        separate = timed(lambda: [renderer.render(cam, keep[i:i + 1]) for i in range(masks)]).best
        out[f"{size}x{size}"] = {"render_s": round(single, 4), f"batched_{masks}_s": round(batched, 3),
                                 f"separate_{masks}_s": round(separate, 3),
                                 "speedup": round(separate / batched, 2)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=None, help="training steps (default: the trainer's)")
    parser.add_argument("--skip-train", action="store_true", help="reuse runs/lego{100,16}/model.ply")
    parser.add_argument("--masks", type=int, default=16)
    parser.add_argument("--model", choices=("3dgs", "2dgs"), default="3dgs", help="splat family (default 3dgs)")
    parser.add_argument("--views", default="16,100", help="training view counts (default 16,100)")
    parser.add_argument("--depth-distortion", type=float, default=1.0, help="2DGS regulariser weight (default 1)")
    parser.add_argument("--normal-consistency", type=float, default=0.05, help="2DGS regulariser weight (default 0.05)")
    parser.add_argument("--out", type=Path, default=RESULTS / "gaussians.json")
    args = parser.parse_args()
    module, function = FAMILIES[args.model].trainer.split(":")
    train = getattr(importlib.import_module(module), function)
    options = {name: getattr(args, name) for name in FAMILIES[args.model].train_options}
    test = load_blender(LEGO, "test", downscale=2, views=25)
    results = {"machine": machine(),
               "settings": {"downscale": 2, "test_views": 25, "masks": args.masks, "model": args.model,
                            "iterations": args.iterations, **options}, "models": {}}
    for views in (int(v) for v in args.views.split(",")):
        path = ROOT / "runs" / f"lego{views}{'' if args.model == '3dgs' else '_' + args.model}" / "model.ply"
        entry: dict = {}
        if not args.skip_train:
            start = time.perf_counter()
            train(LEGO, views=views, downscale=2, iterations=args.iterations, out=path, progress=False, **options)
            entry["train_s"] = round(time.perf_counter() - start, 1)
        else:
            entry["train_s"] = json.loads(path.with_suffix(".json").read_text())["train_seconds"]
        entry.update(evaluate(path, test))
        entry["speed"] = speed(path, args.masks)
        results["models"][f"{views}_views"] = entry
        print(views, "views:", json.dumps(entry), flush=True)
    write_result(args.out, results)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
