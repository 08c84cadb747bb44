"""PH-Dropout engine: masks, calibration (Algorithm 1), zeta, ranking, selection, extremes.

Toy renderers (tests/support/toy_renderers.py) make every case cheap; the GS tests use a small
random GaussianModel through the real rasteriser, and a model trained on lego for the
checks asked of a real model (float32 accumulation, bisection = linear scan). Expected
values come from independent computations: one render per mask, numpy float64 std,
explicit loops.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from phd_core import uq as phd
from phd_core.errors import InputError
from phd_core.eval import psnr, ssim
from support.fixtures import LEGO
from support.toy_renderers import BlobRenderer, ConstantRenderer, EmptyRenderer, away_camera, ring_cameras

CAMERAS = ring_cameras(6)


@pytest.fixture(scope="module")
def blobs() -> BlobRenderer:
    return BlobRenderer.random(40, seed=0)


# ---------------------------------------------------------------------------------------- masks

def test_uniforms_are_seeded_and_in_range() -> None:
    u = phd.dropout_uniforms(500, 8, seed=3)
    assert u.shape == (8, 500) and u.dtype == torch.float32
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    assert torch.equal(u, phd.dropout_uniforms(500, 8, seed=3))
    assert not torch.equal(u, phd.dropout_uniforms(500, 8, seed=4))


def test_more_samples_extend_the_same_draw() -> None:
    """N masks are the first N of any larger draw with the same seed: raising N refines one estimate."""
    assert torch.equal(phd.dropout_uniforms(300, 4, seed=9), phd.dropout_uniforms(300, 64, seed=9)[:4])


def test_masks_are_nested_and_hit_the_extremes() -> None:
    u = phd.dropout_uniforms(20000, 4, seed=1)
    previous = phd.keep_masks(u, 0.0)
    assert previous.all()
    for r in (0.1, 0.25, 0.5, 0.9, 0.999):
        keep = phd.keep_masks(u, r)
        assert not (keep & ~previous).any(), "a unit dropped at a lower ratio came back"
        assert abs(keep.float().mean().item() - (1 - r)) < 0.01
        previous = keep
    assert not phd.keep_masks(u, 1.0).any()


@pytest.mark.parametrize("call, field", [
    (lambda: phd.dropout_uniforms(10, 0, 0), "samples"),
    (lambda: phd.dropout_uniforms(-1, 4, 0), "num_units"),
    (lambda: phd.dropout_uniforms(10, 4, -1), "seed"),
    (lambda: phd.dropout_uniforms(10, 4, True), "seed"),
    (lambda: phd.dropout_uniforms(10, 4, 1.5), "seed"),
    (lambda: phd.keep_masks(torch.rand(2, 3), 1.5), "ratio"),
    (lambda: phd.keep_masks(torch.rand(2, 3), -0.1), "ratio"),
    (lambda: phd.keep_masks(torch.rand(2, 3), math.nan), "ratio"),
])
def test_mask_arguments_are_validated(call, field: str) -> None:
    with pytest.raises(InputError) as info:
        call()
    assert info.value.field == field


# ---------------------------------------------------------------------------------------- std

@pytest.mark.parametrize("ddof", [0, 1])
def test_sample_std_matches_numpy(ddof: int) -> None:
    g = torch.Generator().manual_seed(0)
    images = (torch.rand(70, 5, 4, 3, generator=g) * 0.01 + 1000.0)   # large offset, tiny spread; > one chunk
    std, mean = phd.sample_std(images, ddof=ddof)
    ref = images.double().numpy()
    np.testing.assert_allclose(std.numpy(), ref.std(axis=0, ddof=ddof), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(mean.numpy(), ref.mean(axis=0), rtol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identical_samples_give_exactly_zero(dtype: torch.dtype) -> None:
    image = torch.rand(6, 7, 3) / 3 + 1 / 7            # values with long binary expansions
    std, mean = phd.sample_std(image.expand(13, -1, -1, -1), dtype=dtype)
    assert torch.count_nonzero(std) == 0
    assert torch.equal(mean.to(torch.float32), image)


def test_sample_count_against_ddof() -> None:
    one = torch.rand(1, 2, 2, 3)
    with pytest.raises(InputError) as info:
        phd.sample_std(one, ddof=1)
    assert info.value.field == "samples"
    std, _ = phd.sample_std(one, ddof=0)
    assert torch.count_nonzero(std) == 0


# ---------------------------------------------------------------------------------------- uncertainty

def test_zeta_matches_one_render_per_mask(blobs: BlobRenderer) -> None:
    camera, ratio, samples = CAMERAS[1], 0.3, 9
    view = phd.view_uncertainty(blobs, camera, ratio=ratio, samples=samples, seed=5, keep_maps=True)
    keep = phd.dropout_uniforms(blobs.num_units, samples, 5).numpy() >= ratio
    renders = np.stack([blobs.render(camera, torch.from_numpy(k[None]))[0].double().numpy() for k in keep])
    zeta = renders.std(axis=0, ddof=1)
    np.testing.assert_allclose(view.zeta.numpy(), zeta, atol=1e-6)
    np.testing.assert_allclose(view.mean.numpy(), renders.mean(axis=0), atol=1e-6)
    assert view.sigma_max == pytest.approx(zeta.max(), abs=1e-6)
    assert view.sigma_mean == pytest.approx(zeta.mean(), abs=1e-7)
    assert view.sigma_max > 0.05, "the toy view must be uncertain for this test to mean anything"


def test_masks_are_rendered_in_one_batched_call_per_view() -> None:
    renderer = BlobRenderer.random(20, seed=2)
    phd.uncertainty(renderer, CAMERAS[:3], ratio=0.2, samples=phd.MAX_MASKS_PER_RENDER)
    assert renderer.calls == 3
    renderer.calls = 0
    big = phd.view_uncertainty(renderer, CAMERAS[0], ratio=0.2, samples=phd.MAX_MASKS_PER_RENDER + 6, seed=1)
    assert renderer.calls == 2   # chunked only beyond MAX_MASKS_PER_RENDER
    reference = BlobRenderer.random(20, seed=2)
    u = phd.dropout_uniforms(20, phd.MAX_MASKS_PER_RENDER + 6, 1) >= 0.2
    expected = reference.render(CAMERAS[0], u).double().std(0).max().item()
    assert big.sigma_max == pytest.approx(expected, abs=1e-6)


def test_same_submodels_for_every_view_of_a_call(blobs: BlobRenderer) -> None:
    together = phd.uncertainty(blobs, CAMERAS[:3], ratio=0.4, samples=6, seed=11)
    alone = [phd.view_uncertainty(blobs, c, ratio=0.4, samples=6, seed=11) for c in CAMERAS[:3]]
    assert [v.sigma_max for v in together] == [v.sigma_max for v in alone]
    assert phd.sigma_max_bar(together) == pytest.approx(np.mean([v.sigma_max for v in alone]), abs=1e-15)


def test_ratio_zero_gives_exactly_zero(blobs: BlobRenderer) -> None:
    view = phd.view_uncertainty(blobs, CAMERAS[0], ratio=0.0, samples=8, keep_maps=True)
    assert view.sigma_max == 0.0 and view.sigma_mean == 0.0
    assert torch.count_nonzero(view.zeta) == 0
    assert torch.equal(view.mean, blobs.render(CAMERAS[0])[0])


@pytest.mark.parametrize("ratio", [0.999, 1.0])
def test_ratio_near_and_at_one_is_finite(ratio: float) -> None:
    renderer = BlobRenderer.random(40, seed=0, background=(0.2, 0.5, 1.0))
    view = phd.view_uncertainty(renderer, CAMERAS[0], ratio=ratio, samples=8, keep_maps=True)
    assert math.isfinite(view.sigma_max) and torch.isfinite(view.zeta).all()
    if ratio == 1.0:   # every unit dropped: the background, identical in every sample
        assert view.sigma_max == 0.0
        assert torch.equal(view.mean, torch.tensor([0.2, 0.5, 1.0]).expand(12, 12, 3))


def test_two_samples_defined_and_one_sample_rejected(blobs: BlobRenderer) -> None:
    two = phd.view_uncertainty(blobs, CAMERAS[0], ratio=0.5, samples=2, keep_maps=True)
    assert torch.isfinite(two.zeta).all() and two.sigma_max > 0
    with pytest.raises(InputError) as info:
        phd.view_uncertainty(blobs, CAMERAS[0], ratio=0.5, samples=1)
    assert info.value.field == "samples"
    one = phd.view_uncertainty(blobs, CAMERAS[0], ratio=0.5, samples=1, ddof=0)
    assert one.sigma_max == 0.0


@pytest.mark.parametrize("renderer", [ConstantRenderer(), EmptyRenderer()], ids=["constant", "empty"])
def test_mask_independent_renderers_have_zero_uncertainty(renderer) -> None:
    views = phd.uncertainty(renderer, CAMERAS[:2], ratio=0.5, samples=5, keep_maps=True)
    assert all(v.sigma_max == 0.0 and torch.count_nonzero(v.zeta) == 0 for v in views)
    assert phd.sigma_max_bar(views) == 0.0


def test_camera_that_sees_nothing_has_zero_uncertainty(blobs: BlobRenderer) -> None:
    view = phd.view_uncertainty(blobs, away_camera(), ratio=0.5, samples=8)
    assert view.sigma_max == 0.0 and view.sigma_mean == 0.0


def test_float32_accumulation_agrees_with_float64(blobs: BlobRenderer) -> None:
    a = phd.uncertainty(blobs, CAMERAS, ratio=0.4, samples=16, dtype=torch.float64)
    b = phd.uncertainty(blobs, CAMERAS, ratio=0.4, samples=16, dtype=torch.float32)
    assert abs(phd.sigma_max_bar(a) - phd.sigma_max_bar(b)) < 1e-5


@pytest.mark.parametrize("kwargs, field", [
    ({"ratio": 1.2}, "ratio"), ({"ratio": 0.3, "samples": 0}, "samples"), ({"ratio": 0.3, "ddof": -1}, "ddof"),
    ({"ratio": 0.3, "seed": "a"}, "seed"), ({"ratio": 0.3, "samples": 3, "ddof": 3}, "samples"),
    ({"ratio": 0.3, "dtype": torch.float16}, "dtype"),
])
def test_uncertainty_arguments_are_validated(blobs: BlobRenderer, kwargs: dict, field: str) -> None:
    with pytest.raises(InputError) as info:
        phd.uncertainty(blobs, CAMERAS[:1], **kwargs)
    assert info.value.field == field
    with pytest.raises(InputError) as info:
        phd.uncertainty(blobs, [], ratio=0.3)
    assert info.value.field == "cameras"


def test_broken_renderer_output_is_reported() -> None:
    class NaNRenderer(ConstantRenderer):
        def render(self, camera, keep=None, signal="composited"):
            out = super().render(camera, keep, signal)
            out[:, 0, 0, 0] = math.nan
            return out

    with pytest.raises(RuntimeError, match="NaN"):
        phd.view_uncertainty(NaNRenderer(), CAMERAS[0], ratio=0.5, samples=3)


# ---------------------------------------------------------------------------------------- calibration

def brute_force_error(renderer, cameras, ratio: float, samples: int, seed: int) -> float:
    """Algorithm 1's error: one render per mask and view, numpy float64."""
    keep = phd.dropout_uniforms(renderer.num_units, samples, seed).numpy() >= ratio
    per_view = []
    for camera in cameras:
        full = renderer.render(camera)[0].double().numpy()
        per_view.append(np.mean([np.abs(renderer.render(camera, torch.from_numpy(k[None]))[0].double().numpy()
                                        - full).mean() for k in keep]))
    return float(np.mean(per_view))


