"""Next-best-view strategies: one module per family, one registry entry per strategy.

`STRATEGIES` maps a name to a `Strategy`; the CLI, the REST schema and the client take
their allowed names from it. Adding a strategy is one module plus one `STRATEGIES.register`
call.
"""

from __future__ import annotations

from ...registry import Registry
from .base import Evidence, Selection, Strategy
from .baselines import FVS, RANDOM
from .fisher import FISHER
from .hybrid import FVS_SIGMA, FVS_SIGMA_FLOOR
from .uncertainty import SIGMA_MAX, SIGMA_MEAN
from .visibility import VISIBILITY, VISIBILITY_SIGMA, VISIBILITY_SIGMA_FVS

STRATEGIES: Registry[Strategy] = Registry("strategy")
for _strategy in (SIGMA_MAX, SIGMA_MEAN, RANDOM, FVS, FVS_SIGMA, FVS_SIGMA_FLOOR, VISIBILITY, VISIBILITY_SIGMA,
                  VISIBILITY_SIGMA_FVS, FISHER):
    STRATEGIES.register(_strategy)

DEFAULT_STRATEGY = "visibility_sigma_fvs"   # the best over the four scenes of docs/nbv.md, ahead of FVS on each
CHEAPER_STRATEGY = "fvs_sigma_floor"        # what the visibility strategies fall back to: no visibility to keep
# Which strategy for which capture, as the real family measured it (docs/nbv.md, "Real captures"): said by
# `phd rank --help` (the README and docs/nbv.md say the same).
STRATEGY_ADVICE = (
    "Measured on five real captures (docs/nbv.md, 'Real captures': 15 capture-seed pairs, 6 views added, final "
    "test PSNR, mean [95 percent bootstrap interval]): told the capture's own frames as --targets, the default "
    "leads fvs by 0.51 dB [-0.03, 1.10] and random by 0.32 [-0.11, 0.73]; untargeted, by 0.37 [-0.09, 0.91] "
    "and 0.18 [-0.39, 0.71]: no lead shown above 0. Use the default on objects photographed all round; add "
    "--targets (the frames of the path) when the model will be looked at along the capture's path (a walk); on "
    "the one drone flight random was best, 1.3 dB above the default, and in the one room fvs, 0.2 dB above it.")


def get_strategy(name: str) -> Strategy:
    """The registered strategy called `name`, or an InputError listing the known names."""
    return STRATEGIES.lookup(name, "strategy")


__all__ = ["CHEAPER_STRATEGY", "DEFAULT_STRATEGY", "STRATEGIES", "STRATEGY_ADVICE",
           "Evidence", "Selection", "Strategy", "get_strategy"]
