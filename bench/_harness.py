"""What every bench script shares: paths, one timing helper, one machine record, atomic
result files, and the docs' bench sections (markers, tables, plots).

Run a bench from the checkout's root as a module, `python -m bench.bench_speed ...`
(bench/README.md): then `bench` is a package (bench/__init__.py applies the `phd` command's
process settings before torch loads), and the scripts import this module, and the tests'
shared fixtures as `tests.support`, without editing sys.path.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

import numba
import torch

from phd_core.data import Dataset, load_blender, load_dataset
from phd_core.io import write_bytes_atomic, write_json_atomic
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer, write_ply
from phd_core.renderers.splats import SH_C0
from phd_core.scene import Camera
from phd_core.train.gs3d import TrainConfig, fit, training_background
from phd_core.uq.candidates import hemisphere_cameras

ROOT = Path(__file__).resolve().parents[1]          # the checkout
BENCH = ROOT / "bench"
RESULTS = BENCH / "results"
DOCS = ROOT / "docs"
DATA = ROOT.parent / "shared" / "data"              # ../shared/data beside the checkout
DONUT = DATA / "donut_200"
LEGO = DATA / "lego_200"
REAL_CAPTURES = ("cup_colmap", "flask_desk", "imac_chair", "meeting_room_a", "drone_flight1")   # real photos


def capture_path(name: str) -> Path:
    """Where a real capture of REAL_CAPTURES lies: cup_colmap in ../shared/data, the others in its real/."""
    return DATA / name if name == "cup_colmap" else DATA / "real" / name


def command(argv: list[str] | None = None) -> str:
    """How this bench was started, as a command to type again from the checkout's root."""
    argv = sys.argv if argv is None else argv
    return " ".join([f"python -m bench.{Path(argv[0]).stem}", *argv[1:]])


# ----------------------------------------------------------------------------- timing

@dataclass(frozen=True)
class Timing:
    result: Any              # what the last call returned
    times: list[float]       # wall seconds of every call

    @property
    def best(self) -> float:
        """The least disturbed by other load."""
        return min(self.times)

    @property
    def median(self) -> float:
        return statistics.median(self.times)

    @property
    def seconds(self) -> float:
        """The wall time of a single call."""
        assert len(self.times) == 1, "several calls: choose best or median"
        return self.times[0]


def vm(pid: int, key: str) -> int:
    """A /proc/<pid>/status memory figure in bytes (VmRSS, VmHWM)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(key)


def reset_peak(pid: int) -> int:
    """Start VmHWM again from the current RSS (clear_refs 5); returns that RSS."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return vm(pid, "VmRSS")


def timed(fn: Callable[[], Any], repeats: int = 1) -> Timing:
    """Call `fn` `repeats` times, timing each call by the wall clock (time.perf_counter)."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return Timing(result, times)


# ----------------------------------------------------------------------------- machine record

def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def machine(**extra: Any) -> dict[str, Any]:
    """The one shape of a result file's "machine" record; `extra` adds what one bench also needs."""
    return {"platform": platform.platform(), "arch": platform.machine(), "processor": platform.processor(),
            "cpus": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "load_average": load_average(), **extra}


def machine_text(record: str | dict[str, Any]) -> str:
    """'x86_64 2 CPUs': a machine record for a sentence (older result files hold that text)."""
    if isinstance(record, str):
        return record
    return " ".join(part for part in (record["arch"], record.get("processor"), f"{record['cpus']} CPUs") if part)


def load_at_start(record: dict[str, Any]) -> list[float]:
    """The load average when the run started (older result files: load_average_at_start)."""
    return record.get("load_average_at_start", record.get("load_average"))


def module_at(revision: str, path: str) -> ModuleType:
    """The module at `path` (e.g. phd_core/renderers/gs3d/kernels.py) as it was at `revision`,
    loaded beside today's as a sibling in the same package, so its relative imports resolve
    against today's code (which holds while the names it imports exist)."""
    source = subprocess.run(["git", "show", f"{revision}:{path}"], cwd=ROOT, check=True, capture_output=True,
                            text=True).stdout
    package = ".".join(Path(path).with_suffix("").parts[:-1])
    name = f"{package}.{Path(path).stem}_at_{revision}"
    file = Path(tempfile.mkdtemp()) / f"{Path(path).stem}_at_{revision}.py"
    file.write_text(source)
    spec = importlib.util.spec_from_file_location(name, file)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    module.__package__ = package
    sys.modules[name] = module                      # dataclasses look their module up while it loads
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- result files

