"""Validation: the declared ranges and choices of every field, then the few cross-field checks.

Each declared check comes from the field's metadata (`coherent_jax.config.groups`);
what cannot be declared on one field (a value that depends on another: a divisor of
``num_envs``, a pair of settings a strategy refuses) is one named function below. The
first problem raises `ConfigError`, one line naming the key and what is allowed. No JAX.

The refusals every entry point shares are here too, so that they read the same
everywhere: an unknown key (`unknown_key`: the key, up to three close ones, a pointer to
``--help``), a sweep's item given to a single run (`sweep_item`), and the warning of a
SAC run too short to leave its warm-up (`warmup_warning`).

What the program's integer counters can hold is checked with the config too: the train
state counts env steps in int32 (``state.env_steps``, the replay buffer's position), so
every count a run reaches must stay within `INT32_MAX`: the env steps of the whole run,
rounded up to whole iterations (``iterations * num_envs * unroll_length``), SAC's warm-up
and the replay ring's write position. `counter_problem` is called by `validate`, so every
entry point refuses such a config before anything is written; `rounding_note` is what a
run says at its start when ``total_steps`` is rounded up to whole iterations. (The seeds'
range is `coherent_jax.config.schema.MAX_SEED`.)
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Iterable
from typing import Any

from coherent_jax.config.schema import ENV_ALLOWED, FIELDS, NO_PRESET, PRESETS, SWEEPABLE, Config, get_value
from coherent_jax.envs.registry import (
    NATIVE_TASKS,
    TASKS,
    PhysicsError,
    TaskDefinitionError,
    TaskSpec,
    check_task,
    is_user_task,
    resolve_physics,
)
from coherent_jax.strategies import ON_POLICY, REFUSED, SUPPORTED_ALGOS


class ConfigError(ValueError):
    """A bad override: unknown key, wrong type or value out of range."""


def check(cond: bool, key: str, value: Any, allowed: str) -> None:
    if not cond:
        raise ConfigError(f"invalid value for {key!r}: {value!r} (allowed: {allowed})")


# ------------------------------------------------------------------ refusals every entry point shares
SWEEP_COMMAND = "python -m coherent_jax.sweep"


def close_keys(key: str, valid: Iterable[str], n: int = 3) -> list[str]:
    """Up to `n` keys of `valid` close to `key` (difflib), closest first; a group's key also by
    its last part, so ``temperatur`` finds ``sac.temperature``."""
    valid = sorted(set(valid))
    found = difflib.get_close_matches(key, valid, n=n, cutoff=0.7)
    by_name: dict[str, list[str]] = {}
    for name in valid:
        by_name.setdefault(name.rpartition(".")[2], []).append(name)
    for name in difflib.get_close_matches(key.rpartition(".")[2], list(by_name), n=n, cutoff=0.75):
        found += by_name[name]
    return list(dict.fromkeys(found))[:n]


def unknown_key(key: str, valid: Iterable[str]) -> ConfigError:
    """The one-line refusal of an unknown key: the key, up to three close valid keys and where
    the full list is (``--help``), never the list itself."""
    close = close_keys(key, valid)
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    return ConfigError(f"unknown key {key!r}{hint}; valid keys: --help lists them all")


def sweep_item(key: str, value: Any, text: str) -> ConfigError | None:
    """The refusal of what only a sweep takes, given to a single run: ``seeds=N``, or a list
    (``lr=[1e-3,3e-4]``) for a key that holds one value (a list setting takes a list of
    lists); None for anything else. `value` is `text` read as YAML."""
    if key == "seeds":
        return ConfigError(
            f"invalid key 'seeds': {text} (allowed: seed=N, the one seed of a single run; "
            f"{SWEEP_COMMAND} seeds={text} runs several)"
        )
    field = FIELDS.get(key)
    if field is None or not isinstance(value, list):
        return None
    if "list" in str(field.type) and not any(isinstance(v, list) for v in value):
        return None  # one value of a list setting: policy_hidden=[64,64]
    if key in (*SWEEPABLE, "seed"):
        where = f"{SWEEP_COMMAND} {key}={text} runs one point per value"
    else:
        where = "it sets shapes or the program, so a sweep cannot vary it either"
    return ConfigError(f"invalid value for {key!r}: {text!r} is a list (allowed: one value; {where})")


def warmup_warning(cfg: Config) -> str | None:
    """The one-line warning of a SAC run that ends within its warm-up, where every action is
    uniformly random (it may be a deliberate smoke run, so it is not refused); None otherwise."""
    steps = cfg.num_iterations * cfg.steps_per_iteration
    if cfg.algo != "sac" or steps > cfg.sac.warmup_steps:
        return None
    return (
        f"warning: total_steps={cfg.total_steps} ({steps} env steps) is within sac.warmup_steps="
        f"{cfg.sac.warmup_steps}: every action is uniformly random, none is the policy's "
        "(raise total_steps or lower sac.warmup_steps)"
    )


# ------------------------------------------------------------------ what the int32 counters hold
INT32_MAX = 2**31 - 1


def counter_problem(cfg: Any) -> tuple[str, Any, str] | None:
    """(key, value, allowed) of the first setting whose counts overflow int32, or None.

    `cfg` is a `coherent_jax.config.Config` whose ranges were checked (positive sizes).
    """
    per_iteration = cfg.num_envs * cfg.unroll_length
    if per_iteration > INT32_MAX:
        return (
            "num_envs",
            cfg.num_envs,
            f"num_envs * unroll_length <= {INT32_MAX}, the int32 env-step counter "
            f"(here {cfg.num_envs} * {cfg.unroll_length} = {per_iteration})",
        )
    total = cfg.num_iterations * per_iteration
    if total > INT32_MAX:
        return (
            "total_steps",
            cfg.total_steps,
            f"at most {INT32_MAX} env steps, the int32 env-step counter, once rounded up to whole "
            f"iterations of num_envs * unroll_length = {per_iteration} (here {total})",
        )
    if cfg.algo == "sac":
        if cfg.sac.warmup_steps > INT32_MAX:
            return ("warmup_steps", cfg.sac.warmup_steps, f"an integer in [0, {INT32_MAX}] (int32 counter)")
        if cfg.sac.buffer_size + per_iteration > INT32_MAX:
            return (
                "buffer_size",
                cfg.sac.buffer_size,
                f"buffer_size + num_envs * unroll_length <= {INT32_MAX}, the replay ring's int32 "
                f"write position (here {cfg.sac.buffer_size} + {per_iteration})",
            )
    return None


def rounding_note(cfg: Any) -> str | None:
    """The line a run prints at its start when ``total_steps`` is not a whole number of
    iterations: training runs whole iterations of ``num_envs * unroll_length`` env steps,
    so it stops at the next multiple (``total_steps=50000`` at 64 envs x 64 steps runs
    13 iterations, 53,248 steps). None when nothing is rounded."""
    per_iteration = cfg.steps_per_iteration
    total = cfg.num_iterations * per_iteration
    if total == cfg.total_steps:
        return None
    return (
        f"total_steps={cfg.total_steps} is rounded up to whole iterations of num_envs * unroll_length"
        f" = {cfg.num_envs} * {cfg.unroll_length} = {per_iteration:,} env steps: "
        f"{cfg.num_iterations:,} iterations, {total:,} env steps"
    )


# ------------------------------------------------------------------ validation
def _declared(cfg: Config) -> None:
    """Every field's declared choices and range, in declaration order."""
    for key, field in FIELDS.items():
        value = get_value(cfg, key)
        choices = field.metadata.get("choices")
        if choices is not None:
            shown = [c for c in choices if c not in NO_PRESET] if key == "preset" else choices
            check(value in choices, key, value, ", ".join(str(c) for c in shown))
        declared = field.metadata.get("check")
        if declared is not None:
            ok, allowed = declared
            check(ok(value), key, list(value) if isinstance(value, list) else value, allowed)


