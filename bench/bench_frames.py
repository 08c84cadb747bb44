"""Trainer frames on the real cup capture: the trainers' own normalisations, and what the
loaders recover from every gsplat sign pattern.

    fixtures   runs the trainers' own functions once and writes their results for the tests
               (tests/support/frames_from_trainers.json): gsplat's `similarity_from_cameras` and
               `align_principal_axes` (examples/datasets/normalize.py of a gsplat checkout:
               the pip wheel does not ship examples/, give its folder with --gsplat-examples)
               with the Parser's upside-down turn of 1.5.2+, and nerfstudio's
               `auto_orient_and_center_poses` (`pip install --no-deps nerfstudio==1.1.5
               jaxtyping`: camera_utils imports with torch alone; the dataparser, colmap_to_json
               and the exporter need cv2, tensorboard, open3d and are not run)
    table      for each (eigh sign pattern, gsplat version): a gsplat run on the cup written by
               tests/support/trainers.py, loaded; the recovered frame, the residuals, and the
               PSNR of the training views rendered by the loaded model against the same views of
               the model in the capture's frame (`--train N`: a model trained N iterations on the
               capture at 1/10 size instead of splats grown from the SfM points)

    nice -n 10 .venv/bin/python -m bench.bench_frames fixtures --gsplat-examples /tmp/gsplat/examples
    nice -n 10 .venv/bin/python -m bench.bench_frames table --out bench/results/frames.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from bench import _harness
from phd_core.data import load_colmap
from phd_core.errors import ModelWarning
from phd_core.eval import psnr
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.renderers.outputs import gsplat, read_output
from tests.support.trainers import APPLIED_TRANSFORM_1_1_5, CV, cup_gsplat_run

CUP = _harness.ROOT.parent / "shared" / "data" / "cup_colmap"
FIXTURE = _harness.ROOT / "tests" / "support" / "frames_from_trainers.json"
PATTERNS = [((1.0, 1.0, 1.0), False), ((1.0, 1.0, -1.0), False), ((1.0, -1.0, 1.0), False),
            ((1.0, -1.0, -1.0), False), ((1.0, 1.0, 1.0), True), ((1.0, 1.0, -1.0), True)]


def fixtures(gsplat_examples: Path, out: Path) -> dict:
    spec = importlib.util.spec_from_file_location("gsplat_normalize", gsplat_examples / "datasets" / "normalize.py")
    assert spec is not None and spec.loader is not None
    normalize = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(normalize)
    from nerfstudio.cameras.camera_utils import auto_orient_and_center_poses

    capture = load_colmap(CUP, "all", with_images=False)                 # every image, sorted by name
    # gsplat's Parser: OpenCV camera-to-world, the SfM points as float32, then its three steps.
    c2w = np.stack([c.c2w.numpy() @ CV for c in capture.cameras])
    points = capture.points.numpy().astype(np.float32)
    t1 = normalize.similarity_from_cameras(c2w)
    p1 = normalize.transform_points(t1, points)
    t2 = normalize.align_principal_axes(p1)
    p2 = normalize.transform_points(t2, p1)
    before_fix = t2 @ t1
    turn = np.diag([1.0, -1.0, -1.0, 1.0])                                  # the Parser's T3 (1.5.2 on)
    current = turn @ before_fix if np.median(p2[:, 2]) > np.mean(p2[:, 2]) else before_fix
    # nerfstudio: the cup as ns-process-data writes it (OpenGL c2w turned by its applied_transform),
    # frames sorted by name, then the dataparser's defaults: orientation "up", centre "poses",
    # the largest camera coordinate scaled to 1.
    applied = APPLIED_TRANSFORM_1_1_5
    poses = torch.from_numpy(np.stack([applied @ c.c2w.numpy() for c in capture.cameras]).astype(np.float32))
    oriented, transform = auto_orient_and_center_poses(poses, method="up", center_method="poses")
    scale = 1.0 / float(torch.max(torch.abs(oriented[:, :3, 3])))
    found = {"capture": "cup_colmap (every registered image sorted by name, every SfM point)",
             "gsplat_1_5_3": current.tolist(), "gsplat_1_5_1": before_fix.tolist(),
             "nerfstudio_1_1_5": {"applied_transform": applied[:3].tolist(), "transform": transform.tolist(),
                                  "scale": scale}}
    out.write_text(json.dumps(found, indent=1) + "\n")
    return found


def table(train: int, out: Path) -> dict:
    rows = []
    capture = load_colmap(CUP, "all", with_images=False)
    points = capture.points.numpy()
    with tempfile.TemporaryDirectory() as tmp:
        model = None
        if train:
            from phd_core.train.gs3d import train_gaussians

            model = train_gaussians(CUP, views=23, downscale=10, iterations=train, sh_degree=0,
                                    out=Path(tmp) / "cup.ply", progress=False).model
        for signs, fix in PATTERNS:
            root = Path(tmp) / f"{signs}{fix}"
            scene = cup_gsplat_run(root, CUP, eigh_signs=signs, upside_down_fix=fix, user_model=model)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                output = read_output(scene["folder"])
            # The frame the loader chose, and the runner-up it told apart, rendered against the model
            # in the capture's frame (the runner-up is what a loader without the margin could pick).
            raw = gsplat.checkpoint_model(output.source)
            choice = gsplat.best_frame(raw, gsplat.normalisations(capture.cameras, points), capture.cameras, points,
                                       CUP)
            assert choice.runner_up is not None and choice.residual is not None
            reference = GaussianRenderer(scene["user_model"], (0.0, 0.0, 0.0))
            views = [c.scaled(10) for c in scene["training"][::6]]

            def scores(model) -> list[float]:
                renderer = GaussianRenderer(model, (0.0, 0.0, 0.0))
                return [psnr(renderer.render(c)[0], reference.render(c)[0]) for c in views]

            chosen = scores(output.model)
            runner = scores(raw.transformed(gsplat.normalisations(capture.cameras, points)[choice.runner_up[0]]
                                            .inverse()))
            rows.append({"eigh_signs": signs, "upside_down_fix": fix, "chosen": choice.name,
                         "frame_error": float(np.abs(output.frame.matrix.numpy() - scene["to_model"]).max()),
                         "residual": choice.residual, "runner_up": choice.runner_up[0],
                         "runner_up_residual": choice.runner_up[1], "decided_by_renders": choice.renders is not None,
                         "warnings": [str(w.message) for w in caught if w.category is ModelWarning],
                         "views": len(views), "psnr_min": min(chosen), "psnr_max": max(chosen),
                         "runner_up_psnr_min": min(runner), "runner_up_psnr_max": max(runner)})
            print(json.dumps(rows[-1]), file=sys.stderr)
    result = {"machine": _harness.machine(), "model": f"trained {train} iterations" if train else
              "splats grown from every 3rd SfM point", "rows": rows}
    _harness.write_result(out, result)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    make = sub.add_parser("fixtures")
    make.add_argument("--gsplat-examples", type=Path, required=True, help="examples/ of a gsplat 1.5.3 checkout")
    make.add_argument("--out", type=Path, default=FIXTURE)
    run = sub.add_parser("table")
    run.add_argument("--train", type=int, default=0, help="train the cup model this many iterations (0: SfM splats)")
    run.add_argument("--out", type=Path, default=_harness.RESULTS / "frames.json")
    args = parser.parse_args()
    if args.command == "fixtures":
        print(json.dumps(fixtures(args.gsplat_examples, args.out), indent=1))
    else:
        table(args.train, args.out)


if __name__ == "__main__":
    main()
