"""``key=value`` overrides into a validated `Config`; stored configs; the keys of before.

OmegaConf turns the dataclass into a structured config, so ``key=value`` overrides
(Hydra's syntax, ``ppo.clip_eps=0.1`` for a group's key) are type-checked on merge.

The keys of before, every old name of a setting and what it is now, are all here (below
`help_text`). Two renamings, both still accepted:

* the flat keys of before the groups (`LEGACY_KEYS`: ``clip_eps`` is ``ppo.clip_eps``,
  ``beta`` is ``coherent.beta``), for every run;
* Coherent-SAC's sigma rule, which was set through ``psne.*`` before it had its own group
  (`COHERENT_SAC_KEYS`: with ``algo=sac explore=coherent``, ``psne.sigma_init`` is
  ``coherent_sac.sigma_init``; so is the flat ``sigma_init``). With any other pair ``psne.*``
  is PSNE's own.

An old key works on the command line and in the API with a one-line note on stderr naming
the new key (`modern_key`, `modern_items`; they are renamed first), and in a stored
``config.yaml`` or policy record silently (`upgrade_stored`), so every run written before
still loads, resumes and reports. A checkpoint's fingerprint is taken over the flat layout
of before (`flat_dict`), so a run checkpointed before resumes under the new names.
No JAX here.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from coherent_jax.config.checks import ConfigError, sweep_item, unknown_key, validate
from coherent_jax.config.schema import (
    ALGO_DEFAULTS,
    FIELDS,
    GROUPS,
    SECTIONS,
    SWEEPABLE,
    Config,
    dotted_items,
    help_lines,
    layered_base,
)


def from_stored(stored: dict[str, Any]) -> Config:
    """The (unvalidated) `Config` of a stored mapping, flat or grouped; OmegaConf errors propagate."""
    merged = OmegaConf.merge(OmegaConf.structured(Config()), OmegaConf.create(upgrade_stored(stored)))
    return OmegaConf.to_object(merged)


def to_dict(cfg: Config) -> dict[str, Any]:
    """Plain-dict view of the config, groups as nested dicts (``config.yaml``)."""
    return dataclasses.asdict(cfg)


def parse_overrides(overrides: Sequence[str], base: Config | None = None) -> Config:
    """Builds a validated `Config` from ``key=value`` strings (Hydra/OmegaConf syntax).

    Lists are written ``policy_hidden=[64,64]``, a group's key dotted (``ppo.clip_eps=0.1``).
    Raises `ConfigError` with a one-line message for a malformed override, an unknown
    key, a value of the wrong type or out of range. The defaults of the chosen algorithm
    (`schema.ALGO_DEFAULTS`) apply first, then the chosen preset's values for it, then the
    overrides (`coherent_jax.config.schema.layered_base`): ``algo=sac num_envs=4`` keeps
    SAC's network sizes and takes the user's env count.
    """
    overrides = modern_items(overrides, base=base)
    chosen: dict[str, str | None] = {"algo": None, "preset": None}
    for item in overrides:
        if "=" not in item or item.startswith("="):
            raise ConfigError(f"malformed override {item!r}: expected key=value")
        key, text = (s.strip() for s in item.split("=", 1))
        value = _check_yaml(key, text)
        refusal = sweep_item(key, value, text)
        if refusal is not None:
            raise refusal
        if key not in FIELDS:
            raise unknown_key(key, FIELDS)
        if isinstance(value, dict):  # env=os: reads as a mapping, which no key takes
            raise ConfigError(f"invalid value for {key!r}: {text!r} (allowed: {_expected_one(key)})")
        if key in chosen:
            chosen[key] = text
    base = layered_base(base if base is not None else Config(), **chosen)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(base), OmegaConf.from_dotlist(list(overrides)))
        cfg = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        msg = str(exc).splitlines()[0]
        raise ConfigError(f"invalid value for {key!r}: {msg} (allowed: {_expected(key)})") from None
    return validate(cfg)


def _expected_one(key: str) -> str:
    """What `key` takes, said briefly for a value that is no value at all (a mapping)."""
    if key == "env":  # ``env=os:``: a task of the user's without its attribute
        return "MODULE:NAME or path/to/file.py:NAME, NAME the task's attribute, or a registered task (--help)"
    return _expected(key)


def _expected(key: str) -> str:
    """What `key` takes, as a refusal names it: its choices, its declared range, or its type."""
    field = FIELDS.get(key)
    if field is None:
        return "a valid value"
    if "choices" in field.metadata:
        return ", ".join(str(c) for c in field.metadata["choices"] if c)
    return field.metadata.get("allowed") or _type_name(field.type)


def override_items(overrides: Mapping[str, Any]) -> list[str]:
    """``key=value`` strings of a mapping of overrides, as the command line would give them.

    A nested mapping is a group's keys (``{"ppo": {"clip_eps": 0.2}}`` is
    ``ppo.clip_eps=0.2``); values are bools, numbers, strings, paths, lists of them or
    None. A string YAML would read as something else (``"true"``, ``""``) is quoted, so
    it stays a string; an empty string where that is the default (``run_dir``, ``resume``,
    ``preset``) is left out, as not given. Raises `ConfigError` naming a key or value of
    another kind.
    """

    def text(key: str, value: Any) -> str:
        if value is None:
            return "null"
        if isinstance(value, bool):
            return str(value).lower()
        if isinstance(value, int | float):
            return repr(value)
        if isinstance(value, str | os.PathLike):
            value = os.fspath(value)
            plain = value and yaml.safe_load(value) == value and "," not in value
            return value if plain else json.dumps(value)
        if isinstance(value, list | tuple):
            return "[" + ",".join(text(key, v) for v in value) + "]"
        raise ConfigError(
            f"invalid value for {key!r}: {value!r} of type {type(value).__name__} "
            "(allowed: a bool, number, string, path, list or None)"
        )

    items: list[str] = []
    for key, value in overrides.items():
        if not isinstance(key, str) or not key:
            raise ConfigError(f"invalid key {key!r}: not a string (allowed: config keys, e.g. 'lr')")
        if isinstance(value, Mapping):
            items += override_items({f"{key}.{k}" if isinstance(k, str) else k: v for k, v in value.items()})
        elif value == "" and key in FIELDS and FIELDS[key].default == "":
            continue  # the default ``run_dir``, ``resume``, ``preset``: as if not given
        else:
            items.append(f"{key}={text(key, value)}")
    return items


def make_config(
    overrides: Mapping[str, Any] | None = None, base: Config | None = None, **kwargs: Any
) -> Config:
    """The validated `Config` of a mapping of overrides and keyword overrides (the latter win).

    ``make_config(env="hopper", preset="thesis", **{"ppo.clip_eps": 0.1})`` or
    ``make_config({"env": "hopper", "ppo": {"clip_eps": 0.1}})``: the same layers as the
    command line (`parse_overrides`): the defaults, then ``algo``'s
    (`coherent_jax.config.schema.ALGO_DEFAULTS`), then the ``preset``'s values for that
    algorithm (`coherent_jax.config.schema.PRESETS`), then these overrides. Raises
    `ConfigError` in one line naming the bad key or value.
    """
    if overrides is not None and not isinstance(overrides, Mapping):
        raise ConfigError(
            f"invalid config {overrides!r}: a {type(overrides).__name__} "
            "(allowed: a Config or a mapping of config keys to values)"
        )
    return parse_overrides(override_items({**(overrides or {}), **kwargs}), base=base)


def _check_yaml(key: str, text: str) -> Any:
    """`text` read as YAML; raises `ConfigError` naming `key` if it is not valid YAML (``[64,64``, ``{``)."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        problem = getattr(exc, "problem", None) or "malformed"
        raise ConfigError(
            f"invalid value for {key!r}: {text!r} is not valid YAML ({problem}) "
            f"(allowed: a YAML scalar or a list such as [64,64])"
        ) from None


def _type_name(tp: Any) -> str:
    return {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string"}.get(
        str(tp), str(tp)
    )


def _shown(value: Any) -> str:
    if isinstance(value, list):
        return "[" + ",".join(str(v) for v in value) + "]"
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def _is_default(key: str, value: Any) -> bool:
    """Whether dotted `key`'s default in `Config` equals `value`."""
    obj = Config()
    for part in key.split("."):
        obj = getattr(obj, part)
    return obj == value


def _algo_changes() -> dict[str, dict[str, Any]]:
    """key -> {algo: the default that algorithm sets} (`ALGO_DEFAULTS`), keys dotted;
    a default the algorithm leaves as it is is not a change."""
    out: dict[str, dict[str, Any]] = {}
    for algo, values in ALGO_DEFAULTS.items():
        for key, value in dotted_items(values).items():
            if not _is_default(key, value):
                out.setdefault(key, {})[algo] = value
    return out


def help_text(cfg: Config | None = None, given: Sequence[str] = ()) -> str:
    """Every option with its value and a one-line description, in sections and groups; a
    default another algorithm changes says so (``[algo=sac: 8]``).

    The values are the defaults, or with `cfg` its values: ``preset=thesis --help`` shows
    what the items `given` (which resolve to `cfg`) make of each key."""
    changes = _algo_changes()
    legacy = former_keys()
    lines = [
        "usage: python -m coherent_jax.train [key=value ...]",
        "dry_run=true (or --print-config) prints the resolved config and exits, writing nothing",
        "",
        *help_lines(_is_default),
    ]
    lines.append(f"sweepable (a list runs a grid with coherent_jax.sweep): {', '.join(SWEEPABLE)}")
    lines.append(
        "a group's key is dotted (ppo.clip_eps=0.1); the flat keys of before (clip_eps=0.1), and "
        "psne.* for algo=sac explore=coherent, still work, with a note naming the new key"
    )
    default = cfg if cfg is not None else Config()
    if given:
        lines += ["", f"values below: those of {' '.join(given)} (each key=value as it resolves)"]
    sections = [(s, [k for k, f in FIELDS.items() if f.metadata.get("group") == s]) for s in SECTIONS]
    group_help = {f.name: f.metadata["help"] for f in dataclasses.fields(Config) if f.name in GROUPS}
    sections += [(f"{g}.* ({group_help[g]})", [k for k in FIELDS if k.startswith(g + ".")]) for g in GROUPS]
    for title, keys in sections:
        lines += ["", f"{title}:"]
        for key in keys:
            group, _, name = key.rpartition(".")
            value = getattr(getattr(default, group) if group else default, name)
            text = FIELDS[key].metadata.get("help", "")
            text += "".join(f" [algo={a}: {_shown(v)}]" for a, v in changes.get(key, {}).items())
            if key in legacy and legacy[key] != name:
                text += f" (was {legacy[key]})"
            lines.append(f"  {key}={_shown(value)}".ljust(34) + f"  {text}")
    return "\n".join(lines)


# ------------------------------------------------------------------ the keys of before
# Flat keys of the settings that moved into a group -> their key now.
LEGACY_KEYS: dict[str, str] = {
    "gae_lambda": "ppo.gae_lambda",
    "num_epochs": "ppo.num_epochs",
    "num_minibatches": "ppo.num_minibatches",
    "clip_eps": "ppo.clip_eps",
    "target_kl": "ppo.target_kl",
    "vf_coef": "ppo.vf_coef",
    "vf_lr": "ppo.vf_lr",
    "vf_iters": "ppo.vf_iters",
    "ent_coef": "ppo.ent_coef",
    "max_grad_norm": "ppo.max_grad_norm",
    "normalize_advantages": "ppo.normalize_advantages",
    "normalize_rewards": "ppo.normalize_rewards",
    "buffer_size": "sac.buffer_size",
    "batch_size": "sac.batch_size",
    "utd_ratio": "sac.utd_ratio",
    "warmup_steps": "sac.warmup_steps",
    "update_after": "sac.update_after",
    "tau": "sac.tau",
    "temperature": "sac.temperature",
    "auto_temperature": "sac.auto_temperature",
    "target_entropy": "sac.target_entropy",
    "beta": "coherent.beta",
    "w_std_init": "coherent.w_std_init",
    "action_std": "coherent.action_std",
    "learn_action_std": "coherent.learn_action_std",
    "coherent_inference": "coherent.inference",
    "remat": "coherent.remat",
    "noisynet_sigma0": "noisynet.sigma0",
    "sigma_init": "psne.sigma_init",
    "sigma_delta": "psne.sigma_delta",
    "sigma_alpha": "psne.sigma_alpha",
    "gsde_resample_every": "gsde.resample_every",
    "pink_exponent": "pink.exponent",
}

# The (algo, explore) pair whose psne.* keys of before are its own group's now.
COHERENT_SAC = ("sac", "coherent")
COHERENT_SAC_KEYS: dict[str, str] = {
    "psne.sigma_init": "coherent_sac.sigma_init",
    "psne.sigma_delta": "coherent_sac.sigma_delta",
    "psne.sigma_alpha": "coherent_sac.sigma_alpha",
}

# The groups whose settings the flat layout of before holds (checkpoint fingerprints hash
# it). Every other group came later (``lattice``, ``coherent_sac``, a new strategy's): its
# settings enter the layout only where they differ from the group's defaults, so that every
# config of before keeps its fingerprint. Coherent-SAC's settings enter it as psne's did.
FLAT_LAYOUT_GROUPS = ("ppo", "sac", "coherent", "noisynet", "psne", "gsde", "pink")

_NOTED: set[str] = set()  # the old keys already noted in this process


def pair_of(values: dict[str, Any]) -> tuple[str, str]:
    """The (algo, explore) of a config mapping (``config.yaml``'s, `dataclasses.asdict`'s)."""
    return (
        str(values.get("algo", FIELDS["algo"].default)),
        str(values.get("explore", FIELDS["explore"].default)),
    )


def run_pair(items: Sequence[str], base: Config | None = None) -> tuple[str, str]:
    """The (algo, explore) that ``key=value`` `items` give, the last one of each winning, the
    rest `base`'s (default: the defaults')."""
    values = {"algo": base.algo, "explore": base.explore} if base is not None else {}
    for item in items:
        key, eq, text = item.partition("=")
        if eq and key.strip() in ("algo", "explore"):
            values[key.strip()] = text.strip().strip("'\"")
    return pair_of(values)


def modern_key(key: str, note: bool = True, pair: tuple[str, str] | None = None) -> str:
    """`key`, or the key an old one now is (with a note on stderr, once per key).

    `pair`, the run's (algo, explore), decides whether ``psne.*`` (and its flat keys)
    is Coherent-SAC's group; without it they stay ``psne.*``."""
    new = LEGACY_KEYS.get(key, key)
    renamed = pair is not None and tuple(pair) == COHERENT_SAC and new in COHERENT_SAC_KEYS
    if renamed:
        new = COHERENT_SAC_KEYS[new]
    if new == key:
        return key
    if note and key not in _NOTED:
        _NOTED.add(key)
        where = " with algo=sac explore=coherent" if renamed else ""
        print(f"note: config key {key!r} is now {new!r}{where}; the old name is deprecated", file=sys.stderr)
    return new


def modern_items(
    items: Sequence[str],
    note: bool = True,
    pair: tuple[str, str] | None = None,
    base: Config | None = None,
) -> list[str]:
    """``key=value`` items with every old key renamed to its key now (`modern_key`), for the
    run's `pair` (default: the one `items` and `base` give, `run_pair`)."""
    pair = pair if pair is not None else run_pair(items, base)
    out = []
    for item in items:
        key, eq, value = item.partition("=")
        new = modern_key(key.strip(), note, pair) if eq else key
        out.append(f"{new}={value}" if eq and new != key.strip() else item)
    return out


def former_keys() -> dict[str, str]:
    """Each key now -> the old key ``--help`` names beside it (``coherent.inference`` ->
    ``coherent_inference``, ``coherent_sac.sigma_init`` -> ``psne.sigma_init``)."""
    return {**{new: old for old, new in LEGACY_KEYS.items()}, **{v: k for k, v in COHERENT_SAC_KEYS.items()}}


def _split(key: str) -> tuple[str, str]:
    group, name = key.split(".", 1)
    return group, name


def upgrade_stored(stored: dict[str, Any]) -> dict[str, Any]:
    """A stored config (``config.yaml``, a policy record) in the layout of now, silently: a flat
    one of before is moved into its groups (a key both flat and grouped keeps the grouped),
    and a Coherent-SAC config without a ``coherent_sac`` group has its psne values moved there."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in stored.items() if k not in LEGACY_KEYS}
    for old, new in LEGACY_KEYS.items():
        if old in stored:
            group, name = _split(new)
            out.setdefault(group, {}).setdefault(name, stored[old])
    if pair_of(out) == COHERENT_SAC and "coherent_sac" not in stored:
        for old, new in COHERENT_SAC_KEYS.items():
            (old_group, old_name), (group, name) = _split(old), _split(new)
            if old_name in out.get(old_group, {}):
                out.setdefault(group, {})[name] = out[old_group].pop(old_name)
        if "psne" in out and not out["psne"]:
            del out["psne"]
    return out


def overrides_of(cfg: Config) -> dict[str, Any]:
    """`cfg` as a mapping of overrides that reads back as `cfg`: every field, groups nested,
    but for Coherent-SAC without the psne group (its keys would read as coherent_sac's; it
    does not read them)."""
    out = dataclasses.asdict(cfg)
    if (cfg.algo, cfg.explore) == COHERENT_SAC:
        del out["psne"]
    return out


def flat_dict(cfg: Config) -> dict[str, Any]:
    """The config in the flat layout of before the groups (what checkpoint fingerprints hash):
    the moved settings at the top level under their old keys (Coherent-SAC's sigma rule under
    psne's), ``coherent``'s ablations nested, the setting of a later group (not in
    `FLAT_LAYOUT_GROUPS`) only where it is not its default."""
    out = dataclasses.asdict(cfg)
    if (cfg.algo, cfg.explore) == COHERENT_SAC:
        for old, new in COHERENT_SAC_KEYS.items():
            (old_group, old_name), (group, name) = _split(old), _split(new)
            out[old_group][old_name] = out[group].pop(name)
    for group in (g for g in GROUPS if g not in FLAT_LAYOUT_GROUPS):
        default = dataclasses.asdict(type(getattr(cfg, group))())
        out[group] = {k: v for k, v in out[group].items() if v != default[k]}
    for old, new in LEGACY_KEYS.items():
        group, name = _split(new)
        out[old] = out[group].pop(name)
    for group in GROUPS:
        if not out[group]:
            del out[group]
    return out