def test_linear_scan_follows_algorithm_1(blobs: BlobRenderer) -> None:
    cameras = CAMERAS[::2]
    result = phd.calibrate(blobs, cameras, epsilon=0.03, step=0.05, samples=4, seed=2)
    k = round(result.r_drop / 0.05)
    assert result.method == "linear" and not result.capped and result.warnings == []
    assert result.ratios == [round(0.05 * j, 10) for j in range(1, k + 2)]   # every ratio up to the first failure
    assert all(e < 0.03 for e in result.errors[:-1]) and result.errors[-1] >= 0.03
    for ratio, error in zip(result.ratios, result.errors):
        assert error == pytest.approx(brute_force_error(blobs, cameras, ratio, 4, 2), abs=1e-6)
    assert result.to_dict()["r_drop"] == result.r_drop


def linear_answer(curve: phd.CalibrationResult, epsilon: float) -> float:
    """What Algorithm 1's loop returns for `epsilon`, read off the full error curve."""
    passing = 0.0
    for ratio, error in zip(curve.ratios, curve.errors):
        if not error < epsilon:
            break
        passing = ratio
    return passing


def assert_bisection_agrees(renderer, cameras, step: float, samples: int,
                            quantiles: tuple[float, ...] = (0.1, 0.35, 0.6, 0.9)) -> None:
    curve = phd.calibrate(renderer, cameras, epsilon=100.0, step=step, samples=samples)   # every ratio
    assert curve.capped and len(curve.ratios) == round(1 / step) - 1
    for epsilon in np.quantile(curve.errors, quantiles).tolist():
        bisection = phd.calibrate(renderer, cameras, epsilon=epsilon, step=step, samples=samples,
                                  method="bisection")
        assert bisection.r_drop == linear_answer(curve, epsilon) > 0
        assert bisection.method == "bisection"
        assert len(bisection.ratios) <= math.ceil(math.log2(len(curve.ratios) + 1))   # O(log K) probes
        assert set(bisection.ratios) <= set(curve.ratios)
        probes = dict(zip(curve.ratios, curve.errors))
        assert all(probes[r] == e for r, e in zip(bisection.ratios, bisection.errors))
    linear = phd.calibrate(renderer, cameras, epsilon=epsilon, step=step, samples=samples)
    assert linear.r_drop == linear_answer(curve, epsilon)