def write_result(path: Path, obj: Any) -> None:
    """`obj` as indented JSON at `path`, atomically (a cut run leaves the previous file whole)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(path, obj)


def write_doc(path: Path, body: str, section: str) -> None:
    """Replace the text between `<!-- bench:<section>:begin -->` and its end marker (or append)."""
    begin, end = f"<!-- bench:{section}:begin -->", f"<!-- bench:{section}:end -->"
    text = path.read_text() if path.exists() else ""
    block = f"{begin}\n{body}\n{end}"
    if begin in text and end in text:
        text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
    else:
        text = text + ("\n" if text else "") + block + "\n"
    write_bytes_atomic(path, text.encode())


def fmt(value: Any, digits: int = 3) -> str:
    """A number for a table: `digits` decimals for floats, 'undefined' for None."""
    if value is None:
        return "undefined"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def svg_plot(path: Path, series: dict[str, list[tuple[float, float]]], xlabel: str, ylabel: str,
             log_y: bool = False, log_x: bool = True) -> None:
    """A minimal line chart, one polyline per series (log2 x axis by default: N)."""
    width, height, left, right, top, bottom = 420, 280, 60, 110, 20, 45
    points = [p for s in series.values() for p in s if p[1] is not None and (p[1] > 0 or not log_y)]
    if not points:
        return
    fy = (lambda v: math.log10(v)) if log_y else (lambda v: v)
    fx = math.log2 if log_x else (lambda v: v)
    x0, x1 = fx(min(p[0] for p in points)), fx(max(p[0] for p in points))
    y0, y1 = min(fy(p[1]) for p in points), max(fy(p[1]) for p in points)
    x1, y1 = (x1 if x1 > x0 else x0 + 1), (y1 if y1 > y0 else y0 + 1)

    def xy(x: float, y: float) -> tuple[float, float]:
        return (left + (fx(x) - x0) / (x1 - x0) * (width - left - right),
                height - bottom - (fy(y) - y0) / (y1 - y0) * (height - top - bottom))

    colours = ["#440154", "#31688e", "#35b779", "#b5de2b", "#fde725", "#e4572e", "#888888"]
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-family="sans-serif" '
           f'font-size="11"><rect width="100%" height="100%" fill="white"/>',
           f'<line x1="{left}" y1="{height - bottom}" x2="{width - right}" y2="{height - bottom}" stroke="black"/>',
           f'<line x1="{left}" y1="{top}" x2="{left}" y2="{height - bottom}" stroke="black"/>',
           f'<text x="{(left + width - right) / 2}" y="{height - 8}" text-anchor="middle">{xlabel}</text>',
           f'<text x="12" y="{(top + height - bottom) / 2}" transform="rotate(-90 12 {(top + height - bottom) / 2})" '
           f'text-anchor="middle">{ylabel}</text>']
    for x in sorted({p[0] for p in points}):
        px, _ = xy(x, 10 ** y0 if log_y else y0)
        out.append(f'<text x="{px:.1f}" y="{height - bottom + 14}" text-anchor="middle">{x:g}</text>')
    for frac in (0, 0.5, 1):
        value = y0 + frac * (y1 - y0)
        label = 10 ** value if log_y else value
        py = height - bottom - frac * (height - top - bottom)
        out.append(f'<text x="{left - 4}" y="{py + 4:.1f}" text-anchor="end">{label:.3g}</text>')
    for i, (name, pts) in enumerate(series.items()):
        pts = [p for p in pts if p[1] is not None and (p[1] > 0 or not log_y)]
        colour = colours[i % len(colours)]
        coords = " ".join(f"{a:.1f},{b:.1f}" for a, b in (xy(*p) for p in pts))
        out.append(f'<polyline points="{coords}" fill="none" stroke="{colour}" stroke-width="2"/>')
        out.append(f'<text x="{width - right + 8}" y="{top + 14 * (i + 1)}" fill="{colour}">{name}</text>')
    out.append("</svg>")
    write_bytes_atomic(path, "\n".join(out).encode())


# ----------------------------------------------------------------------------- data, models, cameras, `phd` in a child

def load_test_at_size(data: Path, views: int, size: int):
    """`views` evenly spaced test-split frames with their images, downscaled to `size` pixels wide."""
    width = load_dataset(data, "test", views=1, with_images=False).cameras[0].width
    return load_dataset(data, "test", views=views, downscale=width / size)


def subset(data: Dataset, indices: list[int]) -> Dataset:
    """The views `indices` of `data` (with their images, when it holds any)."""
    return dataclasses.replace(data, cameras=[data.cameras[i] for i in indices],
                               images=None if data.images is None else [data.images[i] for i in indices],
                               alphas=None if data.alphas is None else [data.alphas[i] for i in indices],
                               indices=[data.indices[i] for i in indices])


def pin_determinism() -> None:
    """One thread for torch and numba and only deterministic kernels: the same views and seed then train
    the same model bit for bit (parallel sums round differently from run to run), as a comparison of
    strategies that share their first model needs."""
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    numba.set_num_threads(1)


def train(data: Dataset, indices: list[int], iterations: int, seed: int) -> GaussianRenderer:
    """A 3DGS model fitted to the views `indices` of `data`, as a renderer with their cameras."""
    chosen = subset(data, indices)
    model, _ = fit(chosen, TrainConfig(iterations=iterations, seed=seed), progress=False)
    return GaussianRenderer(model, training_background(chosen), chosen.cameras)


def random_model(path: Path, count: int = 10_000, seed: int = 0) -> None:
    """A seeded random splat cloud of lego's size, for when no trained model exists."""
    g = torch.Generator().manual_seed(seed)
    write_ply(GaussianModel(
        means=(torch.rand(count, 3, generator=g) - 0.5) * 1.6,
        log_scales=torch.log(0.01 + 0.02 * torch.rand(count, 3, generator=g)),
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.randn(count, generator=g),
        sh=torch.randn(count, 16, 3, generator=g) * 0.3,
    ), path)


