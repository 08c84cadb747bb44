"""`phd view`: an interactive 3D view (viser) of a model, its training cameras and the
candidate poses coloured by their ranking score; clicking a candidate shows its mean
render and zeta heat map.

viser is an optional extra (`pip install '.[viewer]'`), imported only when the command
runs, so `phd` and the service never need it. viser serves its browser client from the
installed package: nothing is fetched from the internet.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from phd_core.errors import InputError

from .options import model_help

TRAINING_COLOUR = (40, 40, 40)
UNRANKED_COLOUR = (170, 170, 170)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "view", help="3D view of a model, its training cameras and ranked candidates (needs '.[viewer]')",
        description="Open an interactive 3D view (viser, in the browser) of the model's splats, its training "
                    "cameras and the candidate poses coloured by score (yellow = capture first). Click a candidate "
                    "to see its mean render and zeta heat map.")
    p.add_argument("model", type=Path, help=model_help())
    p.add_argument("--candidates", type=Path, default=None,
                   help="candidate poses (transforms.json or a list of frames), as given to `phd rank`")
    p.add_argument("--ranking", type=Path, default=None,
                   help="a ranking of those candidates: the JSON of `phd rank --out` or of the service's rank result")
    p.add_argument("--ratio", type=float, default=None,
                   help="dropout ratio for the renders shown on click (default: the ranking's)")
    p.add_argument("--samples", type=int, default=16, help="dropout samples N for the renders shown on click")
    p.add_argument("--downscale", type=float, default=1.0, help="render the clicked candidate at 1/downscale")
    p.add_argument("--max-splats", type=int, default=200_000, help="draw at most this many splats (the most opaque)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8080)
    p.set_defaults(func=run)


def import_viser() -> Any:
    try:
        import viser
    except ImportError:
        raise InputError("viser", "the 3D viewer is an optional extra: pip install 'ph-dropout-service[viewer]' "
                                  "(or pip install -e '.[viewer]' in a checkout)") from None
    return viser


# ----------------------------------------------------------------------------- inputs

def read_ranking(path: Path) -> dict:
    """{candidate index: score} plus the dropout ratio, from `phd rank` JSON ("ranking") or a
    service RankResult ("views")."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InputError("ranking", f"cannot read {path}: {exc}") from None
    views = data.get("ranking", data.get("views")) if isinstance(data, dict) else None
    if not isinstance(views, list) or not all(isinstance(v, dict) and "index" in v and "score" in v for v in views):
        raise InputError("ranking", f"{path} holds no ranking: expected 'ranking' (phd rank) or 'views' (the service) "
                                    "with an index and a score per candidate")
    return {"scores": {int(v["index"]): float(v["score"]) for v in views},
            "ranks": {int(v["index"]): int(v.get("rank", k)) for k, v in enumerate(views, 1)},
            "ratio": data.get("dropout_ratio")}


def score_colours(scores: dict[int, float], count: int) -> list[tuple[int, int, int]]:
    """One RGB per candidate: the heat-map ramp over the scores (top score = yellow), grey unranked."""
    from phd_core.io.heatmap import apply_colormap

    colours = [UNRANKED_COLOUR] * count
    if scores:
        lo, hi = min(scores.values()), max(scores.values())
        for index, score in scores.items():
            t = (score - lo) / (hi - lo) if hi > lo else 1.0
            r, g, b = (int(c) for c in apply_colormap(np.array(t)))      # RGB
            colours[index] = (r, g, b)
    return colours


