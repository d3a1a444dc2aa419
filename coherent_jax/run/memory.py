"""Refuses, before anything is compiled or written, a configuration whose data cannot fit in memory.

The estimate is a formula, not a trace: bytes of the arrays an iteration holds at once,
float32 throughout (4 bytes), for ``n = num_envs`` envs, ``T = unroll_length`` steps,
``o`` observation and ``a`` action sizes and ``S`` bytes of one env's state:

* env states: ``3 n S`` (the state stepped, the next one, and the fresh states of the
  automatic reset, computed for every env under the reset's ``cond``);
* rollout: ``4 T n (2o + 3a + 8)`` (observation and final observation, action, its
  mean and the strategy's noise, eight per-step scalars), and for A2C/PPO also
  ``4 T n (o + 4 + h/2)`` for the update (normalised observations, values, advantages,
  targets, behaviour log-probabilities, and hidden activations, ``h`` = the sum of the
  policy's and the value network's layer widths);
* SAC's replay buffer: ``4 buffer_size (2o + a + 2)``;
* the evaluation envs: ``3 eval_episodes S``;
* checkpoints: two more copies of the env states and the replay buffer (the state
  gathered to the host, then its serialisation).

A sweep holds all of that once per grid point. ``o``, ``a`` and ``S`` come from one env
of the task (``jax.eval_shape`` of its reset: no compile, no step); before building it
the estimate is made with bounds above every registered task's sizes, and a
configuration that fits even then (the defaults, a 5-seed sweep, SAC with a 1e6 replay
buffer: nearly all) is let through without it. Network parameters and optimiser states
are left out: they are small next to these for any configuration near the limit.

The estimate is compared with the machine's physical memory (``MemTotal`` of
``/proc/meminfo``, else ``os.sysconf``). It errs low for A2C/PPO: XLA's own peak for
the compiled iteration (``memory_analysis``) was 890 MB against an estimate of 696 MB
(pointmass, 16,384 envs) and 257 MB against 239 MB (halfcheetah, 4,096 envs). For SAC
(halfcheetah, a 1e6 replay buffer) the iteration's peak was 348 MB, twice the buffer;
the estimate, 504 MB, also counts the copies a checkpoint makes. So only a
configuration that clearly cannot run is refused.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax

from coherent_jax.config import ConfigError, get_value
from coherent_jax.envs.registry import is_user_task
from coherent_jax.envs.vec_env import VecEnv

FLOAT = 4  # bytes of a float32
# Above every registered task's sizes, measured with `task_sizes` over
# `coherent_jax.envs.registry.TASKS`: the most observations are Humanoid-v5's 348, the
# most actions and state dmc-humanoid_*'s 21 and 31 KB per env. A task beyond these
# would only make the first estimate too small, never refuse a configuration that fits;
# a task of the user's (``env=MODULE:NAME``) is always measured.
BOUND_OBS, BOUND_ACT, BOUND_STATE = 512, 32, 48 * 1024


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Bytes per part (for one grid point), the number of points and their total."""

    parts: dict[str, int]
    points: int

    @property
    def total(self) -> int:
        return self.points * sum(self.parts.values())


def estimate(cfg: Any, obs: int, act: int, state: int, points: int = 1) -> Estimate:
    """The formula of the module docstring for `cfg` with these sizes (``state``: bytes per env)."""
    n, t = cfg.num_envs, cfg.unroll_length
    parts = {
        "env states": 3 * n * state + 3 * cfg.eval_episodes * state,
        "rollout": FLOAT * t * n * (2 * obs + 3 * act + 8),
    }
    replay = 0
    if cfg.algo == "sac":
        replay = FLOAT * cfg.sac.buffer_size * (2 * obs + act + 2)
        parts["replay buffer"] = replay
    else:
        hidden = sum(cfg.policy_hidden) + sum(cfg.value_hidden)
        parts["update"] = FLOAT * t * n * (obs + 4 + hidden // 2)
    parts["checkpoint copies"] = 2 * (n * state + replay)
    return Estimate(parts=parts, points=points)


def machine_memory() -> int | None:
    """Bytes of physical memory: ``MemTotal`` of ``/proc/meminfo``, else ``os.sysconf``; None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def task_sizes(cfg: Any) -> tuple[int, int, int]:
    """(observation size, action size, bytes of one env's state) of `cfg`'s task, from one env."""
    env = VecEnv(cfg.env, 1, cfg.episode_length, cfg.physics, cfg.physics_threads)
    shapes = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    state = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))
    return env.observation_size, env.action_size, int(state)


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def check_memory(cfg: Any, points: int = 1, memory: int | None = None) -> None:
    """Raises `ConfigError` in one line when `cfg` (run as `points` grid points) cannot fit in memory.

    Names the setting behind most of it (``num_envs``, or ``buffer_size`` when SAC's
    replay buffer and its copies are), the estimate with its parts and the machine's memory.
    `memory` (bytes) replaces the machine's, for tests.
    """
    memory = memory if memory is not None else machine_memory()
    if memory is None:
        return
    bounded = not is_user_task(cfg.env)  # the bounds hold for the registry's tasks only
    if bounded and estimate(cfg, BOUND_OBS, BOUND_ACT, BOUND_STATE, points).total <= memory:
        return
    est = estimate(cfg, *task_sizes(cfg), points=points)
    if est.total <= memory:
        return
    replay = 3 * est.parts.get("replay buffer", 0)  # the buffer and its checkpoint copies
    key = "sac.buffer_size" if 2 * replay > sum(est.parts.values()) else "num_envs"
    parts = ", ".join(f"{k} {_gb(v)}" for k, v in est.parts.items())
    per = f" for {points} sweep points" if points > 1 else ""
    raise ConfigError(
        f"invalid value for {key!r}: {get_value(cfg, key)} (allowed: a configuration whose data fits in "
        f"memory: this one needs about {_gb(est.total)}{per} ({parts}{' per point' if points > 1 else ''}), "
        f"this machine has {_gb(memory)})"
    )
