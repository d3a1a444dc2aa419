"""What the program's integer counters and key derivation can hold, checked with the config.

* Seeds: a run's PRNG key is ``jax.random.PRNGKey(seed)`` (`coherent_jax.run.loop.run_keys`).
  With 32-bit JAX (the default, ``jax_enable_x64`` off) it takes the seed's low 32 bits,
  so seeds 0 and 2**32 give the same key, and a seed of 2**63 or more does not convert
  at all (OverflowError). The seeds that give distinct keys are [0, `MAX_SEED`].
* Env-step counters: the train state counts env steps in int32 (``state.env_steps``,
  the replay buffer's position), so every count a run reaches must stay within
  `INT32_MAX`: the env steps of the whole run, rounded up to whole iterations
  (``iterations * num_envs * unroll_length``), SAC's warm-up and the replay ring's
  write position.

`counter_problem` is called by `coherent_jax.config.validate`, so every entry point
refuses such a config before anything is written; `rounding_note` is what a run says at
its start when ``total_steps`` is rounded up to whole iterations.
"""

from __future__ import annotations

from typing import Any

MAX_SEED = 2**32 - 1
SEED_ALLOWED = f"an integer in [0, {MAX_SEED}]: the PRNG key is derived from the seed's 32 bits"
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
