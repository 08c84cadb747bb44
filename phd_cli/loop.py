"""`phd loop`: one round of an active capture through a running service (`phd serve`): the
photos in (a new capture, or added to `--capture`), a model trained on it (warm-started from the
last round's), the next views out as a pose file a capture tool reads. Round after round:

    phd loop photos/ --server http://127.0.0.1:8000 --test 0007.jpg --out next.json
    phd loop more/ --server http://127.0.0.1:8000 --capture ID --out next.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from phd_core.data import POSES, export_cameras
from phd_core.renderers import DEFAULT_FAMILY
from phd_core.scene import cameras_from_json
from phd_core.uq.strategies import DEFAULT_STRATEGY, STRATEGIES

from .report import add_progress_args, say

SERVER_FAULTS = ("internal_error", "interrupted", "executor_failed")   # a failed job's codes that are not the input's


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "loop", help="one round of an active capture through a service: photos in, model trained, next views out",
        description="Send photos to a running service (phd serve): a new capture (structure-from-motion), or photos "
                    "added to --capture (registered into its reconstruction). Then train a model on it (warm-started "
                    "from the capture's last model), calibrate it, measure it on the held-out photos (--test), and "
                    "rank candidate poses around it: the next views, written to --out. Prints the capture's id for "
                    "the next round.")
    p.add_argument("photos", nargs="+", type=Path, metavar="PHOTOS", help="a folder of photos, photo files, or (a new "
                   "capture only) one video")
    p.add_argument("--server", required=True, help="the service's URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--api-key", default=None, help="the service's API key, if it needs one")
    p.add_argument("--capture", default=None, help="add the photos to this capture (its id) instead of a new one")
    p.add_argument("--test", nargs="*", default=[], metavar="NAME",
                   help="photo names held out of training: every round's model is measured on them (PSNR, "
                   "sigma-max-bar)")
    p.add_argument("--model", default=None, help=f"model family to train (default {DEFAULT_FAMILY})")
    p.add_argument("--iterations", type=int, default=None, help="training steps (default: the trainer's)")
    p.add_argument("--downscale", type=float, default=None, help="train on the photos at 1/downscale (default 1)")
    p.add_argument("--cold", action="store_true", help="train from scratch, not from the capture's last model")
    p.add_argument("--count", type=int, default=2, help="how many next views (default 2)")
    p.add_argument("--strategy", default=None, choices=list(STRATEGIES),
                   help=f"next-best-view strategy (default {DEFAULT_STRATEGY})")
    p.add_argument("--targets", choices=("none", "capture"), default="none",
                   help="'capture': rank for the capture's own path (the views the model will be looked at from)")
    p.add_argument("--candidates", default=None, help="candidate generator (default orbit: 64 poses around it)")
    p.add_argument("--out", type=Path, default=None,
                   help="write the next poses here, in the convention its name says (transforms.json, cameras.json, "
                   "or a folder for COLMAP text files)")
    p.add_argument("--format", choices=list(POSES), default=None, help="the pose convention of --out")
    add_progress_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from client import JobFailedError, PHDClient, PHDError

    try:
        with PHDClient(args.server, api_key=args.api_key, timeout=60) as phd:
            if args.capture is None:
                say(args, f"structure-from-motion on {_shown(args.photos)} ...")
                capture = phd.create_capture(args.photos if len(args.photos) > 1 else args.photos[0], test=args.test)
            else:
                capture = phd.get_capture(args.capture)
                say(args, f"registering {_shown(args.photos)} into capture {capture.id} ...")
                capture.add_photos(args.photos, test=args.test)
            latest = capture.info.rounds[-1]
            print(f"capture {capture.id} round {latest.round}: {len(latest.registered)} of {len(latest.photos)} photos "
                  f"registered ({capture.info.num_photos} in all)" + (
                      f"; not registered: {', '.join(latest.not_registered)}" if latest.not_registered else ""))
            say(args, "training ...")
            trained = capture.train(args.model, iterations=args.iterations, downscale=args.downscale,
                                    warm_start=not args.cold)
            summary = trained.summary  # type: ignore[union-attr]   # waited for: a TrainResult
            start = f"from {summary.warm_from}" if summary.warm_from else "from scratch"
            psnr = "no test photos" if summary.test_psnr is None else f"test PSNR {summary.test_psnr:.2f} dB"
            bar = "" if summary.sigma_max_bar is None else f", sigma-max-bar {summary.sigma_max_bar:.4f}"
            print(f"model {summary.model_id} ({summary.family}, {summary.num_units:,} units, {start}, "
                  f"{summary.seconds:.1f} s): {psnr}{bar}")
            ranked = capture.next_views(args.count, candidates=args.candidates, strategy=args.strategy,
                                        targets="capture" if args.targets == "capture" else None)
    except PHDError as error:
        print(f"phd loop: error: {error}", file=sys.stderr)
        theirs = (error.code not in SERVER_FAULTS if isinstance(error, JobFailedError) else
                  error.status is not None and 400 <= error.status < 500)
        return 2 if theirs else 1
    views = ranked.views  # type: ignore[union-attr]   # waited for: a RankResult
    print(f"next views ({ranked.rule}):")  # type: ignore[union-attr]
    for view in views:
        c2w = view.camera["transform_matrix"] if view.camera else None
        position = "" if c2w is None else " at ({:.3f}, {:.3f}, {:.3f})".format(*(row[3] for row in c2w[:3]))
        print(f"  {view.rank}. candidate {view.index}{position}, sigma_max {view.sigma_max:.4f}")
    if args.out is not None:
        cameras = cameras_from_json([v.camera for v in views if v.camera is not None])
        export_cameras(args.out, cameras, [f"next_{view.rank:02d}.png" for view in views], args.format)
        print(f"wrote {len(cameras)} poses -> {args.out}")
    print(f"next round: phd loop PHOTOS --server {args.server} --capture {capture.id}")
    return 0


def _shown(paths: list[Path]) -> str:
    return str(paths[0]) if len(paths) == 1 else f"{len(paths)} photos"
