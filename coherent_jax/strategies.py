"""The names of the exploration strategies and their refusals, without JAX.

This is what the config validates against (its ``explore`` choices, the algorithms each
strategy runs with and the one-line reason for each it does not) and what the
experiments enumerate, so it must load without JAX. The classes are registered by
class in `coherent_jax.agents.registry`, one row per name here; a test keeps the
two equal (`coherent_jax.agents.registry.check_registry`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

ALGOS = ("ppo", "a2c", "sac")
ON_POLICY = ("ppo", "a2c")


@dataclasses.dataclass(frozen=True)
class Strategy:
    """One exploration strategy, as the config sees it.

    Attributes:
      name: its ``explore=`` value.
      refused: algorithm -> the one-line reason it does not run with it; it runs with
        every other algorithm of `ALGOS`.
      variants: on-policy ablations chosen by sub-options, variant name -> the
        ``key=value`` settings that choose it (with ``explore=NAME``).
    """

    name: str
    refused: Mapping[str, str] = dataclasses.field(default_factory=dict)
    variants: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)

    @property
    def algos(self) -> tuple[str, ...]:
        """The algorithms it runs with, in `ALGOS` order."""
        return tuple(a for a in ALGOS if a not in self.refused)


_NOISYNET_SAC = "noisynet's learned noise scales need an on-policy algorithm's score-function gradient"

STRATEGIES: tuple[Strategy, ...] = (
    Strategy("action"),
    Strategy(
        "coherent",
        variants={
            "coherent-mc": ("coherent.integration=mc",),
            "coherent-all": ("coherent.integration=mc", "coherent.layers=all"),
        },
    ),
    Strategy("noisynet", refused={"sac": _NOISYNET_SAC}),
    Strategy("psne"),
    Strategy("gsde"),
    Strategy("pink"),
    Strategy("lattice"),
)

# Derived views (what the config and its checks read).
EXPLORES: tuple[str, ...] = tuple(s.name for s in STRATEGIES)
SUPPORTED_ALGOS: Mapping[str, tuple[str, ...]] = {s.name: s.algos for s in STRATEGIES}
REFUSED: Mapping[tuple[str, str], str] = {
    (s.name, a): why for s in STRATEGIES for a, why in s.refused.items()
}


def overrides(name: str) -> tuple[str, ...]:
    """The settings that choose strategy or variant ``name``: ``("explore=psne",)``,
    ``("explore=coherent", "coherent.integration=mc")``; ValueError for another name."""
    for s in STRATEGIES:
        if name == s.name:
            return (f"explore={s.name}",)
        if name in s.variants:
            return (f"explore={s.name}", *s.variants[name])
    valid = [n for s in STRATEGIES for n in (s.name, *s.variants)]
    raise ValueError(f"unknown strategy {name!r}; valid: {', '.join(valid)}")


def on_policy_names() -> tuple[str, ...]:
    """Every on-policy strategy and variant, each strategy followed by its variants."""
    return tuple(n for s in STRATEGIES if set(ON_POLICY) - set(s.refused) for n in (s.name, *s.variants))
