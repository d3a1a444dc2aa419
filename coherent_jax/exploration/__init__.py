"""Exploration strategies: one module per strategy, two small interfaces (`base`).

`make_strategy` builds the on-policy strategy (A2C/PPO) and `make_behaviour` the
off-policy behaviour (SAC) named by ``cfg.explore``. Each class reads its own settings
(``from_config``); the classes are named in the strategy table (`coherent_jax.strategies`),
so adding a strategy is a module and a row there, never a change to an algorithm.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping

from coherent_jax.exploration.base import (
    ActOutput,
    OffPolicyBehaviour,
    OnPolicyStrategy,
    Segment,
    SegmentLogProb,
)
from coherent_jax.strategies import OFF_POLICY_CLASSES, ON_POLICY_CLASSES

# explore name (and ablation variant) -> "module:Class", from the strategy table.
_ON_POLICY = ON_POLICY_CLASSES
_OFF_POLICY = OFF_POLICY_CLASSES


def _load(table: Mapping[str, str], name: str, kind: str):
    if name not in table:
        raise ValueError(f"unknown {kind} explore {name!r}; valid: {', '.join(sorted(table))}")
    module, cls = table[name].split(":")
    return getattr(importlib.import_module(f"coherent_jax.exploration.{module}"), cls)


def strategy_name(cfg) -> str:
    """The on-policy strategy of ``cfg``: ``cfg.explore``, or a coherent ablation (thesis §5)."""
    if cfg.explore == "coherent" and cfg.coherent.layers == "all":
        return "coherent-all"
    if cfg.explore == "coherent" and cfg.coherent.integration == "mc":
        return "coherent-mc"
    return cfg.explore


def make_strategy(cfg, action_size: int) -> OnPolicyStrategy:
    """The on-policy strategy named by ``cfg``, built for ``action_size`` actions."""
    return _load(_ON_POLICY, strategy_name(cfg), "on-policy").from_config(cfg, action_size)


def make_behaviour(cfg, action_size: int) -> OffPolicyBehaviour:
    """The off-policy (SAC) behaviour named by ``cfg.explore``."""
    return _load(_OFF_POLICY, cfg.explore, "off-policy").from_config(cfg, action_size)


__all__ = [
    "ActOutput",
    "OffPolicyBehaviour",
    "OnPolicyStrategy",
    "Segment",
    "SegmentLogProb",
    "make_behaviour",
    "make_strategy",
    "strategy_name",
]
