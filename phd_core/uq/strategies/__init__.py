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


def get_strategy(name: str) -> Strategy:
    """The registered strategy called `name`, or an InputError listing the known names."""
    return STRATEGIES.lookup(name, "strategy")


__all__ = ["CHEAPER_STRATEGY", "DEFAULT_STRATEGY", "STRATEGIES", "Evidence", "Selection", "Strategy", "get_strategy"]
