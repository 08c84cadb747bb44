"""`phd view`: viser stays optional (lazy import, clear error without it); with viser the
scene holds the splats, the training cameras and the candidates coloured by score, and a
click on a candidate shows its PH-Dropout mean render and heat map."""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import numpy as np
import pytest
import torch

from phd_core import uq
from phd_core.io import colorize
from phd_core.renderers.gs3d import GaussianRenderer, write_ply
from support.fixtures import svc_cameras, svc_free_port, svc_random_gaussians

BLOCK_VISER = "import sys; sys.modules['viser'] = None; "   # as if viser were not installed


def test_phd_runs_without_viser_and_view_names_the_extra(tmp_path):
    path = tmp_path / "m.ply"
    write_ply(svc_random_gaussians(20), path)
    code = (BLOCK_VISER + "from phd_cli import build_parser, main; build_parser(); "
            "assert 'viser' not in sys.modules or sys.modules['viser'] is None; "
            f"sys.exit(main(['view', {str(path)!r}]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "phd view: error: viser:" in done.stderr and "[viewer]" in done.stderr
    assert "Traceback" not in done.stderr


def test_view_needs_candidates_for_a_ranking(tmp_path, capsys):
    from phd_cli import main

    ranking = tmp_path / "r.json"
    ranking.write_text(json.dumps({"ranking": [{"index": 0, "score": 1.0}]}))
    assert main(["view", str(tmp_path / "m.ply"), "--ranking", str(ranking)]) == 2
    assert "candidates: a ranking names candidates by index" in capsys.readouterr().err


@pytest.fixture
def scene(tmp_path):
    viser = pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from phd_cli.view import Viewer, read_ranking

    model = svc_random_gaussians(300)
    training, candidates = svc_cameras(3), svc_cameras(5, phase=0.35)
    renderer = GaussianRenderer(model, training_cameras=training)
    ranked = uq.rank_views(renderer, candidates, ratio=0.3, samples=4, seed=0, top_k=3)
    path = tmp_path / "ranking.json"   # the shape `phd rank --out` writes
    path.write_text(json.dumps({"dropout_ratio": 0.3, "ranking": [r.to_dict() for r in ranked]}))
    server = viser.ViserServer(host="127.0.0.1", port=svc_free_port(), verbose=False)
    viewer = Viewer(server, renderer, candidates, read_ranking(path), ratio=None, samples=4, max_splats=250)
    yield viewer, renderer, candidates, ranked, server
    server.stop()


def test_scene_holds_splats_cameras_and_candidates_coloured_by_score(scene):
    viewer, renderer, candidates, ranked, server = scene
    assert viewer.num_splats == 250                      # capped at --max-splats, the most opaque kept
    names = sorted(viewer.frustums)
    assert names == sorted([f"/training/{i}" for i in range(3)] + [f"/candidates/{i}" for i in range(5)])
    colours = {i: tuple(int(c) for c in viewer.frustums[f"/candidates/{i}"].color) for i in range(5)}
    top = max(ranked, key=lambda r: r.score).index
    bottom = min(ranked, key=lambda r: r.score).index
    assert colours[top] == (253, 231, 37) and colours[bottom] == (68, 1, 84)   # the heat-map ramp's ends
    unranked = set(range(5)) - {r.index for r in ranked}
    assert len(unranked) == 2 and all(colours[i] == (170, 170, 170) for i in unranked)
    # Frustum poses: viser's camera looks along +z (OpenCV); ours along -z (OpenGL).
    for i, camera in enumerate(candidates):
        handle = viewer.frustums[f"/candidates/{i}"]
        c2w = camera.c2w.double().numpy()
        assert np.allclose(handle.position, c2w[:3, 3], atol=1e-5)
        w, x, y, z = handle.wxyz
        forward = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])   # R @ (0, 0, 1)
        assert np.allclose(forward, -c2w[:3, 2], atol=1e-5)
    # viser serves its browser client from the installed package (nothing fetched from elsewhere).
    page = httpx.get(f"http://127.0.0.1:{server.get_port()}/", timeout=30)
    assert page.status_code == 200 and "<script" in page.text and len(page.content) > 100_000


def test_clicking_a_candidate_shows_its_render_and_heat_map(scene):
    viewer, renderer, candidates, ranked, _ = scene
    index = ranked[0].index
    callbacks = viewer.frustums[f"/candidates/{index}"]._impl.click_cb   # what viser calls on a click
    assert len(callbacks) == 1 and not viewer.frustums["/training/0"]._impl.click_cb
    callbacks[0].callback(None)
    expected = uq.view_uncertainty(renderer, candidates[index], ratio=0.3, samples=4, keep_maps=True)
    assert viewer.shown == index
    assert np.array_equal(viewer.heatmap_image.image, colorize(expected.zeta)[0])
    assert np.array_equal(viewer.render_image.image,
                          (expected.mean.clamp(0, 1) * 255).round().to(torch.uint8).numpy())
    assert f"candidate {index}**, rank 1" in viewer.info.content
    assert f"sigma_max {expected.sigma_max:.4g}" in viewer.info.content


def test_a_2dgs_model_is_drawn_as_flat_splats(tmp_path):
    viser = pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from phd_cli.view import Viewer
    from phd_core.renderers.gs2d import SurfelRenderer
    from support.surfels import random_surfels

    renderer = SurfelRenderer(random_surfels(40, seed=2), training_cameras=svc_cameras(2))
    server = viser.ViserServer(host="127.0.0.1", port=svc_free_port(), verbose=False)
    try:
        viewer = Viewer(server, renderer, svc_cameras(3, phase=0.35), None, ratio=0.3, samples=4, max_splats=30)
        assert viewer.num_splats == 30
        assert sorted(viewer.frustums) == ["/candidates/0", "/candidates/1", "/candidates/2",
                                           "/training/0", "/training/1"]
    finally:
        server.stop()


def test_the_first_view_stands_on_the_captures_up(tmp_path):
    """Training photos from one side, looking down (support/upright.py): the viewer's up is the
    capture's, not the cameras' mean up (38 degrees off)."""
    viser = pytest.importorskip("viser", reason="viser is not installed (pip install -e '.[viewer]')")
    from phd_cli.view import Viewer
    from support.upright import degrees_from_up, mean_up, one_side

    training = one_side()
    server = viser.ViserServer(host="127.0.0.1", port=svc_free_port(), verbose=False)
    try:
        Viewer(server, GaussianRenderer(svc_random_gaussians(20), training_cameras=training), [], None, ratio=None,
               samples=4, max_splats=20)
        assert degrees_from_up(torch.tensor(server.initial_camera.up, dtype=torch.float64)) < 2.0
        assert degrees_from_up(mean_up(training)) > 25.0
    finally:
        server.stop()
