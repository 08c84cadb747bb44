"""What a model's captured views saw, kept beside the model: a rank renders only the captured
views the store lacks, and ranks exactly as it does when it renders them all."""

from __future__ import annotations

from pathlib import Path

import torch

from phd_core.io import ModelCache
from phd_core.renderers.gs3d import GaussianRenderer, write_ply
from phd_core.renderers.visibility import Seen
from phd_core.uq import rank_views
from phd_core.uq.strategies.captured import FORMAT, KIND, CapturedStore, camera_key, captured_seen
from support.fixtures import svc_cameras, svc_random_gaussians


def counting_renderer(path: Path) -> tuple[GaussianRenderer, list[str]]:
    """A renderer of the model at `path` that notes the camera of every visibility pass it runs."""
    renderer = GaussianRenderer(svc_random_gaussians(400, seed=2))
    write_ply(renderer.model, path)
    passes: list[str] = []
    visibility = renderer.visibility

    def noted(view, pixel_values=None):
        passes.append(camera_key(view.camera))
        return visibility(view, pixel_values)

    renderer.visibility = noted       # type: ignore[method-assign]
    return renderer, passes


def rank(renderer, captured, store=None):
    return rank_views(renderer, svc_cameras(6, size=20, phase=0.3), ratio=0.3, samples=4, captured=captured,
                      captured_store=store)


def test_a_rank_renders_only_the_captured_views_the_store_lacks_and_ranks_as_without_it(tmp_path: Path) -> None:
    renderer, passes = counting_renderer(tmp_path / "model.ply")
    store = CapturedStore(ModelCache(tmp_path / "model.ply"))
    rig = svc_cameras(5, size=24, phase=0.1)
    keys = [camera_key(c) for c in rig]
    expected = [r.to_dict() for r in rank(renderer, rig[:3])]           # no store: every view rendered
    assert sum(p in keys for p in passes) == 3

    for want_rendered in (keys[:3], []):                                # first rank: computed and stored
        passes.clear()
        assert [r.to_dict() for r in rank(renderer, rig[:3], store)] == expected       # bit for bit
        assert [p for p in passes if p in keys] == want_rendered
    assert set(store.index()) == set(keys[:3])

    # The rig captured two more poses: only those are rendered, and the store now holds all five.
    passes.clear()
    extended = rank(renderer, rig, store)
    assert [p for p in passes if p in keys] == keys[3:]
    assert set(store.index()) == set(keys)
    passes.clear()
    assert [r.to_dict() for r in rank(renderer, rig)] == [r.to_dict() for r in extended]

    # Another set: what the store holds is reused, the rest rendered, and the stored set stays.
    other = svc_cameras(2, size=24, phase=0.7)
    passes.clear()
    rank(renderer, [rig[0]] + other, store)
    assert [p for p in passes if p in keys + [camera_key(c) for c in other]] == [camera_key(c) for c in other]
    assert set(store.index()) == set(keys)


def test_stored_views_are_what_a_render_sees_bit_for_bit_and_survive_a_new_process(tmp_path: Path) -> None:
    renderer, passes = counting_renderer(tmp_path / "model.ply")
    rig = svc_cameras(3, size=24)
    rendered = captured_seen(renderer, rig)
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    passes.clear()
    loaded = captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))   # a fresh cache object
    assert passes == []
    for a, b in zip(rendered, loaded):
        assert isinstance(b, Seen) and b.camera is not None
        assert torch.equal(a.elements, b.elements) and a.elements.dtype == b.elements.dtype == torch.long
        assert torch.equal(a.visible_share, b.visible_share)


def test_other_renderer_settings_or_a_changed_model_render_again(tmp_path: Path) -> None:
    renderer, passes = counting_renderer(tmp_path / "model.ply")
    rig = svc_cameras(2, size=24)
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    renderer.tile = 8                                                  # another tiling sums in another order
    passes.clear()
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    assert len(passes) == 2
    passes.clear()                                                     # and what it saw replaced the views
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    assert passes == []
    write_ply(svc_random_gaussians(400, seed=5), tmp_path / "model.ply")          # another model at the path
    passes.clear()
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    assert len(passes) == 2
    # The same file loaded into another place (a trainer folder read against another capture, or
    # by a newer loader): the splats moved, so what the views saw is measured again.
    renderer.model.means = renderer.model.means + 0.01
    passes.clear()
    captured_seen(renderer, rig, CapturedStore(ModelCache(tmp_path / "model.ply")))
    assert len(passes) == 2


def test_the_models_own_captured_set_is_stored_beside_another_and_a_planned_rank_finds_its_views(
        tmp_path: Path) -> None:
    renderer, passes = counting_renderer(tmp_path / "model.ply")
    training, other = svc_cameras(3, size=24), svc_cameras(2, size=24, phase=0.7)
    store = CapturedStore(ModelCache(tmp_path / "model.ply"), default=training)
    captured_seen(renderer, other, store)                       # the first rank asked for another set
    planned = store.index()                                     # a job is planned on it (as the service does)
    assert set(planned) == {camera_key(c) for c in other}
    captured_seen(renderer, training, store)                    # meanwhile the default rank stores its own
    assert set(store.index()) == {camera_key(c) for c in other + training}
    passes.clear()
    captured_seen(renderer, other, store)                       # the planned job renders nothing
    captured_seen(renderer, training, store)
    assert passes == []
    assert {k: store.index()[k] for k in planned} == planned
    captured_seen(renderer, svc_cameras(2, size=24, phase=0.4), store)       # any other set adds nothing
    assert set(store.index()) == {camera_key(c) for c in other + training}
    since = svc_cameras(1, size=24, phase=0.9)                  # the model's own set and a capture since: kept
    captured_seen(renderer, training + since, store)
    assert set(store.index()) == {camera_key(c) for c in other + training + since}


def test_a_view_stored_but_missing_from_the_index_is_read_and_named_again(tmp_path: Path) -> None:
    renderer, passes = counting_renderer(tmp_path / "model.ply")
    rig = svc_cameras(3, size=24)
    cache = ModelCache(tmp_path / "model.ply")
    captured_seen(renderer, rig, CapturedStore(cache))
    counts = CapturedStore(cache).index()
    cache.path(KIND, {"format": FORMAT}, ".json").unlink()      # a crash after the views, before the index
    passes.clear()
    captured_seen(renderer, rig, CapturedStore(cache))
    assert passes == [] and CapturedStore(cache).index() == counts