@pytest.mark.parametrize("compositing", ["over", "additive"])
@pytest.mark.parametrize("step", [0.1, 0.02])
def test_bisection_agrees_with_linear_scan(compositing: str, step: float) -> None:
    renderer = BlobRenderer.random(40, seed=1, compositing=compositing)
    if compositing == "additive":   # linear in the mask: error provably non-decreasing in r
        curve = phd.calibrate(renderer, CAMERAS[:2], epsilon=100.0, step=step, samples=4)
        assert all(a <= b for a, b in zip(curve.errors, curve.errors[1:]))
    assert_bisection_agrees(renderer, CAMERAS[:2], step, samples=4)


def test_grid_ratios_are_exact_decimals(blobs: BlobRenderer) -> None:
    result = phd.calibrate(blobs, CAMERAS[:2], epsilon=100.0, step=0.1, samples=2)
    assert result.ratios == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]
    assert result.r_drop == 0.9


@pytest.mark.parametrize("method", ["linear", "bisection"])
@pytest.mark.parametrize("renderer", [BlobRenderer.random(30, seed=0), EmptyRenderer()], ids=["blobs", "empty"])
def test_epsilon_that_everything_passes_is_capped_below_one(renderer, method: str) -> None:
    result = phd.calibrate(renderer, CAMERAS[:2], epsilon=10.0, step=0.3, samples=3, method=method)
    assert result.r_drop == 0.9 and result.capped
    assert result.warnings and "capped" in result.warnings[0]


