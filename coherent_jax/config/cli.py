"""One ``key=value`` parser for every command-line entry point.

A command describes its own settings as a table of `Key`s (default, parser,
allowed-values text, help) and names the training-config keys it sets itself;
`parse_command` then splits the user's ``key=value`` items into

* the command's own settings, each parsed by its `Key`;
* training-config items (every `Config` key, a group's dotted: ``ppo.clip_eps``; a flat
  key of before, ``clip_eps``, is renamed with a note), handed to
  `config.parse_overrides` after the command's config defaults and before the keys it
  fixes.

Every problem is one `ConfigError` line naming the bad item and what is allowed: a
malformed item, an unknown key (with up to three close ones and a pointer to ``--help``), a key the command
sets itself, a bad value, a YAML syntax error in a config value. Parsing has no
side effects, so a command that parses first refuses bad input before it runs or
writes anything.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import yaml

from coherent_jax.config.checks import ConfigError, unknown_key
from coherent_jax.config.parse import modern_items, parse_overrides, run_pair
from coherent_jax.config.schema import FIELDS, Config


@dataclasses.dataclass(frozen=True)
class Key:
    """One setting of a command: its default, how its text is parsed, what is allowed, what it does.

    ``parse`` raises `ValueError` (or `TypeError`) for a bad value; the message is
    built from ``allowed``, so parsers need not write one.
    """

    default: Any
    parse: Callable[[str], Any]
    allowed: str
    help: str


class Parsed(NamedTuple):
    """What `parse_command` returns."""

    settings: dict[str, Any]  # the command's own keys, defaults filled in
    config: Config | None  # the validated training config (None for a command without one)
    config_items: list[str]  # the user's training-config items, as given


# ------------------------------------------------------------------ value parsers
def _yaml(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        raise ValueError(text) from None


def int_at_least(low: int) -> Callable[[str], int]:
    """Parser of an integer >= ``low``."""

    def parse(text: str) -> int:
        value = int(text)  # int("2.5") and int("true") raise ValueError
        if value < low:
            raise ValueError(text)
        return value

    return parse


def int_between(low: int, high: int) -> Callable[[str], int]:
    """Parser of an integer in [``low``, ``high``]."""

    def parse(text: str) -> int:
        value = int(text)
        if not low <= value <= high:
            raise ValueError(text)
        return value

    return parse


def positive_float(text: str) -> float:
    """Parser of a finite number > 0."""
    value = _yaml(text)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(text)
    return float(value)


def boolean(text: str) -> bool:
    """Parser of ``true`` or ``false``."""
    value = _yaml(text)
    if not isinstance(value, bool):
        raise ValueError(text)
    return value


def text_value(text: str) -> str:
    """Parser of a non-empty string, taken as written."""
    if not text:
        raise ValueError(text)
    return text


def int_list(low: int = 1) -> Callable[[str], list[int]]:
    """Parser of a non-empty list of integers >= ``low``: ``[16,64]`` (a single ``16`` too)."""
    one = int_at_least(low)

    def parse(text: str) -> list[int]:
        value = _yaml(text)
        items = value if isinstance(value, list) else [value]
        if not items:
            raise ValueError(text)
        return [one(str(v)) for v in items]

    return parse


def choice(choices: Sequence[str]) -> Callable[[str], str]:
    """Parser of one of ``choices``."""

    def parse(text: str) -> str:
        if text not in choices:
            raise ValueError(text)
        return text

    return parse


def _listed(text: str, choices: Sequence[str]) -> list[str]:
    """The items of a non-empty list (``[a,b]``, or one bare value) of ``choices``, as given."""
    value = _yaml(text)
    items = [str(v) for v in (value if isinstance(value, list) else [value])]
    if not items or any(item not in choices for item in items):
        raise ValueError(text)
    return items


def choice_list(choices: Sequence[str]) -> Callable[[str], list[str]]:
    """Parser of a non-empty list of ``choices`` (``[a,b]``), returned in the order of ``choices``."""

    def parse(text: str) -> list[str]:
        items = _listed(text, choices)
        return [c for c in choices if c in items]

    return parse


def ordered_choice_list(choices: Sequence[str]) -> Callable[[str], list[str]]:
    """Parser of a non-empty list of distinct ``choices`` (``[b,a]``), returned in the order given."""

    def parse(text: str) -> list[str]:
        items = _listed(text, choices)
        if len(set(items)) != len(items):
            raise ValueError(text)
        return items

    return parse


def output_file(text: str) -> str:
    """Parser of a file path that can be written: not a directory, under a writable folder.

    The nearest existing ancestor must be a directory in which a file can be
    created (tested with a temporary file that is removed at once), so a read-only
    or invalid location is refused before a long command runs, not after it.
    """
    if not text or text.endswith(os.sep):
        raise ValueError(text)
    path = Path(text)
    if path.is_dir() or (path.exists() and not os.access(path, os.W_OK)):
        raise ValueError(text)
    _check_writable_folder(path.parent)
    return text


def output_dir(text: str) -> str:
    """Parser of a directory path that can be created or written into."""
    if not text:
        raise ValueError(text)
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise ValueError(text)
    _check_writable_folder(path)
    return text


def _check_writable_folder(folder: Path) -> None:
    existing = folder.absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(str(folder))
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError:
        raise ValueError(str(folder)) from None


# ------------------------------------------------------------------ the parser
def config_keys() -> set[str]:
    """Every training-config key: `Config`'s fields, a group's dotted (``coherent.beta``)."""
    return set(FIELDS)


def split_item(item: str) -> tuple[str, str]:
    """``"key=value"`` -> (key, value), both stripped; a malformed item is a `ConfigError`."""
    if "=" not in item or not item.split("=", 1)[0].strip():
        raise ConfigError(f"malformed item {item!r}: expected key=value")
    key, value = item.split("=", 1)
    return key.strip(), value.strip()


def check_unique(items: Sequence[str]) -> None:
    """Refuses a key given twice (``lr=0.1 lr=0.2``): which one was meant is not for us to guess.

    Items that are not ``key=value`` (a run directory) are left to the caller.
    """
    seen: dict[str, str] = {}
    for item in items:
        if "=" not in item or not item.split("=", 1)[0].strip():
            continue
        key = item.split("=", 1)[0].strip()
        if key in seen:
            raise ConfigError(f"duplicated key {key!r}: {seen[key]} and {item} (allowed: each key once)")
        seen[key] = item


def parse_value(key: str, text: str, spec: Key) -> Any:
    """``spec.parse(text)``, a failure turned into the one-line `ConfigError` naming ``key``."""
    try:
        return spec.parse(text)
    except (ValueError, TypeError):
        raise ConfigError(f"invalid value for {key!r}: {text!r} (allowed: {spec.allowed})") from None


def _check_config_syntax(key: str, text: str) -> None:
    """A config value must be valid YAML (OmegaConf's syntax); says which key is not."""
    try:
        yaml.safe_load(text)
    except yaml.YAMLError as exc:
        problem = str(getattr(exc, "problem", None) or "a YAML syntax error")
        raise ConfigError(
            f"invalid value for {key!r}: {text!r} is not valid YAML ({problem}) "
            "(allowed: a value such as 3, 0.1, true, name or [64,64])"
        ) from None


def parse_command(
    items: Sequence[str],
    keys: Mapping[str, Key],
    *,
    command: str,
    config: bool = True,
    fixed: Mapping[str, str | None] | None = None,
    config_defaults: Sequence[str] = (),
    ignored: Sequence[str] = (),
) -> Parsed:
    """Splits ``key=value`` items into the command's settings and a validated training config.

    ``keys``: the command's own keys. ``config``: whether training-config keys are
    taken (and a `Config` built). ``fixed``: config keys the command sets itself,
    refused from the user: with a value (``{"algo": "sac"}``) it goes into the config,
    with None the command varies the key itself (a benchmark that runs every
    ``explore``) and the config keeps its default. ``config_defaults``: config items
    the command starts from, which the user's items override (``env=halfcheetah``).
    ``command`` names the command in the refusal of a fixed key. ``ignored``: config
    keys the command never reads (a benchmark's ``run_dir``), refused rather than
    silently dropped. A key given twice is refused. Raises `ConfigError` in one line for
    any bad item; nothing else happens, so callers parse first.
    """
    fixed = dict(fixed or {})
    valid_config = (config_keys() - set(fixed) - set(ignored)) if config else set()
    fixed_items = [f"{k}={v}" for k, v in fixed.items() if v is not None]
    if config:  # the keys of before, renamed to today's (with a note) for the run's algo and explore
        pair = run_pair([*config_defaults, *items, *fixed_items])
        items = [i if i.split("=", 1)[0].strip() in keys else modern_items([i], pair=pair)[0] for i in items]
    settings = {k: spec.default for k, spec in keys.items()}
    config_items = []
    check_unique(items)
    for item in items:
        key, text = split_item(item)
        if key in keys:
            settings[key] = parse_value(key, text, keys[key])
        elif config and key in ignored:
            raise ConfigError(
                f"invalid key {key!r}: {command} does not use it "
                f"(allowed: any key except {', '.join(sorted({*fixed, *ignored}))})"
            )
        elif key in fixed:
            raise ConfigError(
                f"invalid key {key!r}: {command} sets it itself "
                f"(allowed: any key except {', '.join(sorted(fixed))})"
            )
        elif key in valid_config:
            _check_config_syntax(key, text)
            config_items.append(item)
        else:
            raise unknown_key(key, set(keys) | valid_config)
    cfg = None
    if config:
        cfg = parse_overrides([*config_defaults, *config_items, *fixed_items])
    return Parsed(settings, cfg, config_items)


def help_lines(keys: Mapping[str, Key]) -> list[str]:
    """One line per key: ``key=default  help (allowed: ...)``."""
    lines = []
    for name, spec in keys.items():
        default = spec.default
        if isinstance(default, list):
            default = "[" + ",".join(str(v) for v in default) + "]"
        elif isinstance(default, bool):
            default = str(default).lower()  # as it is written on the command line
        lines.append(f"  {name}={default}".ljust(34) + f"  {spec.help} (allowed: {spec.allowed})")
    return lines
