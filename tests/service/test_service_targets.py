"""Target views through the real server and client: the ranking equals phd_core's with the same
targets (rendered at the candidates' size), differs from the one without, and a strategy that
ignores targets is refused with the field named."""

from __future__ import annotations

import pytest

from client import InvalidInputError, PHDClient
from phd_core import uq
from phd_core.renderers.gs3d import GaussianRenderer, read_ply
from support.fixtures import svc_cameras


def test_rank_with_target_views_equals_the_library(svc_start, svc_model_files):
    # Targets whose photos are above the render cap are rendered at the candidates' size, not refused.
    server = svc_start(max_image_size=40)       # the targets at their own size would render at 48 px
    train, candidates = svc_cameras(3), svc_cameras(6, phase=0.3)
    targets = svc_cameras(4, radius=2.5, size=96, phase=1.1)          # their own size: rendered at the candidates'
    renderer = GaussianRenderer(read_ply(svc_model_files["ply"]), training_cameras=train)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
        told = phd.rank(info.id, candidates, samples=4, seed=2, dropout_ratio=0.2, targets=targets, downscale=2)
        scaled = [c.scaled(2) for c in candidates]
        expected = uq.rank_views(renderer, scaled, ratio=0.2, samples=4, seed=2,
                                 targets=[c.resized(12, 12) for c in targets])
        plain = uq.rank_views(renderer, scaled, ratio=0.2, samples=4, seed=2)
        assert [v.index for v in told.views] == [r.index for r in expected]
        assert [v.score for v in told.views] == pytest.approx([r.score for r in expected], rel=1e-6)
        assert [r.score for r in expected] != [r.score for r in plain]
        assert told.num_targets == 4 and phd.rank(info.id, candidates, samples=4, dropout_ratio=0.2).num_targets == 0
        with pytest.raises(InvalidInputError) as refused:
            phd.rank(info.id, candidates, samples=4, dropout_ratio=0.2, strategy="fvs", targets=targets)
        assert refused.value.field == "targets" and "ignores target views" in str(refused.value)


def test_the_rank_answer_names_the_rule_that_ordered_it(svc_start, svc_model_files):
    """The default told targets standing where the candidates stand (the capture's own path) follows their
    density; told other targets, or none, it spreads from the captured views; fvs names its own rule. The
    server's words are phd_core's for the same request."""
    server = svc_start()
    train, candidates = svc_cameras(3), svc_cameras(6, phase=0.3)
    elsewhere = svc_cameras(4, radius=2.5, phase=1.1)
    renderer = GaussianRenderer(read_ply(svc_model_files["ply"]), training_cameras=train)
    with PHDClient(server.url) as phd:
        info = phd.upload_model(svc_model_files["ply"], cameras=train)
        rules = {told: phd.rank(info.id, candidates, samples=4, dropout_ratio=0.2, targets=targets).rule
                 for told, targets in (("path", candidates), ("elsewhere", elsewhere), ("none", None))}
        fvs = phd.rank(info.id, candidates, samples=4, dropout_ratio=0.2, strategy="fvs").rule
    assert rules["path"].startswith("followed the targets' density")
    assert rules["elsewhere"] == "spread from the captured views, toward what the target views show that no " \
                                 "captured view saw"
    assert rules["none"] == "spread from the captured views, toward what no captured view saw"
    assert fvs == uq.STRATEGIES["fvs"].summary
    assert rules["path"] == uq.rank_views(renderer, candidates, ratio=0.2, samples=4, targets=candidates).rule