@pytest.mark.parametrize("method", ["linear", "bisection"])
def test_r_drop_zero_raises_a_clear_error(blobs: BlobRenderer, method: str) -> None:
    with pytest.raises(phd.CalibrationError) as info:
        phd.calibrate(blobs, CAMERAS, epsilon=1e-4, step=0.05, samples=3, method=method)
    assert isinstance(info.value, InputError) and info.value.field == "epsilon"
    assert "not properly trained" in str(info.value) and "epsilon is too small" in str(info.value)
    assert info.value.ratios[0] == 0.05 and info.value.errors[0] >= 1e-4


@pytest.mark.parametrize("kwargs, field", [
    ({"epsilon": 0}, "epsilon"), ({"epsilon": -1}, "epsilon"), ({"epsilon": math.inf}, "epsilon"),
    ({"epsilon": math.nan}, "epsilon"), ({"step": 0}, "step"), ({"step": 1}, "step"), ({"step": 1e-6}, "step"),
    ({"samples": 0}, "samples"), ({"method": "golden"}, "method"), ({"seed": -2}, "seed"),
])
def test_calibration_arguments_are_validated(blobs: BlobRenderer, kwargs: dict, field: str) -> None:
    with pytest.raises(InputError) as info:
        phd.calibrate(blobs, CAMERAS[:1], **kwargs)
    assert info.value.field == field


