"""Mask-independent work once per camera: calibration prepares each training view once and
re-uses it for every ratio it tries (within the byte budget), with unchanged results."""

from __future__ import annotations

import importlib
import math

import pytest
import torch
from renderers.test_gaussian_render import camera, random_scene

import phd_core.uq.sampling as sampling
from phd_core import uq as phd
from phd_core.renderers.gs3d import GaussianRenderer
from phd_core.uq.calibrate import LOOKAHEAD

calibration = importlib.import_module("phd_core.uq.calibrate")   # the module (phd.calibrate is the function)


def counting_renderer() -> tuple[GaussianRenderer, list]:
    renderer = GaussianRenderer(random_scene(60, 0, seed=1))
    prepared = []
    original = renderer.prepare

    def prepare(cam):
        prepared.append(cam)
        return original(cam)
    renderer.prepare = prepare
    return renderer, prepared


CAMERAS = [camera(24, 18, eye=(0.5 * i - 1.0, -3.0, 1.0)) for i in range(4)]


def test_calibration_prepares_each_training_view_once(monkeypatch) -> None:
    renderer, prepared = counting_renderer()
    kept = phd.calibrate(renderer, CAMERAS, epsilon=0.04, step=0.05, samples=3)
    passes = math.ceil(len(kept.ratios) / LOOKAHEAD)                 # the linear scan's passes over the views
    assert passes >= 2, "several passes must be made for re-use to matter"
    assert len(prepared) == len(CAMERAS)

    monkeypatch.setattr(sampling, "VIEW_CACHE_BYTES", 0)           # nothing fits: prepared on every use
    renderer, prepared = counting_renderer()
    again = phd.calibrate(renderer, CAMERAS, epsilon=0.04, step=0.05, samples=3)
    assert len(prepared) == len(CAMERAS) * passes, "a reference comes from its view's first pass, not a preparation"
    assert (again.r_drop, again.errors) == (kept.r_drop, kept.errors)


def test_linear_scan_with_lookahead_equals_the_one_by_one_scan(monkeypatch) -> None:
    """Rendering LOOKAHEAD ratios per pass changes the cost, not the result or the curve."""
    batched = phd.calibrate(counting_renderer()[0], CAMERAS, epsilon=0.04, step=0.05, samples=3)
    monkeypatch.setattr(calibration, "LOOKAHEAD", 1)
    single = phd.calibrate(counting_renderer()[0], CAMERAS, epsilon=0.04, step=0.05, samples=3)
    assert batched.r_drop == single.r_drop and batched.ratios == single.ratios
    assert batched.errors == pytest.approx(single.errors, rel=1e-12)
    assert batched.errors[-1] >= 0.04 > batched.errors[-2]      # the curve ends at the first failure


def test_uncertainty_prepares_once_per_view_for_all_mask_chunks(monkeypatch) -> None:
    monkeypatch.setattr(sampling, "MAX_MASKS_PER_RENDER", 3)       # 10 masks = 4 chunks
    renderer, prepared = counting_renderer()
    views = phd.uncertainty(renderer, CAMERAS[:2], ratio=0.3, samples=10)
    assert len(prepared) == 2 and all(v.sigma_max > 0 for v in views)


def test_selection_prepares_each_view_once_per_model_for_masks_and_full_renders() -> None:
    renderer_a, prepared_a = counting_renderer()
    renderer_b, prepared_b = counting_renderer()
    result = phd.select_models(renderer_a, renderer_b, CAMERAS, ratio_a=0.2, ratio_b=0.4, samples=4,
                               rule="sigma_mean", keep_images="both")
    assert len(prepared_a) == len(prepared_b) == len(CAMERAS)
    for view, cam in zip(result.views, CAMERAS):          # the kept renders are the full models'
        chosen, other = (renderer_a, renderer_b) if view.choice == "a" else (renderer_b, renderer_a)
        assert torch.equal(view.image, chosen.render(cam)[0])
        assert torch.equal(view.other_image, other.render(cam)[0])
