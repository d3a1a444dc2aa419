"""How a config field is declared: its metadata, the ranges, the sweepable marker.

A field declares everything about itself in its metadata: the one-line help
(``--help``), the allowed values (``choices``) or range (``check``: a predicate and the
text of what it allows), the help section of a top-level field (``group``), for a
sweepable scalar a `Sweepable`, and the text of the allowed values where they are no
fixed list (``allowed``: the env's). The keys a setting had before are
`coherent_jax.config.legacy`'s. `coherent_jax.config.checks`
validates from these declarations. No JAX here.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

from coherent_jax.strategies import ALGOS, EXPLORES, ON_POLICY


@dataclasses.dataclass(frozen=True)
class Sweepable:
    """Marks a scalar that lives in the train state as an array, so a vmapped sweep may vary it.

    Attributes:
      reads: the (algos, explores) pairs whose train state holds it; a sweep axis
        for any other pair would run identical points and is refused.
      hparam: its typed path in the trainer's hyperparameters, field names joined by dots
        (e.g. ``explore.beta``: the strategy's own dataclass), when that is not the key's
        last part (a field of the trainer's own).
    """

    reads: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...]
    hparam: str | None = None

    def read_by(self, algo: str, explore: str) -> bool:
        return any(algo in algos and explore in explores for algos, explores in self.reads)


# --- declared ranges: (predicate, what is allowed)
Check = tuple[Callable[[Any], bool], str]


def number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


POSITIVE: Check = (lambda v: number(v) and v > 0, "a finite number > 0")
NON_NEGATIVE: Check = (lambda v: number(v) and v >= 0, "a finite number >= 0")
UNIT: Check = (lambda v: number(v) and 0.0 <= v <= 1.0, "a number in [0, 1]")


def at_least(low: int, allowed: str | None = None, below: int | None = None) -> Check:
    """An integer >= ``low`` (and < ``below``, if given)."""
    return (
        lambda v: v >= low and (below is None or v < below),
        allowed or f"an integer >= {low}",
    )


COUNT = at_least(1, below=2**31)  # sizes and counts held in int32 counters
LAYERS: Check = (lambda v: len(v) >= 1 and all(n >= 1 for n in v), "a list of ints >= 1")


def field(
    default: Any,
    help: str,
    *,
    group: str | None = None,
    check: Check | None = None,
    choices: tuple[Any, ...] | None = None,
    sweep: Sweepable | None = None,
    allowed: str | None = None,
) -> Any:
    """A config field with its help and declarations (see the module's docstring)."""
    metadata: dict[str, Any] = {"help": help}
    for name, value in (
        ("group", group),
        ("check", check),
        ("choices", choices),
        ("sweep", sweep),
        ("allowed", allowed),
    ):
        if value is not None:
            metadata[name] = value
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def sweep(*reads: tuple[tuple[str, ...], tuple[str, ...]], hparam: str | None = None) -> Sweepable:
    return Sweepable(reads=tuple(reads), hparam=hparam)


EVERY = (ALGOS, EXPLORES)
ON_POLICY_ALL = (ON_POLICY, EXPLORES)
SAC_ALL = (("sac",), EXPLORES)
# The adaptive-sigma rule (4.50)-(4.51): PSNE's with every algorithm (sigma itself is in the
# state with SAC only: on-policy it is per-env state), Coherent-SAC's for its chain's scale.
PSNE_SAC = (("sac",), ("psne",))
SIGMA_RULE = (PSNE_SAC, (ON_POLICY, ("psne",)))
COHERENT_SAC = (("sac",), ("coherent",))


class Group:
    """A group's ``__str__``: ``{key=value,...}``, as a log line shows it."""

    def __str__(self) -> str:
        return "{" + ",".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self)) + "}"