def test_calibration_reports_progress_and_can_be_cancelled(blobs: BlobRenderer) -> None:
    seen: list[float] = []
    phd.calibrate(blobs, CAMERAS[:3], epsilon=0.03, samples=2, progress=seen.append)
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) > 3

    def cancel(fraction: float) -> None:
        if fraction > 0.2:
            raise KeyboardInterrupt

    renderer = BlobRenderer.random(40, seed=0)
    with pytest.raises(KeyboardInterrupt):
        phd.calibrate(renderer, CAMERAS[:3], epsilon=0.03, samples=2, progress=cancel)
    calls = renderer.calls
    assert calls < 3 * 6, "cancellation must stop the scan"


def test_ssim_criterion_matches_its_definition(blobs: BlobRenderer) -> None:
    cameras = CAMERAS[:3]
    images = torch.stack([blobs.render(c)[0] for c in cameras]) * 0.9 + 0.05   # ground truth near the model
    result = phd.calibrate_ssim(blobs, cameras, images, margin=0.05, step=0.1, samples=3, seed=4)
    assert result.method == "ssim" and result.epsilon == 0.05
    baseline = np.mean([float(ssim(blobs.render(c)[0], im)) for c, im in zip(cameras, images)])
    keep_all = phd.dropout_uniforms(blobs.num_units, 3, 4)
    for ratio, drop in zip(result.ratios, result.errors):
        scores = [float(ssim(blobs.render(c, (keep_all[j] >= ratio)[None])[0], im))
                  for c, im in zip(cameras, images) for j in range(3)]
        assert drop == pytest.approx((baseline - np.mean(scores)) / baseline, abs=1e-6)
    assert all(d < 0.05 for d in result.errors[:-1])
    assert result.capped or result.errors[-1] >= 0.05
    with pytest.raises(InputError) as info:
        phd.calibrate_ssim(blobs, cameras, images[:2])
    assert info.value.field == "images"


# ---------------------------------------------------------------------------------------- ranking

def test_sigma_max_ranking_orders_by_sigma_max_with_index_ties(blobs: BlobRenderer) -> None:
    cameras = [away_camera(), CAMERAS[0], CAMERAS[2], away_camera(), CAMERAS[0], CAMERAS[4]]
    ranked = phd.rank_views(blobs, cameras, ratio=0.4, samples=8, seed=1, strategy="sigma_max")
    views = phd.uncertainty(blobs, cameras, ratio=0.4, samples=8, seed=1)
    assert [r.rank for r in ranked] == list(range(1, 7))
    expected = sorted(range(6), key=lambda i: (-views[i].sigma_max, i))
    assert [r.index for r in ranked] == expected
    positions = {r.index: r.rank for r in ranked}
    assert positions[1] + 1 == positions[4]       # identical candidates: lower index first
    assert [r.index for r in ranked[-2:]] == [0, 3]   # seeing nothing: last, by index
    assert ranked[-1].sigma_max == 0.0
    assert [r.score for r in ranked] == [r.sigma_max for r in ranked]
    top = phd.rank_views(blobs, cameras, ratio=0.4, samples=8, seed=1, top_k=2, strategy="sigma_max")
    assert [r.index for r in top] == expected[:2]
    assert len(phd.rank_views(blobs, cameras, ratio=0.4, samples=8, seed=1, top_k=50)) == 6
    with pytest.raises(InputError) as info:
        phd.rank_views(blobs, cameras, ratio=0.4, top_k=0)
    assert info.value.field == "top_k"



