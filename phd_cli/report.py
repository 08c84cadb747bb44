"""What the long commands say while they work, and what they keep for the next one.

Progress: a tqdm bar on stderr per long step (calibration, the masked renders of uq, rank and
select, the renders of `phd render`, each stage of `phd capture`), driven by the
`progress(fraction)` callback the `phd_core.uq` functions call as views finish (and
`progress(stage, fraction)` for `phd_core.process`). Bars show when stderr is a terminal,
never with `--quiet`, always with `--progress` (a log file). stdout keeps only the results.

Calibration: `phd calibrate`, and any command that had to calibrate, stores the result beside
the model (`phd_core.io.cache.ModelCache`, keyed by the model's content and every setting that
changes r_drop: epsilon, step, masks, method, seed, signal, the background rendered over and
the cameras calibrated on); `phd rank`, `uq` and `select` reuse it and say so on stderr, unless
`--recalibrate`.
"""

from __future__ import annotations

import argparse
import sys
from contextlib import contextmanager
from datetime import datetime, timezone
from typing import Any, Callable, Iterator

from phd_core import uq as phd
from phd_core.io.cache import CALIBRATION, ModelCache, cameras_digest, content_digest
from phd_core.scene import Camera

from .models import OpenedModel

PERCENT = 100                       # a bar counts percent of the step's views


def add_progress_args(parser: argparse.ArgumentParser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quiet", action="store_true", help="no progress bars (they go to stderr, and by "
                       "default only when it is a terminal)")
    group.add_argument("--progress", action="store_true", help="progress bars on stderr even when it is not a "
                       "terminal (a log file)")


def bars_on(args: argparse.Namespace) -> bool:
    if getattr(args, "quiet", False):
        return False
    return bool(getattr(args, "progress", False)) or sys.stderr.isatty()


@contextmanager
def progress_bar(args: argparse.Namespace, label: str) -> Iterator[phd.Progress | None]:
    """A `progress(fraction)` callback drawing a bar on stderr (None when bars are off); the bar
    is closed when the step ends, finished or not."""
    if not bars_on(args):
        yield None
        return
    bar = _bar(label)
    try:
        yield lambda fraction: _advance(bar, fraction)
    finally:
        bar.close()


@contextmanager
def stage_bars(args: argparse.Namespace) -> Iterator[Callable[[str, float], None] | None]:
    """A `progress(stage, fraction)` callback drawing one bar per stage on stderr, each closed
    when the next stage begins (None when bars are off)."""
    if not bars_on(args):
        yield None
        return
    bars: dict[str, Any] = {}

    def show(stage: str, fraction: float) -> None:
        if stage not in bars:
            for bar in bars.values():
                bar.close()
            bars[stage] = _bar(stage)
        _advance(bars[stage], fraction)

    try:
        yield show
    finally:
        for bar in bars.values():
            bar.close()


def _bar(label: str) -> Any:
    """A tqdm bar on stderr counting PERCENT of a step."""
    from tqdm import tqdm

    return tqdm(total=PERCENT, desc=label, file=sys.stderr, dynamic_ncols=True,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]")


def _advance(bar: Any, fraction: float) -> None:
    bar.update(max(0, round(fraction * PERCENT) - bar.n))


def say(args: argparse.Namespace, message: str) -> None:
    """A line about what the command did (not its result): stderr, `phd <command>: ...`."""
    print(f"phd {args.command}: {message}", file=sys.stderr)


# ----------------------------------------------------------------------------- the stored calibration

def calibration_settings(args: argparse.Namespace, model: OpenedModel, cameras: list[Camera]) -> dict[str, Any]:
    """Everything that changes r_drop besides the model's content (the cache key)."""
    return {"epsilon": args.epsilon, "step": args.step, "samples": args.calibration_samples, "method": args.method,
            "seed": args.seed, "signal": args.signal, "background": model.renderer.describe().get("background"),
            "cameras": cameras_digest([c.to_frame() for c in cameras])}


def calibrated(args: argparse.Namespace, model: OpenedModel, cameras: list[Camera], *,
               reuse: bool = True) -> phd.CalibrationResult:
    """r_drop of `model` on `cameras`: the stored calibration with the same settings when there
    is one (and `reuse`), else Algorithm 1 run now (with a bar) and stored for the next command."""
    cache, settings = ModelCache(model.path), calibration_settings(args, model, cameras)
    stored = cache.load_json(CALIBRATION, settings) if reuse else None
    if stored is not None:
        result = phd.CalibrationResult(**stored["result"])
        say(args, f"{model.label}: r_drop {result.r_drop} from the calibration stored by `{stored['by']}` on "
                  f"{stored['created_at']} ({cache.path(CALIBRATION, settings, '.json')}); --recalibrate to run "
                  "it again")
        return result
    with progress_bar(args, f"calibrate {model.path.name} ({len(cameras)} views)") as progress:
        result = phd.calibrate(model.renderer, cameras, epsilon=args.epsilon, step=args.step,
                               samples=args.calibration_samples, method=args.method, seed=args.seed,
                               executor=args.executor, signal=args.signal, progress=progress)
    # The model file's own digest: a service given the folder (without its photos) finds the entry by it.
    digest = cache.digest if model.output is None else content_digest(model.output.source)
    entry = {"by": f"phd {args.command}", "created_at": datetime.now(timezone.utc).isoformat(timespec="seconds"),
             "views": len(cameras), "settings": settings, "result": result.to_dict(),
             "model_sha256": digest}
    if cache.save_json(CALIBRATION, settings, entry):
        say(args, f"{model.label}: calibrated, r_drop {result.r_drop}; stored in "
                  f"{cache.path(CALIBRATION, settings, '.json')} for the next commands")
    else:
        say(args, f"{model.label}: calibrated, r_drop {result.r_drop}; not stored ({cache.skipped})")
    return result


# ----------------------------------------------------------------------------- the ranking table

TABLE_ROWS = 10     # rows `phd rank` prints without --top-k


def rank_table(ranked: list[phd.RankedView], poses: list[Camera], rows: int) -> list[str]:
    """The first `rows` ranked candidates: their place in the capture order (#1 first, the
    JSON's `rank` and the page's number), candidate index, score, sigma_max,
    the pose's centre and viewing direction (the camera's -z axis), in the candidates' frame."""
    lines = [f"{'#':>4}  {'candidate':>9}  {'score':>10}  {'sigma_max':>10}  {'centre x, y, z':^30}  "
             f"{'viewing direction x, y, z':^26}"]
    for view in ranked[:rows]:
        c2w = poses[view.index].c2w
        centre, forward = c2w[:3, 3].tolist(), (-c2w[:3, 2]).tolist()
        lines.append(f"{'#' + str(view.rank):>4}  {view.index:>9}  {view.score:>10.4g}  {view.sigma_max:>10.4g}  "
                     + " ".join(f"{v:>9.4f}" for v in centre) + "   " + " ".join(f"{v:>+7.3f}" for v in forward))
    return lines