def validate(cfg: Config) -> Config:
    """Checks ranges, choices and the cross-field rules; returns `cfg` with the task's time
    limit for ``episode_length=0`` and ``""`` for no preset. Raises `ConfigError` naming the
    first bad key."""
    spec = task_spec(cfg.env)
    if cfg.episode_length == 0:  # the task's registered time limit, written into the resolved config
        cfg = dataclasses.replace(cfg, episode_length=spec.episode_length)
    _declared(cfg)
    limit = spec.max_episode_length
    check(
        limit is None or cfg.episode_length <= limit,
        "episode_length",
        cfg.episode_length,
        f"at most {limit}, the TimeLimit the env wears (build it without one for longer episodes)",
    )
    cfg = dataclasses.replace(cfg, preset="") if cfg.preset in NO_PRESET else cfg
    for rule in CROSS_CHECKS:
        rule(cfg)
    overflow = counter_problem(cfg)
    if overflow is not None:
        check(False, *overflow)
    return cfg


def task_spec(env: str) -> TaskSpec:
    """The registry's entry of ``env``: a registered name, or a user's ``MODULE:NAME``, which
    is imported and checked here (loading JAX) so that a bad definition is refused before
    anything is written."""
    check(env in TASKS or is_user_task(env), "env", env, ENV_ALLOWED)
    try:
        return check_task(env)
    except TaskDefinitionError as exc:
        raise ConfigError(f"invalid value for 'env': {exc}") from None


