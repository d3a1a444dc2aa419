"""Typed, validated run configuration with ``key=value`` overrides; no JAX.

The configuration is one dataclass (`Config`, `coherent_jax.config.schema`): the
settings every run reads at the top level, an algorithm's or a strategy's own in a
group (``ppo.*``, ``sac.*``, ``coherent.*``, ``coherent_sac.*``, ``noisynet.*``, ``psne.*``,
``gsde.*``, ``pink.*``, ``lattice.*``; `coherent_jax.config.groups`). Every field declares
its help, its range or choices and, for a sweepable scalar, a `Sweepable` saying which (algo, explore) pairs
hold it in the train state (`coherent_jax.config.groups`); the defaults of an algorithm and
the presets are layered over `Config`'s (`coherent_jax.config.schema`); validation is derived
from the declarations plus a few named cross-field checks (`coherent_jax.config.checks`).
Overrides are parsed, and stored configs read, by `coherent_jax.config.parse`; the keys
of before (the flat ``clip_eps``, Coherent-SAC's ``psne.*``) and what they are now
(``ppo.clip_eps``, ``coherent_sac.*``) are `coherent_jax.config.parse`'s, all of them.
The ``key=value`` parser every command shares, its own keys beside the config's, is
`coherent_jax.config.cli`.

Shape-determining settings (``num_envs``, ``unroll_length``, network sizes, ...) are
static Python values; the sweepable scalars (`SWEEPABLE`) become arrays inside the
train state so that `jax.vmap` can run a grid of them as one program.
"""

from typing import Any

from coherent_jax.compat import warn_once
from coherent_jax.config.checks import CROSS_CHECKS, ConfigError, validate
from coherent_jax.config.groups import (
    COHERENT_GRADIENT,
    COHERENT_INFERENCE,
    COHERENT_INTEGRATION,
    COHERENT_LAYERS,
    CoherentOptions,
    CoherentSACOptions,
    GsdeOptions,
    LatticeOptions,
    NoisyNetOptions,
    PinkOptions,
    PPOOptions,
    PsneOptions,
    SACOptions,
    Sweepable,
)
from coherent_jax.config.parse import (
    COHERENT_SAC_KEYS,
    LEGACY_KEYS,
    flat_dict,
    from_stored,
    help_text,
    make_config,
    modern_items,
    modern_key,
    override_items,
    overrides_of,
    parse_overrides,
    to_dict,
    upgrade_stored,
)
from coherent_jax.config.schema import (
    ACTIVATIONS,
    FIELDS,
    GROUPS,
    SECTIONS,
    SWEEPABLE,
    Config,
    get_value,
    hparam_path,
    sweepable,
    with_values,
)
from coherent_jax.strategies import ALGOS, EXPLORES, ON_POLICY, REFUSED, SUPPORTED_ALGOS


def _from_overrides(cls: type[Config], mapping: Any = None, /, **keys: Any) -> Config:
    """Deprecated (removed in 0.3): `make_config`, which takes the same arguments."""
    warn_once("coherent_jax.Config.from_overrides", "coherent_jax.make_config")
    return make_config(mapping, **keys)


# ``Config.from_overrides`` stays until 0.3, attached here: as a method written in schema.py it
# would call the parser, which builds on schema.py (the import cycle `make_config` removed);
# this package imports both, and every import of the config passes through it.
Config.from_overrides = classmethod(_from_overrides)  # type: ignore[attr-defined]

__all__ = [
    "ACTIVATIONS",
    "ALGOS",
    "COHERENT_GRADIENT",
    "COHERENT_INFERENCE",
    "COHERENT_INTEGRATION",
    "COHERENT_LAYERS",
    "COHERENT_SAC_KEYS",
    "CROSS_CHECKS",
    "EXPLORES",
    "FIELDS",
    "GROUPS",
    "LEGACY_KEYS",
    "ON_POLICY",
    "REFUSED",
    "SECTIONS",
    "SUPPORTED_ALGOS",
    "SWEEPABLE",
    "CoherentOptions",
    "CoherentSACOptions",
    "Config",
    "ConfigError",
    "GsdeOptions",
    "LatticeOptions",
    "NoisyNetOptions",
    "PPOOptions",
    "PinkOptions",
    "PsneOptions",
    "SACOptions",
    "Sweepable",
    "make_config",
    "flat_dict",
    "from_stored",
    "get_value",
    "help_text",
    "hparam_path",
    "modern_items",
    "modern_key",
    "override_items",
    "overrides_of",
    "parse_overrides",
    "sweepable",
    "to_dict",
    "upgrade_stored",
    "validate",
    "with_values",
]
