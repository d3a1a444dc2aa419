"""The table of exploration strategies: one row per ``explore=`` value, no JAX.

Each row names the strategy's on-policy class (A2C/PPO) and off-policy behaviour (SAC)
as ``"module:Class"`` strings under ``coherent_jax.exploration`` (imported on first
use by `coherent_jax.exploration.make_strategy` / ``make_behaviour``), and, for every
algorithm it does not run with, the one-line reason it is refused. The config's
choices (``explore``), the algorithms each strategy runs with and the refusals are
derived from this table, so adding a strategy is its module, one row here and its
tests (``docs/strategies.md``, "Adding a strategy").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

ALGOS = ("ppo", "a2c", "sac")
ON_POLICY = ("ppo", "a2c")


@dataclasses.dataclass(frozen=True)
class Strategy:
    """One exploration strategy.

    Attributes:
      name: its ``explore=`` value.
      on_policy: ``"module:Class"`` of its `OnPolicyStrategy` (A2C, PPO); None if it has none.
      off_policy: ``"module:Class"`` of its `OffPolicyBehaviour` (SAC); None if it has none.
      refused: algorithm -> the one-line reason it does not run with it (every algorithm
        without a class needs one).
      variants: on-policy ablations chosen by sub-options (`coherent_jax.exploration.strategy_name`),
        variant name -> ``"module:Class"``.
    """

    name: str
    on_policy: str | None
    off_policy: str | None
    refused: Mapping[str, str] = dataclasses.field(default_factory=dict)
    variants: Mapping[str, str] = dataclasses.field(default_factory=dict)

    @property
    def algos(self) -> tuple[str, ...]:
        """The algorithms it runs with, in `ALGOS` order."""
        return tuple(
            a
            for a in ALGOS
            if (self.on_policy if a in ON_POLICY else self.off_policy) and a not in self.refused
        )


_NOISYNET_SAC = "noisynet's learned noise scales need an on-policy algorithm's score-function gradient"

STRATEGIES: tuple[Strategy, ...] = (
    Strategy("action", "action:ActionNoise", "base:OffPolicyBehaviour"),
    Strategy(
        "coherent",
        "coherent.strategy:CoherentExploration",
        "coherent.strategy:CoherentBehaviour",
        variants={"coherent-mc": "coherent.mc:CoherentMC", "coherent-all": "coherent.mc:CoherentAllLayers"},
    ),
    Strategy("noisynet", "noisynet:NoisyNet", None, refused={"sac": _NOISYNET_SAC}),
    Strategy("psne", "psne:ParameterNoise", "psne:PsneBehaviour"),
    Strategy("gsde", "gsde:GeneralizedSDE", "gsde:GsdeBehaviour"),
    Strategy("pink", "pink:PinkNoise", "pink:PinkBehaviour"),
    Strategy("lattice", "lattice:Lattice", "lattice:LatticeBehaviour"),
)
BY_NAME: Mapping[str, Strategy] = {s.name: s for s in STRATEGIES}

# Derived views (what the config and its checks read).
EXPLORES: tuple[str, ...] = tuple(BY_NAME)
SUPPORTED_ALGOS: Mapping[str, tuple[str, ...]] = {s.name: s.algos for s in STRATEGIES}
REFUSED: Mapping[tuple[str, str], str] = {
    (s.name, a): why for s in STRATEGIES for a, why in s.refused.items()
}
ON_POLICY_CLASSES: Mapping[str, str] = {
    **{s.name: s.on_policy for s in STRATEGIES if s.on_policy},
    **{v: cls for s in STRATEGIES for v, cls in s.variants.items()},
}
OFF_POLICY_CLASSES: Mapping[str, str] = {s.name: s.off_policy for s in STRATEGIES if s.off_policy}


def check_table() -> None:
    """Every algorithm a strategy does not run with has a reason (a test calls this)."""
    for s in STRATEGIES:
        for algo in ALGOS:
            has_class = s.on_policy if algo in ON_POLICY else s.off_policy
            if not has_class and algo not in s.refused:
                raise AssertionError(f"strategy {s.name!r} has no class for {algo} and no reason for it")