# ------------------------------------------------------------------ cross-field checks
def strategy_runs_with_algo(cfg: Config) -> None:
    """The strategy table's algorithms for ``explore`` (`coherent_jax.strategies`)."""
    supported = SUPPORTED_ALGOS[cfg.explore]
    reason = REFUSED.get((cfg.explore, cfg.algo))
    check(
        cfg.algo in supported,
        "algo",
        cfg.algo,
        f"{', '.join(supported)} with explore={cfg.explore}" + (f": {reason}" if reason else ""),
    )


def preset_has_values_for_algo(cfg: Config) -> None:
    """A preset holds values for some algorithms (`PRESETS`); with another it is refused,
    not silently empty."""
    algos = PRESETS.get(cfg.preset, {})
    check(
        cfg.preset in NO_PRESET or cfg.algo in algos,
        "preset",
        cfg.preset,
        f"a preset with values for algo={cfg.algo}: "
        + ", ".join(name for name, values in PRESETS.items() if cfg.algo in values),
    )


def minibatches_split_envs(cfg: Config) -> None:
    """A2C/PPO: minibatches split the envs, never time."""
    check(
        cfg.algo not in ON_POLICY or cfg.num_envs % cfg.ppo.num_minibatches == 0,
        "ppo.num_minibatches",
        cfg.ppo.num_minibatches,
        f"a divisor of num_envs={cfg.num_envs} (minibatches split envs)",
    )


def value_steps_match_rate(cfg: Config) -> None:
    """A separate value function has both a rate and steps, a joint loss neither."""
    ppo = cfg.ppo
    separate = f"an integer >= 1 with vf_lr={ppo.vf_lr}" if ppo.vf_lr > 0 else "0 with vf_lr=0 (joint loss)"
    check(ppo.vf_iters >= 0 and (ppo.vf_iters > 0) == (ppo.vf_lr > 0), "ppo.vf_iters", ppo.vf_iters, separate)


def sac_sizes(cfg: Config) -> None:
    """SAC: no reward scaling, a buffer that holds an iteration, at least one update per iteration."""
    if cfg.algo != "sac":
        return
    check(
        not cfg.ppo.normalize_rewards,
        "ppo.normalize_rewards",
        cfg.ppo.normalize_rewards,
        "false with algo=sac (reward scaling is a2c/ppo's)",
    )
    check(
        cfg.sac.buffer_size >= cfg.steps_per_iteration,
        "sac.buffer_size",
        cfg.sac.buffer_size,
        f"at least num_envs * unroll_length = {cfg.steps_per_iteration} (one iteration's data)",
    )
    check(
        cfg.updates_per_iteration >= 1,
        "sac.utd_ratio",
        cfg.sac.utd_ratio,
        f"at least 1 / (num_envs * unroll_length) = {1 / cfg.steps_per_iteration:.3g}",
    )


