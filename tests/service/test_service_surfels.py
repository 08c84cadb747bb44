"""2DGS models through the real server and client: a hand-made PLY in the 2DGS reference
layout and a model trained by `phd train --model 2dgs` are uploaded, calibrated, ranked with
every strategy and selected against a 3DGS model; every number equals `phd_core` called
directly."""

from __future__ import annotations

import pytest

from client import PHDClient
from phd_core import uq
from phd_core.renderers import load_model
from phd_core.renderers.gs2d import SurfelRenderer, parse_surfel_ply
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from phd_core.uq.strategies import STRATEGIES
from support.fixtures import LEGO, svc_cameras
from support.surfels import random_surfels, reference_layout_ply


@pytest.fixture(scope="module")
def surfel_ply(tmp_path_factory):
    path = tmp_path_factory.mktemp("surfels") / "hand_made.ply"
    path.write_bytes(reference_layout_ply(random_surfels(300, seed=4)))
    return path


def test_a_hand_made_2dgs_ply_calibrates_ranks_and_selects(svc_start, svc_model_files, surfel_ply):
    server = svc_start()
    train, candidates = svc_cameras(3), svc_cameras(5, phase=0.3)
    surfels = SurfelRenderer(parse_surfel_ply(surfel_ply.read_bytes()), training_cameras=train)
    splats = GaussianRenderer(read_ply(svc_model_files["ply"]), training_cameras=train)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(surfel_ply, cameras=train)
        assert (info.kind, info.num_units, info.sh_degree, info.num_training_cameras) == ("2dgs", 300, 1, 3)
        assert [p.name for p in server.settings.data_dir.rglob(f"{info.id}.*")] == [f"{info.id}.ply"]
        other = phd.upload_model(svc_model_files["ply"], cameras=train)
        assert other.kind == "3dgs"

        calibration = phd.calibrate(info.id, epsilon=0.05, step=0.2, samples=3, seed=1)
        direct = uq.calibrate(surfels, train, epsilon=0.05, step=0.2, samples=3, seed=1)
        assert calibration.r_drop == direct.r_drop > 0 and calibration.ratios == direct.ratios
        assert calibration.errors == pytest.approx(direct.errors, rel=1e-9)

        for strategy in STRATEGIES:
            ranking = phd.rank(info.id, candidates, samples=4, seed=2, strategy=strategy)
            expected = uq.rank_views(surfels, candidates, ratio=direct.r_drop, samples=4, seed=2, strategy=strategy)
            assert [v.index for v in ranking.views] == [r.index for r in expected], strategy
            assert [v.sigma_max for v in ranking.views] == pytest.approx([r.sigma_max for r in expected], rel=1e-6)

        result = phd.select(info.id, other.id, candidates, samples=4, seed=5, ratio_b=0.3, rule="sigma_mean")
        chosen = uq.select_models(surfels, splats, candidates, ratio_a=direct.r_drop, ratio_b=0.3, samples=4, seed=5,
                                  rule="sigma_mean")
        assert [v.choice for v in result.views] == [v.choice for v in chosen.views]
        assert [v.score_a for v in result.views] == pytest.approx([v.score_a for v in chosen.views], rel=1e-6)
        default = phd.select(info.id, other.id, candidates, samples=4, seed=5, ratio_b=0.3)   # coverage_checked
        assert len(default.views) == 5 and {v.model_id for v in default.views} <= {info.id, other.id}


def test_a_trained_2dgs_model_uploads_with_its_sidecar_and_ranks(svc_start, tmp_path):
    from phd_core.train.gs2d import train_surfels

    out = tmp_path / "trained2d.ply"
    train_surfels(LEGO, views=[0, 20, 40], downscale=8, iterations=12, out=out, progress=False, init_points=300,
                  normal_consistency=0.05, depth_distortion=1.0)
    renderer = load_model(out)
    assert renderer.kind == "2dgs" and len(renderer.training_cameras) == 3
    candidates = [c.resized(16, 16) for c in renderer.training_cameras] + svc_cameras(2, radius=4.0, size=16)
    server = svc_start()
    with PHDClient(server.url) as phd:
        info = phd.upload_model(out)                      # cameras from the trainer's sidecar
        assert (info.kind, info.num_units, info.num_training_cameras) == ("2dgs", renderer.num_units, 3)
        calibration = phd.calibrate(info.id, epsilon=0.5, step=0.25, samples=2, width=16, height=16)
        training = [c.resized(16, 16) for c in renderer.training_cameras]
        direct = uq.calibrate(renderer, training, epsilon=0.5, step=0.25, samples=2)
        assert calibration.r_drop == direct.r_drop > 0
        ranking = phd.rank(info.id, candidates, samples=3, seed=1)
        expected = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=3, seed=1)
        assert [v.index for v in ranking.views] == [r.index for r in expected]
