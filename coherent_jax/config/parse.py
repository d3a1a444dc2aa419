"""``key=value`` overrides into a validated `Config`; stored configs; the flat keys of before.

OmegaConf turns the dataclass into a structured config, so ``key=value`` overrides
(Hydra's syntax, ``ppo.clip_eps=0.1`` for a group's key) are type-checked on merge.

The keys of before (the flat ``clip_eps=0.1``, Coherent-SAC's ``psne.sigma_init``) keep
working: they are renamed first (`coherent_jax.config.legacy`, with a one-line note on
stderr), and a stored ``config.yaml`` is read in the layout of now (`upgrade_stored`).
No JAX here.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from coherent_jax.config.checks import ConfigError, sweep_item, unknown_key, validate
from coherent_jax.config.legacy import former_keys, modern_items, upgrade_stored
from coherent_jax.config.presets import ALGO_DEFAULTS, dotted_items, help_lines, layered_base
from coherent_jax.config.schema import FIELDS, GROUPS, SECTIONS, SWEEPABLE, Config


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
    (`presets.ALGO_DEFAULTS`) apply first, then the chosen preset's values for it, then the
    overrides (`coherent_jax.config.presets.layered_base`): ``algo=sac num_envs=4`` keeps
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
    (`coherent_jax.config.presets.ALGO_DEFAULTS`), then the ``preset``'s values for that
    algorithm (`coherent_jax.config.presets.PRESETS`), then these overrides. Raises
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
    """key -> {algo: the default that algorithm sets} (`presets.ALGO_DEFAULTS`), keys dotted;
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
