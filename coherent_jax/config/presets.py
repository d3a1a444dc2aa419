"""Defaults that depend on the algorithm, and named protocols (``preset=NAME``).

A configuration is built in layers, each over the one before:

1. `coherent_jax.config.Config`'s defaults;
2. `ALGO_DEFAULTS` of the chosen algorithm;
3. the chosen preset's values for that algorithm (`PRESETS`);
4. the user's ``key=value`` overrides (the user wins).

A layer is applied when its choice is made: a stored config (a run being resumed)
already holds every value, so nothing is applied over it again (`layered_base`).

``preset=thesis`` is the protocol of "Deep Coherent Exploration for Continuous
Control" (Zhang and van Hoof, ICML 2021), whose implementation base is OpenAI Spinning
Up: Spinning Up's documented defaults for PPO (``spinup/algos/pytorch/ppo/ppo.py``),
VPG (A2C here, ``vpg/vpg.py``) and SAC (``sac/sac.py``). ``docs/presets.md`` gives
each value, its source and where this library differs.

No JAX here: ``--help`` and the config parser read these tables.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

# Defaults that differ by algorithm (applied before the preset and the user's overrides):
# SAC's networks, batch and env count follow Haarnoja et al. 2018 / CleanRL rather than PPO.
ALGO_DEFAULTS: dict[str, dict[str, Any]] = {
    "sac": {
        "total_steps": 300_000,
        "num_envs": 8,
        "unroll_length": 16,
        "lr": 3e-4,
        "policy_hidden": [256, 256],
        "value_hidden": [256, 256],
        "activation": "relu",
        "normalize_obs": False,
        "eval_every": 20,
        # A checkpoint holds the replay buffer (1M transitions: 170 MB per seed on
        # HalfCheetah). Every 10 iterations of 128 steps, writing it took longer than the
        # training between (a 5-seed sweep at UTD 0.25: 12-17 s stalls every 1,280
        # steps, 45% of the wall time); every 200 it is a few percent.
        "checkpoint_every": 200,
        # Coherent-SAC uses the sampled w_t (thesis §4.3): there is no log-prob to integrate.
        "coherent": {"integration": "mc"},
    },
}

# Spinning Up's PPO and VPG share the buffer, GAE, networks and the value function's
# own optimiser (ppo.py / vpg.py: steps_per_epoch=4000, gamma=0.99, lam=0.97,
# pi_lr=3e-4, vf_lr=1e-3, train_v_iters=80, MLPActorCritic (64, 64) tanh, log_std -0.5).
_THESIS_ON_POLICY: dict[str, Any] = {
    "num_envs": 4,  # 4 x 1000 = steps_per_epoch 4000 (ppo.py's __main__ runs --cpu 4 of 1000)
    "unroll_length": 1000,
    "gamma": 0.99,
    "lr": 3e-4,  # pi_lr
    "normalize_obs": False,
    "policy_hidden": [64, 64],
    "value_hidden": [64, 64],
    "activation": "tanh",
    "init_std": math.exp(-0.5),  # MLPGaussianActor: log_std = -0.5
    # The chain is drawn at the buffer's start and runs through it across resets.
    "coherent": {"episode_restart": False},
}
_THESIS_PPO_GROUP: dict[str, Any] = {
    "gae_lambda": 0.97,
    "vf_lr": 1e-3,
    "vf_iters": 80,  # train_v_iters
    "ent_coef": 0.0,
    "max_grad_norm": 0.0,  # no gradient clipping
    "normalize_advantages": True,  # over the whole buffer (PPOBuffer.get)
    "normalize_rewards": False,
}

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "thesis": {
        "ppo": {
            **_THESIS_ON_POLICY,
            "ppo": {
                **_THESIS_PPO_GROUP,
                "clip_eps": 0.2,  # clip_ratio
                "num_epochs": 80,  # train_pi_iters, full batch, early stopped
                "num_minibatches": 1,
                "target_kl": 0.01,
            },
        },
        # VPG: one policy step
        "a2c": {**_THESIS_ON_POLICY, "ppo": {**_THESIS_PPO_GROUP, "num_epochs": 1, "num_minibatches": 1}},
        "sac": {
            "num_envs": 1,
            "unroll_length": 50,  # update_every
            "lr": 1e-3,
            "gamma": 0.99,
            "sac": {
                "utd_ratio": 1.0,  # update_every updates every update_every steps
                "tau": 0.005,  # polyak 0.995
                "temperature": 0.2,  # alpha
                "auto_temperature": False,
                "batch_size": 100,
                "buffer_size": 1_000_000,  # replay_size
                "warmup_steps": 10_000,  # start_steps
                "update_after": 1_000,
            },
            "policy_hidden": [256, 256],
            "value_hidden": [256, 256],
            "activation": "relu",
            "normalize_obs": False,
            "eval_every": 80,  # every 4000 steps (steps_per_epoch) ...
            "eval_episodes": 10,  # ... num_test_episodes
        },
    },
}
PRESET_DESCRIPTIONS = {
    "thesis": "the thesis's protocol, OpenAI Spinning Up's defaults (docs/presets.md)",
}
# Values of ``preset`` that select no preset (``preset=`` is null); a config records "".
NO_PRESET = ("", "none", "null", None)


def apply_layer(base: Any, changes: dict[str, Any]) -> Any:
    """`base` (a config dataclass) with `changes`; a dict value updates that group's fields."""
    changes = dict(changes)
    for key, value in changes.items():
        if isinstance(value, dict):
            changes[key] = dataclasses.replace(getattr(base, key), **value)
        elif isinstance(value, list):
            changes[key] = list(value)
    return dataclasses.replace(base, **changes)


