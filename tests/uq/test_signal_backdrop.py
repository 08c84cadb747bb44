"""The uncertainty definitions (signals) through the engine: on premultiplied colour plus
alpha, r_drop, the error curve and zeta of one model do not depend on the backdrop; on the
composited colour (the paper's) they do."""

from __future__ import annotations

import pytest
import torch

from phd_core import uq
from phd_core.errors import InputError
from phd_core.renderers.gs3d import GaussianModel, GaussianRenderer
from phd_core.scene import look_at
from support.toy_renderers import ConstantRenderer, ring_cameras

BACKDROPS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5)}


def model() -> GaussianModel:
    gen = torch.Generator().manual_seed(11)
    g = 300
    return GaussianModel(means=(torch.rand(g, 3, generator=gen) * 2 - 1) * 0.6,
                         log_scales=torch.rand(g, 3, generator=gen) * 1.0 - 3.0,
                         quats=torch.randn(g, 4, generator=gen), opacity_logits=torch.randn(g, generator=gen) + 1,
                         sh=torch.randn(g, 1, 3, generator=gen) * 0.3)


def cameras(count: int, phase: float = 0.0):
    return [look_at((3 * torch.cos(torch.tensor(a)).item(), 3 * torch.sin(torch.tensor(a)).item(), 1.0), (0, 0, 0),
                    width=24, height=18, fov_x=0.8) for a in [phase + 6.283 * k / count for k in range(count)]]


@pytest.mark.parametrize("signal", ["composited", "premultiplied"])
def test_premultiplied_measures_are_the_same_over_every_backdrop(signal: str) -> None:
    splats, training, views = model(), cameras(4), cameras(3, phase=0.4)
    calibrations, zetas = {}, {}
    for name, colour in BACKDROPS.items():
        renderer = GaussianRenderer(splats, colour, training)
        calibrations[name] = uq.calibrate(renderer, training, epsilon=0.03, step=0.1, samples=3, signal=signal)
        zetas[name] = uq.uncertainty(renderer, views, ratio=0.3, samples=4, keep_maps=True, signal=signal)
    assert all(c.signal == signal and c.to_dict()["signal"] == signal for c in calibrations.values())
    errors = {name: torch.tensor(c.errors[:2]) for name, c in calibrations.items()}   # every run tests 0.1 and 0.2
    sigma = {name: torch.tensor([v.sigma_max for v in views]) for name, views in zetas.items()}
    channels = {name: views[0].zeta.shape[-1] for name, views in zetas.items()}
    if signal == "premultiplied":
        assert set(channels.values()) == {4}
        assert len({c.r_drop for c in calibrations.values()}) == 1
        for name in BACKDROPS:
            assert torch.allclose(errors[name], errors["grey"], rtol=0, atol=1e-6)
            assert torch.allclose(sigma[name], sigma["grey"], rtol=0, atol=1e-6)
            for a, b in zip(zetas[name], zetas["grey"]):
                assert (a.zeta - b.zeta).abs().max() <= 1e-6
    else:
        assert set(channels.values()) == {3}
        assert (errors["white"] - errors["black"]).abs().max() > 1e-4       # far above float noise
        assert (sigma["white"] - sigma["black"]).abs().max() > 1e-3


def test_identical_renders_give_a_std_of_exactly_zero_on_every_signal() -> None:
    for signal in ("composited", "premultiplied"):
        view = uq.view_uncertainty(ConstantRenderer(), ring_cameras(1, size=9)[0], ratio=0.5, samples=5,
                                   keep_maps=True, signal=signal)
        assert view.sigma_max == 0.0 and view.sigma_mean == 0.0 and not view.zeta.any()


def test_an_unknown_signal_is_refused_naming_the_field() -> None:
    renderer = GaussianRenderer(model(), training_cameras=cameras(2))
    for call in (lambda: uq.calibrate(renderer, cameras(2), signal="straight"),
                 lambda: uq.uncertainty(renderer, cameras(1), ratio=0.2, signal="straight"),
                 lambda: uq.rank_views(renderer, cameras(2), ratio=0.2, signal=None)):
        with pytest.raises(InputError) as info:
            call()
        assert info.value.field == "signal"