def test_ranking_keeps_each_views_zeta_peak_from_one_render_per_candidate() -> None:
    blobs = BlobRenderer.random(40, seed=0)
    cameras = [CAMERAS[0], away_camera(), CAMERAS[2], CAMERAS[4]]
    ranked = phd.rank_views(blobs, cameras, ratio=0.4, samples=6, seed=3, top_k=3, keep_peak=True)
    assert blobs.calls == len(cameras)             # one batched render per candidate, none again for the maps
    for r in ranked:
        zeta = phd.view_uncertainty(blobs, cameras[r.index], ratio=0.4, samples=6, seed=3, keep_maps=True).zeta
        assert torch.equal(r.peak, zeta.amax(dim=-1))
        assert float(r.peak.max()) == pytest.approx(r.sigma_max, rel=1e-6)
        assert "peak" not in r.to_dict()
    assert all(r.peak is None for r in phd.rank_views(blobs, cameras, ratio=0.4, samples=6, seed=3))

# ---------------------------------------------------------------------------------------- selection

def test_paper_selection_picks_the_lower_mean_zeta(blobs: BlobRenderer) -> None:
    other = BlobRenderer.random(40, seed=6)
    result = phd.select_models(blobs, other, CAMERAS, ratio_a=0.3, ratio_b=0.3, samples=6, keep_images=True,
                               rule="sigma_mean")
    ua = phd.uncertainty(blobs, CAMERAS, ratio=0.3, samples=6)
    ub = phd.uncertainty(other, CAMERAS, ratio=0.3, samples=6)
    assert [v.score_a for v in result.views] == [v.sigma_mean for v in ua]
    assert [v.score_b for v in result.views] == [v.sigma_mean for v in ub]
    choices = ["a" if a.sigma_mean <= b.sigma_mean else "b" for a, b in zip(ua, ub)]
    assert [v.choice for v in result.views] == choices and len(set(choices)) == 2
    for view, camera in zip(result.views, CAMERAS):
        chosen = blobs if view.choice == "a" else other
        assert torch.equal(view.image, chosen.render(camera)[0])
    assert result.metrics is None
    tie = phd.select_models(blobs, blobs, CAMERAS[:2], ratio_a=0.3, ratio_b=0.3, samples=4, rule="sigma_mean")
    assert [v.choice for v in tie.views] == ["a", "a"] and tie.views[0].image is None