def physics_runs_task(cfg: Config) -> None:
    """``physics=native`` needs a native task, ``physics=mjx`` a task MJX can run; a JAX
    environment of the user's (``MODULE:NAME``) runs on its own backend, ``physics=auto``."""
    if cfg.physics != "auto" and is_user_task(cfg.env) and task_spec(cfg.env).backend == "jax-env":
        check(
            False,
            "physics",
            cfg.physics,
            f"auto with env={cfg.env} (a JAX environment runs on its own backend)",
        )
    check(
        cfg.physics != "native" or cfg.env in NATIVE_TASKS or is_user_task(cfg.env),
        "env",
        cfg.env,
        "with physics=native: " + ", ".join(NATIVE_TASKS),
    )
    if cfg.physics == "mjx":
        try:
            resolve_physics(cfg.env, cfg.physics)
        except PhysicsError as exc:
            raise ConfigError(
                f"invalid value for 'physics': 'mjx' with env={cfg.env} ({exc}) (allowed: auto, native)"
            ) from None


def coherent_ablations(cfg: Config) -> None:
    """The coherent options that only go together (thesis §5)."""
    if cfg.explore != "coherent":
        return
    co, on_policy = cfg.coherent, cfg.algo in ON_POLICY
    check(
        co.gradient != "episode" or co.inference == "joint",
        "coherent.inference",
        co.inference,
        "joint with coherent.gradient=episode (the loss re-infers the episode prefix in joint form)",
    )
    check(
        co.episode_restart or co.gradient != "episode",
        "coherent.episode_restart",
        co.episode_restart,
        "true with coherent.gradient=episode (the prefix it re-infers starts at the episode start)",
    )
    check(
        co.episode_restart or (on_policy and co.integration == "analytic"),
        "coherent.episode_restart",
        co.episode_restart,
        "true with algo=sac or coherent.integration=mc (the switch is the analytic chain's)",
    )
    check(
        co.integration == "analytic" or co.gradient == "exact",
        "coherent.gradient",
        co.gradient,
        "exact with coherent.integration=mc or algo=sac (the gradient modes are the analytic chain's)",
    )
    check(
        on_policy or co.integration == "mc",
        "coherent.integration",
        co.integration,
        "mc with algo=sac: analytic integration needs an on-policy algorithm "
        "(SAC never scores its behaviour actions)",
    )
    check(
        co.layers == "last" or co.integration == "mc",
        "coherent.integration",
        co.integration,
        "mc with coherent.layers=all: only the last layer integrates analytically",
    )
    check(
        co.layers == "last" or on_policy,
        "coherent.layers",
        co.layers,
        "last with algo=sac: Coherent-SAC perturbs the actor's mean head (thesis §4.3); "
        "every-layer noise for SAC is explore=psne",
    )


def pink_needs_episodes(cfg: Config) -> None:
    """Pink noise draws one sequence per episode: at least two steps."""
    if cfg.explore == "pink":
        check(
            cfg.episode_length >= 2,
            "episode_length",
            cfg.episode_length,
            "an integer >= 2 with explore=pink (one noise sequence per episode)",
        )


def lattice_has_noise(cfg: Config) -> None:
    """Lattice without its action noise needs its latent noise (alpha > 0)."""
    if cfg.explore == "lattice" and not cfg.lattice.action_noise:
        check(
            cfg.lattice.alpha > 0,
            "lattice.alpha",
            cfg.lattice.alpha,
            "a number > 0 with lattice.action_noise=false (no noise otherwise)",
        )


CROSS_CHECKS = (
    strategy_runs_with_algo,
    preset_has_values_for_algo,
    minibatches_split_envs,
    value_steps_match_rate,
    sac_sizes,
    physics_runs_task,
    coherent_ablations,
    pink_needs_episodes,
    lattice_has_noise,
)


def gymnasium_id(env: str) -> str:
    """The Gymnasium id of task ``env``; raises `ConfigError` naming the tasks that have one."""
    if not check_task(env).gymnasium_id:
        having = ", ".join(name for name, spec in TASKS.items() if spec.gymnasium_id)
        raise ConfigError(
            f"invalid value for 'engine': gymnasium with env={env}, which has no Gymnasium id "
            f"(allowed: engine=jax, or a run of one of {having})"
        )
    return TASKS[env].gymnasium_id