def candidates(count: int, size: int):
    """`count` candidate cameras at size x size: lego_200's test poses, else a hemisphere; and where from."""
    if (LEGO / "transforms_test.json").is_file():
        dataset = load_blender(LEGO, "test", downscale=200 / size, views=count, with_images=False)
        return dataset.cameras, f"lego_200 test split, {count} evenly spaced views"
    return (hemisphere_cameras(count, radius=4.0, width=size, height=size, min_elevation=0.2, max_elevation=1.2),
            f"{count} hemisphere poses at radius 4")



SPLATS = 45_624
# `phd` in a child that reports its own peak RSS: VmHWM starts afresh at exec, whereas the
# child's ru_maxrss would inherit this (larger) process's high-water mark at fork.
PHD = [sys.executable, "-c", "import sys; from phd_cli import main; code = main(); "
       "print(*[l for l in open('/proc/self/status') if l.startswith('VmHWM')], file=sys.stderr); sys.exit(code)"]


def donut_model(splats: int = SPLATS, seed: int = 0) -> GaussianModel:
    """A synthetic 3DGS "glazed donut" of `splats` splats, SH degree 0 (45,624: the size of the
    third-party PLY of issue 11): splats on a torus surface inside [-1.2, 1.2]^3, flat discs (two
    tangential scales log-normal around 0.018, normal 0.003) oriented along the surface normal,
    60 % opaque (logit ~ 3) and 40 % faint (logit ~ -1), the glaze and dough colours plus noise.
    donut_200's poses look at it."""
    g = torch.Generator().manual_seed(seed)
    f64 = dict(dtype=torch.float64)
    u, v = (torch.rand(splats, generator=g, **f64) * 2 * math.pi for _ in range(2))
    normal = torch.stack([torch.cos(v) * torch.cos(u), torch.cos(v) * torch.sin(u), torch.sin(v)], -1)
    ring = torch.stack([0.8 * torch.cos(u), 0.8 * torch.sin(u), torch.zeros_like(u)], -1)
    means = ring + (0.35 * (1 - 0.1 * torch.rand(splats, generator=g, **f64)))[:, None] * normal
    helper = torch.where(normal[:, :1].abs() < 0.9, torch.tensor([1.0, 0, 0], **f64), torch.tensor([0, 1.0, 0], **f64))
    t1 = torch.nn.functional.normalize(torch.cross(helper, normal, dim=-1), dim=-1)
    rot = torch.stack([t1, torch.cross(normal, t1, dim=-1), normal], -1)          # columns: t1, t2, normal
    w = torch.sqrt((1 + rot[:, 0, 0] + rot[:, 1, 1] + rot[:, 2, 2]).clamp_min(1e-12)) / 2
    quats = torch.stack([w, (rot[:, 2, 1] - rot[:, 1, 2]) / (4 * w), (rot[:, 0, 2] - rot[:, 2, 0]) / (4 * w),
                         (rot[:, 1, 0] - rot[:, 0, 1]) / (4 * w)], -1)
    tangential = torch.randn(splats, 2, generator=g, **f64) * 0.4 + math.log(0.018)
    log_scales = torch.cat([tangential, torch.full((splats, 1), math.log(0.003), **f64)], -1)
    opaque = torch.rand(splats, generator=g) < 0.6
    logits = torch.where(opaque, 3 + torch.randn(splats, generator=g), torch.randn(splats, generator=g) - 1)
    glaze = (means[:, 2] > 0.05).double()[:, None]
    colour = glaze * torch.tensor([0.9, 0.45, 0.6], **f64) + (1 - glaze) * torch.tensor([0.75, 0.5, 0.25], **f64)
    colour = (colour + 0.08 * torch.randn(splats, 3, generator=g, **f64)).clamp(0, 1)
    return GaussianModel(means.float(), log_scales.float(), quats.float(), logits.float(),
                         ((colour - 0.5) / SH_C0)[:, None, :].float())