def test_selection_metrics_with_ground_truth(blobs: BlobRenderer) -> None:
    other = BlobRenderer.random(40, seed=6)
    truth = torch.stack([blobs.render(c)[0] for c in CAMERAS]) * 0.8 + 0.1
    result = phd.select_models(blobs, other, CAMERAS, ratio_a=0.3, ratio_b=0.3, samples=6, images=truth,
                               rule="sigma_mean")
    ratios, matches = [], []
    for view, camera, gt in zip(result.views, CAMERAS, truth):
        sa, sb = float(ssim(blobs.render(camera)[0], gt)), float(ssim(other.render(camera)[0], gt))
        ratios.append((sa if view.choice == "a" else sb) / max(sa, sb))
        matches.append(view.choice == ("a" if sa >= sb else "b"))
    m = result.metrics
    assert m["e_me"] == pytest.approx(np.mean(ratios), abs=1e-9) and m["e_me"] <= 1.0
    assert m["choice_matches_higher_ssim"] == pytest.approx(np.mean(matches))
    assert m["choices_a"] + m["choices_b"] == len(CAMERAS)
    expected_psnr_a = np.mean([psnr(blobs.render(c)[0], gt) for c, gt in zip(CAMERAS, truth)])
    assert m["psnr_a"] == pytest.approx(expected_psnr_a, abs=1e-9)
    expected_oracle = np.mean([max(psnr(blobs.render(c)[0], gt), psnr(other.render(c)[0], gt))
                               for c, gt in zip(CAMERAS, truth)])
    assert m["psnr_oracle"] == pytest.approx(expected_oracle, abs=1e-9)
    assert m["psnr_oracle"] >= max(m["psnr_a"], m["psnr_b"], m["psnr_selected"]) - 1e-9
    assert min(m["ssim_a"], m["ssim_b"]) <= m["ssim_selected"] + 1e-12


# ---------------------------------------------------------------------------------------- 3DGS

@pytest.fixture(scope="module")
def splats():
    from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer

    g = torch.Generator().manual_seed(0)
    count = 300
    model = GaussianModel(
        means=(torch.rand(count, 3, generator=g) * 2 - 1) * 0.8,
        log_scales=torch.rand(count, 3, generator=g) * 1.0 - 3.0,
        quats=torch.randn(count, 4, generator=g),
        opacity_logits=torch.randn(count, generator=g) + 1.0,
        sh=torch.randn(count, 1, 3, generator=g) * 0.5,
    )
    cameras = ring_cameras(4, size=24)
    return GaussianRenderer(model, training_cameras=cameras), cameras


def test_gaussian_zeta_matches_one_render_per_mask(splats) -> None:
    renderer, cameras = splats
    view = phd.view_uncertainty(renderer, cameras[0], ratio=0.3, samples=5, seed=2, keep_maps=True)
    keep = phd.dropout_uniforms(renderer.num_units, 5, 2) >= 0.3
    renders = torch.cat([renderer.render(cameras[0], k[None]) for k in keep]).double()
    np.testing.assert_allclose(view.zeta.numpy(), renders.std(0).numpy(), atol=1e-5)
    assert view.sigma_max > 0.05


def test_gaussian_extremes(splats) -> None:
    renderer, cameras = splats
    zero = phd.view_uncertainty(renderer, cameras[0], ratio=0.0, samples=4, keep_maps=True)
    assert torch.count_nonzero(zero.zeta) == 0
    everything = phd.view_uncertainty(renderer, cameras[0], ratio=1.0, samples=4, keep_maps=True)
    assert everything.sigma_max == 0.0
    assert torch.equal(everything.mean, torch.ones(24, 24, 3))   # all splats dropped: the white background
    nearly = phd.view_uncertainty(renderer, cameras[0], ratio=0.99, samples=4, keep_maps=True)
    assert torch.isfinite(nearly.zeta).all()
    assert phd.view_uncertainty(renderer, away_camera(24), ratio=0.5, samples=4).sigma_max == 0.0


def test_gaussian_float32_accumulation_agrees(splats) -> None:
    renderer, cameras = splats
    a = phd.uncertainty(renderer, cameras, ratio=0.3, samples=16, dtype=torch.float64)
    b = phd.uncertainty(renderer, cameras, ratio=0.3, samples=16, dtype=torch.float32)
    assert abs(phd.sigma_max_bar(a) - phd.sigma_max_bar(b)) < 1e-5


def test_gaussian_bisection_agrees_with_linear(splats) -> None:
    renderer, cameras = splats
    assert_bisection_agrees(renderer, renderer.training_cameras[:2], step=0.1, samples=4, quantiles=(0.25, 0.75))


# ------------------------------------------------------------------------ a real trained 3DGS model

