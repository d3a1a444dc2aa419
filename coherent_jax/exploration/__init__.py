"""Exploration strategies: one module per strategy, two small interfaces (`base`).

Each class reads its own settings (``from_config``). The classes are registered by class
in `coherent_jax.agents.registry` (a layer above this package and `exploration/coherent/`,
as it imports both), whose `make_strategy` builds the on-policy strategy (A2C/PPO) and
`make_behaviour` the off-policy behaviour (SAC) named by ``cfg.explore``; the names the
config validates without JAX are `coherent_jax.strategies`. Adding a strategy never
changes an algorithm: it is its module, one registry row (with its name in the JAX-free
names), its settings group and its tests (docs/strategies.md, "Adding a strategy").
"""

from __future__ import annotations

from coherent_jax.exploration.base import (
    ActOutput,
    OffPolicyBehaviour,
    OnPolicyStrategy,
    Segment,
    SegmentLogProb,
)

__all__ = [
    "ActOutput",
    "OffPolicyBehaviour",
    "OnPolicyStrategy",
    "Segment",
    "SegmentLogProb",
]
