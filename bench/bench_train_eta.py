"""How honest a training job's time left is (issue 49, `phd_core.train.clock`): a cold and a warm
splat run on real scenes, each step's `seconds_left` and `seconds_left_max` against the time the
run then actually took to finish.

Reported at 10 %, 30 %, 50 %, 70 % and 90 % of each run: the estimate and the bound as ratios of
the actual time left (1.00: exact; a bound below 1.00 broke its promise), and over all steps the
share where the bound held. The naive extrapolation (elapsed / done x left, what tqdm shows) is
given beside them for comparison.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m bench.bench_train_eta

Writes bench/results/train_eta.json and the table between the `bench:train-eta` markers of
docs/gaussians.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bench._harness import DATA, DOCS, RESULTS, command, machine, machine_text, write_doc, write_result
from phd_core.renderers.gs3d import read_sidecar
from phd_core.train.clock import TrainStep
from phd_core.train.gs3d import train_gaussians

SCENES = {"cup_colmap": (DATA / "cup_colmap", 8.0, 8), "donut_200": (DATA / "donut_200", 2.0, 8)}
AT = (0.1, 0.3, 0.5, 0.7, 0.9)


def run(data: Path, downscale: float, views: int, iterations: int, out: Path, init: Path | None) -> list[dict]:
    """One training run; per step: wall time, the clock's two numbers, and the naive extrapolation.
    A warm run (`init`) trains over its init's background, as the capture loop does."""
    rows: list[dict] = []
    started = time.perf_counter()

    def record(at: TrainStep) -> None:
        now = time.perf_counter() - started
        rows.append({"t": now, "left": at.seconds_left, "max": at.seconds_left_max,
                     "naive": now / at.step * (at.total - at.step)})

    background = None if init is None else read_sidecar(init)["background"]
    train_gaussians(data, views=views, downscale=downscale, iterations=iterations, seed=0, out=out, progress=False,
                    init=init, on_step=record, background=background)
    end = rows[-1]["t"]
    return [{**row, "actual": end - row["t"]} for row in rows]


def summary(rows: list[dict]) -> dict:
    """Ratios to the actual time left at the `AT` fractions, and the share of steps the bound held."""
    at = {}
    for fraction in AT:
        row = rows[int(fraction * len(rows))]
        at[str(fraction)] = {key: row[key] / row["actual"] for key in ("left", "max", "naive")}
    held = [row["max"] >= row["actual"] for row in rows[:-1]]
    return {"at": at, "bound_held": sum(held) / len(held), "seconds": rows[-1]["t"]}


def markdown(results: dict, record: dict) -> str:
    lines = [f"{machine_text(record)}. Command: `{record['command']}`.", "",
             "Time left as the clock says it, over the time the run then took (1.00 exact; a bound under 1.00 "
             "broke its promise), at a fraction of the run; naive: elapsed / steps done x steps left:", "",
             "| run | " + " | ".join(f"{int(f * 100)} %: estimate / bound / naive" for f in AT) + " | bound held | s |",
             "|---|" + "---|" * len(AT) + "---|---|"]
    for name, found in results.items():
        cells = [" / ".join(f"{found['at'][str(f)][k]:.2f}" for k in ("left", "max", "naive")) for f in AT]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {100 * found['bound_held']:.0f} % | "
                     f"{found['seconds']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=int, default=1000)
    p.add_argument("--out", type=Path, default=RESULTS / "train_eta.json")
    args = p.parse_args()
    record = {**machine(), "command": command()}
    results = {}
    with tempfile.TemporaryDirectory(prefix="phd-eta-") as tmp:
        for name, (data, downscale, views) in SCENES.items():
            first = Path(tmp) / f"{name}_first.ply"              # the cold run's model, the warm run's start
            for start, init in (("cold", None), ("warm", first)):
                rows = run(data, downscale, views if init is None else views + 4, args.iterations,
                           first if init is None else Path(tmp) / f"{name}_warm.ply", init)
                results[f"{name} {start}"] = summary(rows)
                print(name, start, results[f"{name} {start}"], flush=True)
    write_result(args.out, {"record": record, "results": results})
    write_doc(DOCS / "gaussians.md", markdown(results, record), "train-eta")


if __name__ == "__main__":
    main()