SPACING = 2.0           # scene units between neighbouring copies (a donut is about 2.3 across)
SH3_STD = 0.08          # std of the seeded higher SH coefficients of an SH-3 model


def grid_offsets(copies: int) -> torch.Tensor:
    """[copies, 3] centres of the copies: a near-square grid in z = 0, centred on the origin."""
    cols = math.ceil(math.sqrt(copies))
    index = torch.arange(copies)
    cells = torch.stack([index % cols, index // cols], -1).double()
    cells -= cells.mean(0)
    return torch.cat([cells * SPACING, torch.zeros(copies, 1, dtype=torch.float64)], -1)


def tiled_model(copies: int, sh_degree: int, seed: int = 0) -> GaussianModel:
    """`copies` donuts side by side (`grid_offsets`) with SH degree `sh_degree`."""
    donut = donut_model(seed=seed)
    g = donut.num_splats
    k = (sh_degree + 1) ** 2
    higher = torch.randn(g * copies, k - 1, 3, generator=torch.Generator().manual_seed(seed + 1)) * SH3_STD
    offsets = grid_offsets(copies).float().repeat_interleave(g, 0)             # [G, 3]
    return GaussianModel(means=donut.means.repeat(copies, 1) + offsets, log_scales=donut.log_scales.repeat(copies, 1),
                         quats=donut.quats.repeat(copies, 1), opacity_logits=donut.opacity_logits.repeat(copies),
                         sh=torch.cat([donut.sh.repeat(copies, 1, 1), higher], 1).contiguous())


def donut_cameras(width: int, height: int, count: int, split: str = "test") -> list[Camera]:
    """The first `count` poses of donut_200's `split` at width x height."""
    cameras = load_blender(DONUT, split, with_images=False).cameras
    step = max(1, len(cameras) // count)
    return [c.resized(width, height) for c in cameras[::step][:count]]


def child(args: list[str], env: dict[str, str] | None = None, cwd: Path = ROOT) -> dict:
    """Run `phd` in `cwd` (its phd_core is the one found there first); its wall, user and
    system seconds (os.wait4) and peak RSS (its VmHWM)."""
    with tempfile.TemporaryFile() as err:
        start = time.perf_counter()
        proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=err, cwd=cwd,
                                env={**os.environ, **(env or {})})
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
        err.seek(0)
        log = err.read().decode(errors="replace")
    if status != 0:
        raise RuntimeError(f"{' '.join(args)} failed: {log[-2000:]}")
    peak_kb = int(next(line for line in log.splitlines() if line.startswith("VmHWM")).split()[1])
    return {"wall_s": round(wall, 2), "user_s": round(usage.ru_utime, 2), "system_s": round(usage.ru_stime, 2),
            "system_share": round(usage.ru_stime / wall, 3), "peak_rss_mb": round(peak_kb / 1024)}
