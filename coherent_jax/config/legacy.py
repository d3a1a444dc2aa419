"""The keys of before, in one module: every old name of a setting and what it is now.

Two renamings, both still accepted:

* the flat keys of before the groups (`LEGACY_KEYS`: ``clip_eps`` is ``ppo.clip_eps``,
  ``beta`` is ``coherent.beta``), for every run;
* Coherent-SAC's sigma rule, which was set through ``psne.*`` before it had its own group
  (`COHERENT_SAC_KEYS`: with ``algo=sac explore=coherent``, ``psne.sigma_init`` is
  ``coherent_sac.sigma_init``; so is the flat ``sigma_init``). With any other pair ``psne.*``
  is PSNE's own.

An old key works on the command line and in the API with a one-line note on stderr naming
the new key (`modern_key`, `modern_items`), and in a stored ``config.yaml`` or policy
record silently (`upgrade_stored`), so every run written before still loads, resumes and
reports. A checkpoint's fingerprint is taken over the flat layout of before (`flat_dict`),
so a run checkpointed before resumes under the new names. No JAX here.
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Sequence
from typing import Any

from coherent_jax.config.schema import FIELDS, GROUPS, Config

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
