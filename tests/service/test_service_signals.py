"""The uncertainty signal through the real server and client: a model calibrated on the
premultiplied signal is ranked on it (the stored r_drop carries its signal), the numbers equal
phd_core called directly, and a ranking on another signal at that r_drop is refused."""

from __future__ import annotations

import pytest

from client import ConflictError, PHDClient
from phd_core import uq
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from support.fixtures import svc_cameras


def test_a_model_calibrated_on_premultiplied_colour_ranks_on_it(svc_start, svc_model_files):
    server = svc_start()
    train, candidates = svc_cameras(3), svc_cameras(5, phase=0.3)
    renderer = GaussianRenderer(read_ply(svc_model_files["ply"]), training_cameras=train)
    direct = uq.calibrate(renderer, train, epsilon=0.05, step=0.2, samples=3, seed=1, signal="premultiplied")
    with PHDClient(server.url) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
        calibration = phd.calibrate(info.id, epsilon=0.05, step=0.2, samples=3, seed=1, signal="premultiplied")
        assert calibration.signal == "premultiplied" and calibration.r_drop == direct.r_drop > 0
        assert calibration.errors == pytest.approx(direct.errors, rel=1e-9)
        assert phd.get_model(info.id).calibration.signal == "premultiplied"

        ranking = phd.rank(info.id, candidates, samples=4, seed=2, heatmaps="base64")   # the calibration's signal
        expected = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=4, seed=2, signal="premultiplied")
        assert ranking.signal == "premultiplied" and ranking.ratio_source == "calibration"
        assert [v.index for v in ranking.views] == [r.index for r in expected]
        assert [v.sigma_max for v in ranking.views] == pytest.approx([r.sigma_max for r in expected], rel=1e-6)
        assert all(v.heatmap_png and v.render_png for v in ranking.views)

        with pytest.raises(ConflictError) as mismatch:      # r_drop measured on another signal
            phd.rank(info.id, candidates, samples=4, signal="composited")
        assert (mismatch.value.status, mismatch.value.field) == (409, "signal")
        paper = phd.rank(info.id, candidates, samples=4, seed=2, signal="composited", dropout_ratio=direct.r_drop)
        composited = uq.rank_views(renderer, candidates, ratio=direct.r_drop, samples=4, seed=2)
        assert paper.signal == "composited"
        assert [v.sigma_max for v in paper.views] == pytest.approx([r.sigma_max for r in composited], rel=1e-6)

        selected = phd.select(info.id, info.id, candidates, samples=4, seed=5, rule="sigma_mean")
        assert selected.signal == "premultiplied" and {v.choice for v in selected.views} == {"a"}   # ties go to a