def viser_pose(camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a camera for viser, whose frustums look along +z with y down (OpenCV);
    ours are OpenGL (-z forward, y up)."""
    import viser.transforms as vtf

    c2w = camera.c2w.double().numpy()
    rotation = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    return vtf.SO3.from_matrix(rotation).wxyz, c2w[:3, 3]


# ----------------------------------------------------------------------------- the scene

class Viewer:
    """The scene of one model in a viser server; `show(i)` is what a click on candidate i does."""

    def __init__(self, server: Any, renderer, candidates: list, ranking: dict | None, *, ratio: float | None,
                 samples: int, max_splats: int):
        self.server, self.renderer, self.candidates = server, renderer, candidates
        self.ranking = ranking or {"scores": {}, "ranks": {}, "ratio": None}
        self.ratio = ratio if ratio is not None else self.ranking["ratio"]
        self.samples = samples
        self.lock = threading.Lock()   # one render at a time, whatever the clicks
        self.frustums: dict[str, Any] = {}
        scale = self._scene_scale()
        self._place_view()
        self._add_splats(max_splats)
        for i, camera in enumerate(renderer.training_cameras or []):
            self._frustum(f"/training/{i}", camera, TRAINING_COLOUR, scale * 0.6)
        colours = score_colours(self.ranking["scores"], len(candidates))
        for i, camera in enumerate(candidates):
            handle = self._frustum(f"/candidates/{i}", camera, colours[i], scale)
            handle.on_click(lambda _event, i=i: self.clicked(i))
        gui = server.gui
        self.info = gui.add_markdown(self._summary())
        self.render_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="mean render", visible=False)
        self.heatmap_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="zeta heat map", visible=False)
        self.shown: int | None = None

    def _scene_scale(self) -> float:
        cams = list(self.renderer.training_cameras or []) + list(self.candidates)
        if len(cams) < 2:
            return 0.3
        positions = np.stack([c.c2w[:3, 3].double().numpy() for c in cams])
        return 0.03 * float(np.linalg.norm(positions.max(0) - positions.min(0))) or 0.3

    def _place_view(self) -> None:
        """Up = the capture's (`phd_core.scene.capture_up` of the training cameras, else of the
        candidates, on the model's opaque splats as `phd candidates --model` places its poses);
        the browser's first view from beyond the cameras, looking at the point they surround."""
        from phd_core.scene import capture_up
        from phd_core.uq.candidates import scene_points

        training = list(self.renderer.training_cameras or [])
        cams = training + list(self.candidates)
        if not cams:
            return
        c2w = np.stack([c.c2w.double().numpy() for c in cams])            # [C, 4, 4]
        up = capture_up(training or cams, scene_points(self.renderer)).vector.numpy()
        centre = c2w[:, :3, 3].mean(0)
        radius = float(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1).max()) or 1.0
        self.server.scene.set_up_direction(tuple(up))
        side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        camera = self.server.initial_camera
        camera.look_at = tuple(centre)
        camera.position = tuple(centre + radius * (1.1 * side / np.linalg.norm(side) + 0.5 * up))
        camera.up = tuple(up)

    def _add_splats(self, max_splats: int) -> None:
        model = getattr(self.renderer, "model", None)
        if model is None or not hasattr(model, "covariances"):   # NeRF: no primitives to draw
            self.num_splats = 0
            return
        import torch

        order = torch.argsort(model.opacity_logits, descending=True)[:max_splats]   # the most opaque first
        kept = model.subset(order)
        self.num_splats = kept.num_splats
        self.server.scene.add_gaussian_splats(
            "/splats", centers=kept.means.double().numpy().astype(np.float32),
            covariances=kept.covariances().numpy().astype(np.float32),
            rgbs=kept.base_colours().numpy().astype(np.float32),
            opacities=torch.sigmoid(kept.opacity_logits.double()).numpy().astype(np.float32)[:, None])

    def _frustum(self, name: str, camera, colour, scale: float) -> Any:
        wxyz, position = viser_pose(camera)
        handle = self.server.scene.add_camera_frustum(
            name, fov=2 * math.atan(0.5 * camera.height / camera.fy), aspect=camera.width / camera.height,
            scale=scale, color=colour, wxyz=wxyz, position=position)
        self.frustums[name] = handle
        return handle

    def _summary(self) -> str:
        ranked = len(self.ranking["scores"])
        return (f"**{self.num_splats} splats**, {len(self.renderer.training_cameras or [])} training cameras (dark), "
                f"{len(self.candidates)} candidates ({ranked} ranked: yellow = capture first). "
                "Click a candidate for its render and heat map.")

    def clicked(self, index: int) -> None:
        try:
            self.show(index)
        except InputError as exc:   # shown where the user looks, not as a traceback in the terminal
            self.info.content = f"**cannot render candidate {index}**: {exc}"

    def show(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Render candidate `index` with N dropout samples: its mean and its zeta heat map."""
        import torch

        from phd_core import uq
        from phd_core.io import colorize

        if self.ratio is None:
            raise InputError("ratio", "give --ratio (or a --ranking that states its dropout ratio) to render")
        with self.lock:
            view = uq.view_uncertainty(self.renderer, self.candidates[index], ratio=self.ratio, samples=self.samples,
                                       keep_maps=True)
            assert view.mean is not None and view.zeta is not None  # keep_maps=True keeps them
            render = (view.mean.clamp(0, 1) * 255).round().to(torch.uint8).numpy()
            heatmap = colorize(view.zeta)[0]
            self.render_image.image, self.heatmap_image.image = render, heatmap
            self.render_image.visible = self.heatmap_image.visible = True
            rank = self.ranking["ranks"].get(index)
            score = self.ranking["scores"].get(index)
            self.info.content = (f"**candidate {index}**" + (f", rank {rank}, score {score:.4g}" if rank is not None
                                                             else "") +
                                 f": sigma_max {view.sigma_max:.4g}, sigma_mean {view.sigma_mean:.4g} "
                                 f"(ratio {self.ratio}, N = {self.samples}; heat map scaled to its own max)")
            self.shown = index
        return render, heatmap


def run(args: argparse.Namespace) -> int:
    from phd_core.scene import cameras_from_json

    from .models import open_model

    if args.ranking is not None and args.candidates is None:
        raise InputError("candidates",
                         "a ranking names candidates by index: give --candidates with the poses it ranked")
    if args.samples < 2:
        raise InputError("samples", f"must be at least 2, got {args.samples}")
    viser = import_viser()
    renderer = open_model(args.model).renderer
    candidates = [] if args.candidates is None else cameras_from_json(args.candidates)
    candidates = [c.scaled(args.downscale) for c in candidates] if args.downscale != 1 else candidates
    ranking = None if args.ranking is None else read_ranking(args.ranking)
    if ranking is not None and ranking["scores"] and max(ranking["scores"]) >= len(candidates):
        raise InputError("ranking", f"ranks candidate {max(ranking['scores'])} but --candidates has {len(candidates)}")
    server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    Viewer(server, renderer, candidates, ranking, ratio=args.ratio, samples=args.samples, max_splats=args.max_splats)
    print(f"phd view: http://{args.host}:{server.get_port()} (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    finally:
        server.stop()
