"""The strategy registry: each ``explore=`` value's classes, registered by class.

It sits with the algorithms that build the strategies, above `exploration/` and
`exploration/coherent/`, whose classes it imports.

One row per strategy: its on-policy class (A2C/PPO), its off-policy behaviour (SAC),
and the on-policy ablations its sub-options choose (`strategy_name`). The names and the
refusals the config validates without JAX are `coherent_jax.strategies`;
`check_registry` keeps the two equal: a row per name, in the same order, a class for
every algorithm the strategy is not refused, and none for an algorithm it is.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from coherent_jax import strategies
from coherent_jax.exploration.action import ActionNoise
from coherent_jax.exploration.base import OffPolicyBehaviour, OnPolicyStrategy
from coherent_jax.exploration.coherent.mc import CoherentAllLayers, CoherentMC
from coherent_jax.exploration.coherent.strategy import CoherentBehaviour, CoherentExploration
from coherent_jax.exploration.gsde import GeneralizedSDE, GsdeBehaviour
from coherent_jax.exploration.lattice import Lattice, LatticeBehaviour
from coherent_jax.exploration.noisynet import NoisyNet
from coherent_jax.exploration.pink import PinkBehaviour, PinkNoise
from coherent_jax.exploration.psne import ParameterNoise, PsneBehaviour


@dataclasses.dataclass(frozen=True)
class Registered:
    """One strategy's classes.

    Attributes:
      name: its ``explore=`` value (a name of `coherent_jax.strategies.EXPLORES`).
      on_policy: its `OnPolicyStrategy` (A2C, PPO), or None if it refuses both.
      off_policy: its `OffPolicyBehaviour` (SAC), or None if it refuses SAC.
      variants: on-policy ablations chosen by sub-options, variant name -> class.
    """

    name: str
    on_policy: type[OnPolicyStrategy] | None
    off_policy: type[OffPolicyBehaviour] | None
    variants: Mapping[str, type[OnPolicyStrategy]] = dataclasses.field(default_factory=dict)


REGISTRY: tuple[Registered, ...] = (
    Registered("action", ActionNoise, OffPolicyBehaviour),
    Registered(
        "coherent",
        CoherentExploration,
        CoherentBehaviour,
        variants={"coherent-mc": CoherentMC, "coherent-all": CoherentAllLayers},
    ),
    Registered("noisynet", NoisyNet, None),
    Registered("psne", ParameterNoise, PsneBehaviour),
    Registered("gsde", GeneralizedSDE, GsdeBehaviour),
    Registered("pink", PinkNoise, PinkBehaviour),
    Registered("lattice", Lattice, LatticeBehaviour),
)


def on_policy_classes(registry: tuple[Registered, ...] | None = None) -> dict[str, type[OnPolicyStrategy]]:
    """Strategy and ablation name -> on-policy class (of `REGISTRY` by default)."""
    registry = REGISTRY if registry is None else registry
    return {
        **{r.name: r.on_policy for r in registry if r.on_policy},
        **{v: cls for r in registry for v, cls in r.variants.items()},
    }


def off_policy_classes(registry: tuple[Registered, ...] | None = None) -> dict[str, type[OffPolicyBehaviour]]:
    """Strategy name -> off-policy (SAC) behaviour class (of `REGISTRY` by default)."""
    registry = REGISTRY if registry is None else registry
    return {r.name: r.off_policy for r in registry if r.off_policy}


def check_registry(
    registry: tuple[Registered, ...] | None = None, table: tuple[strategies.Strategy, ...] | None = None
) -> None:
    """`REGISTRY` and the JAX-free `coherent_jax.strategies.STRATEGIES` agree (a test calls
    this); AssertionError naming the row that does not."""
    registry = REGISTRY if registry is None else registry
    table = strategies.STRATEGIES if table is None else table
    names, expected = tuple(r.name for r in registry), tuple(s.name for s in table)
    if names != expected:
        raise AssertionError(f"registry names {names} differ from coherent_jax.strategies' {expected}")
    for r, s in zip(registry, table, strict=True):
        for algo in strategies.ALGOS:
            cls = r.on_policy if algo in strategies.ON_POLICY else r.off_policy
            base = OnPolicyStrategy if algo in strategies.ON_POLICY else OffPolicyBehaviour
            if (cls is None) != (algo in s.refused):
                raise AssertionError(f"strategy {r.name!r}: a class for {algo} iff it is not refused")
            if cls is not None and not issubclass(cls, base):
                raise AssertionError(f"strategy {r.name!r}: {cls.__name__} is not an {base.__name__}")
        if tuple(r.variants) != tuple(s.variants):
            raise AssertionError(
                f"strategy {r.name!r}: variants {tuple(r.variants)} differ from {tuple(s.variants)}"
            )


def strategy_name(cfg) -> str:
    """The on-policy strategy of ``cfg``: ``cfg.explore``, or a coherent ablation (thesis §5)."""
    if cfg.explore == "coherent" and cfg.coherent.layers == "all":
        return "coherent-all"
    if cfg.explore == "coherent" and cfg.coherent.integration == "mc":
        return "coherent-mc"
    return cfg.explore


def _lookup(table: Mapping[str, type], name: str, kind: str) -> type:
    if name not in table:
        raise ValueError(f"unknown {kind} explore {name!r}; valid: {', '.join(sorted(table))}")
    return table[name]


def make_strategy(cfg, action_size: int) -> OnPolicyStrategy:
    """The on-policy strategy named by ``cfg``, built for ``action_size`` actions."""
    return _lookup(on_policy_classes(), strategy_name(cfg), "on-policy").from_config(cfg, action_size)


def make_behaviour(cfg, action_size: int) -> OffPolicyBehaviour:
    """The off-policy (SAC) behaviour named by ``cfg.explore``."""
    return _lookup(off_policy_classes(), cfg.explore, "off-policy").from_config(cfg, action_size)
