"""Exploration strategies: one module per strategy, two small interfaces (`base`).

`make_strategy` builds the on-policy strategy (A2C/PPO) and `make_behaviour` the
off-policy behaviour (SAC) named by ``cfg.explore``. Each class reads its own settings
(``from_config``), so adding a strategy is a module and a line in each table below,
never a change to an algorithm.
"""

from __future__ import annotations

import importlib

from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour, OnPolicyStrategy, SegmentLogProb

# explore name -> "module:Class", imported on first use.
_ON_POLICY = {
    "action": "action:ActionNoise",
    "coherent": "coherent:CoherentExploration",
    "coherent-mc": "coherent_mc:CoherentMC",
    "coherent-all": "coherent_mc:CoherentAllLayers",
    "noisynet": "noisynet:NoisyNet",
    "psne": "psne:ParameterNoise",
    "gsde": "gsde:GeneralizedSDE",
    "pink": "pink:PinkNoise",
}
_OFF_POLICY = {
    "action": "base:OffPolicyBehaviour",
    "coherent": "coherent:CoherentBehaviour",
    "psne": "psne:PsneBehaviour",
    "gsde": "gsde:GsdeBehaviour",
    "pink": "pink:PinkBehaviour",
}


def _load(table: dict[str, str], name: str, kind: str):
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
    "SegmentLogProb",
    "make_behaviour",
    "make_strategy",
    "strategy_name",
]