def layered_base(base: Any, algo: str | None, preset: str | None) -> Any:
    """`base` with the layers of the choices the overrides make (`algo`, `preset`: None if not given).

    A choice equal to the base's own applies nothing: the base (a stored config, say)
    already holds its layers, and the user's values over them. Choosing another algorithm
    applies its `ALGO_DEFAULTS` and, if a preset is in force, the preset's values for it.
    """
    new_algo = algo is not None and algo != base.algo
    new_preset = preset is not None and preset != base.preset
    algo = algo if algo is not None else base.algo
    preset = preset if preset is not None else base.preset
    if new_algo and algo in ALGO_DEFAULTS:
        base = apply_layer(base, ALGO_DEFAULTS[algo])
    if (new_algo or new_preset) and preset not in NO_PRESET and algo in PRESETS.get(preset, {}):
        base = apply_layer(base, PRESETS[preset][algo])
    return base


def dotted_items(values: dict[str, Any]) -> dict[str, Any]:
    """A layer's values with a group's fields as dotted keys (``{"ppo": {"clip_eps": 0.2}}`` ->
    ``{"ppo.clip_eps": 0.2}``)."""
    items: dict[str, Any] = {}
    for k, v in values.items():
        items.update({f"{k}.{g}": w for g, w in v.items()} if isinstance(v, dict) else {k: v})
    return items


def _flat(values: dict[str, Any], same: Any = None) -> str:
    """``key=value`` items of a layer, a group's fields dotted (``ppo.clip_eps=0.2``); an item for
    which ``same(key, value)`` is true is left out."""
    items = {k: v for k, v in dotted_items(values).items() if same is None or not same(k, v)}
    shown = {k: str(v).lower() if isinstance(v, bool) else v for k, v in items.items()}
    return " ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in shown.items()).replace(
        ", ", ","
    )


def help_lines(same_as_default: Any = None) -> list[str]:
    """What ``--help`` says about the algorithm defaults and every preset, per algorithm.

    ``same_as_default(key, value)``: whether an algorithm's default equals the base default
    (it changes nothing, so it is not listed as a change)."""
    lines = [
        f"algo={algo} changes these defaults: {_flat(values, same_as_default)}"
        for algo, values in ALGO_DEFAULTS.items()
    ]
    for name, per_algo in PRESETS.items():
        lines.append(f"preset={name}: {PRESET_DESCRIPTIONS[name]}; over the algo's defaults it sets")
        lines += [f"  with algo={algo}: {_flat(values)}" for algo, values in per_algo.items()]
    return lines