@pytest.fixture(scope="module")
def lego(tmp_path_factory):
    """A trained 3DGS model: 200 steps on 8 lego views at 25 x 25 (about 10 s), and test poses."""
    from phd_core.data import load_dataset
    from phd_core.train.gs3d import train_gaussians

    out = tmp_path_factory.mktemp("lego") / "model.ply"
    renderer = train_gaussians(LEGO, views=8, downscale=8, iterations=200, out=out, progress=False)
    return renderer, load_dataset(LEGO, "test", views=6, downscale=8, with_images=False).cameras


def test_real_model_float32_accumulation_agrees(lego) -> None:
    renderer, test_cameras = lego
    a = phd.uncertainty(renderer, test_cameras, ratio=0.3, samples=16, dtype=torch.float64)
    b = phd.uncertainty(renderer, test_cameras, ratio=0.3, samples=16, dtype=torch.float32)
    assert phd.sigma_max_bar(a) > 0.01                  # a real signal, not an all-zero map
    assert abs(phd.sigma_max_bar(a) - phd.sigma_max_bar(b)) < 1e-5


def test_real_model_calibrates_and_bisection_agrees(lego) -> None:
    renderer, _ = lego
    default = phd.calibrate(renderer, renderer.training_cameras)    # engine defaults, stored poses
    assert 0 < default.r_drop < 1 and not default.capped
    assert phd.calibrate(renderer, renderer.training_cameras, method="bisection").r_drop == default.r_drop
    assert_bisection_agrees(renderer, renderer.training_cameras, step=0.05, samples=4)


# ---------------------------------------------------------------------------------------- NeRF

@pytest.fixture(scope="module")
def tiny_nerf():
    from phd_core.renderers.nerf import NeRFConfig, NeRFRenderer, RadianceField

    config = NeRFConfig(depth=2, width=16, color_width=8, pos_freqs=3, dir_freqs=1, samples=12,
                        grid_resolution=8, bounds=[[-1, -1, -1], [1, 1, 1]], near=1.0, far=6.0)
    return NeRFRenderer(RadianceField(config, seed=0), use_grid=False)


def test_nerf_through_the_same_engine(tiny_nerf) -> None:
    camera = ring_cameras(1, size=8)[0]
    view = phd.view_uncertainty(tiny_nerf, camera, ratio=0.4, samples=4, seed=1, keep_maps=True)
    keep = phd.dropout_uniforms(tiny_nerf.num_units, 4, 1) >= 0.4
    renders = torch.cat([tiny_nerf.render(camera, k[None]) for k in keep]).double()
    np.testing.assert_allclose(view.zeta.numpy(), renders.std(0).numpy(), atol=1e-5)
    assert view.sigma_max > 0
    assert torch.count_nonzero(phd.view_uncertainty(tiny_nerf, camera, ratio=0.0, samples=3, keep_maps=True).zeta) == 0
    everything = phd.view_uncertainty(tiny_nerf, camera, ratio=1.0, samples=3, keep_maps=True)
    assert everything.sigma_max == 0.0 and torch.isfinite(everything.mean).all()   # no units: one finite render


def test_other_aggregations_of_zeta_match_their_definition(blobs: BlobRenderer) -> None:
    from phd_core.uq.uncertainty import AREA_THRESHOLD, TOP_SHARE

    view = phd.view_uncertainty(blobs, CAMERAS[0], ratio=0.4, samples=8, seed=3, keep_maps=True)
    per_pixel = np.sort(view.zeta.double().amax(-1).flatten().numpy())[::-1]
    count = max(1, round(TOP_SHARE * per_pixel.size))
    assert view.sigma_top == pytest.approx(per_pixel[:count].mean(), rel=1e-6)
    assert view.area == pytest.approx((per_pixel > AREA_THRESHOLD).mean(), abs=1.5 / per_pixel.size)
    assert view.sigma_mean <= view.sigma_top <= view.sigma_max and 0 < view.area < 1
    still = phd.view_uncertainty(ConstantRenderer(), CAMERAS[0], ratio=0.4, samples=4)
    assert (still.sigma_top, still.area) == (0.0, 0.0)
