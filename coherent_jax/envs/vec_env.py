"""Vectorized environment with time limits and automatic resets.

The stack is vmap -> episode (time limit) -> auto-reset, as in Brax's training
wrappers, with two differences that matter for correct on-policy learning:

* the observation reached by a step is returned as ``final_obs`` before the reset
  replaces it, so a time-limit truncation can be bootstrapped with V(final_obs)
  instead of being treated as a termination;
* a reset draws a fresh initial state (Brax's ``AutoResetWrapper`` replays each
  env's first initial state forever). The reset runs under one ``lax.cond`` on
  "any env done", outside the vmap, so the steps where no episode ends, nearly
  all of them, pay nothing for it.
"""

from __future__ import annotations

from typing import Any

import chex
import jax
import jax.numpy as jnp
from flax import struct

from coherent_jax.envs.brax_env import env_sizes, make_brax_env
from coherent_jax.envs.host_gym import GymPhysics, GymState
from coherent_jax.envs.physics import MjxPhysics, NativePhysics, mujoco_model, native_task
from coherent_jax.envs.registry import (
    DEFAULT_THREADS,
    check_task,
    resolve_physics,
)
from coherent_jax.envs.user import load_user_task
from coherent_jax.sweep_axis import any_point


@struct.dataclass
class EnvState:
    """State of `num_envs` environments.

    Attributes:
      physics: batched Brax ``State`` (pipeline state, obs, reward, done, ...), or a
        `NativeState` with native MuJoCo physics, `MjxState` with a native task on MJX.
      obs: [n, obs_size] observation the agent acts on now.
      first: [n] True where ``obs`` is the first observation of an episode.
      step: [n] steps taken in the current episode.
      episode_return: [n] undiscounted return accumulated in the current episode.
      key: PRNG key for the initial states of future episodes.
    """

    physics: Any
    obs: jax.Array
    first: jax.Array
    step: jax.Array
    episode_return: jax.Array
    key: jax.Array


@struct.dataclass
class StepOutcome:
    """What one vectorized step returns besides the next state (all [n, ...]).

    Attributes:
      reward: r_t.
      terminated: the episode ended in a terminal state (no bootstrap).
      truncated: the episode hit the time limit without terminating (bootstrap
        with V(final_obs)).
      final_obs: s_{t+1} as reached by the step, before any automatic reset.
      episode_return: the completed episode's return where terminated|truncated,
        else 0.
    """

    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    final_obs: jax.Array
    episode_return: jax.Array

    @property
    def done(self) -> jax.Array:
        return jnp.logical_or(self.terminated, self.truncated)


class VecEnv:
    """`num_envs` copies of one task, stepped together under one jit.

    Pure: `reset` and `step` take and return `EnvState`; the object only holds
    static configuration (the task and the sizes), so it is safe to close over in
    jitted functions.

    ``physics`` chooses the engine (`coherent_jax.envs.registry.resolve_physics`):
    ``native`` (MuJoCo's C engine on a thread pool through a callback, `NativePhysics`:
    Gymnasium's tasks always, six of Brax's re-creations and two of Playground's DeepMind
    Control tasks with their MJX env's model, reward and termination; the user's own
    ``MODULE:NAME``), ``mjx`` (Brax's or Playground's MJX env, vmapped; for Gymnasium's
    and the user's tasks their own model and formulas on MJX, `MjxPhysics`) or ``auto`` (native on CPU
    where the task has it, else MJX); ``physics_threads`` is native MuJoCo's thread
    count (0 = every core). A Gymnasium env (``gym:ID``, or the user's ``gymnasium.Env``) runs on
    ``gym``: a pool of copies on the host that reset themselves (`coherent_jax.envs.host_gym`).
    ``episode_length`` defaults to the task's own time limit.
    """

    def __init__(
        self,
        task: str,
        num_envs: int,
        episode_length: int | None = None,
        physics: str = "auto",
        physics_threads: int = DEFAULT_THREADS,
    ):
        spec = check_task(task)
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.task = task
        self.num_envs = int(num_envs)
        self.episode_length = int(episode_length or spec.episode_length)
        # "mjx", "native" (MuJoCo's C engine through a callback) or the task's own pipeline.
        self.physics = resolve_physics(task, physics)
        if self.physics == "gym":  # a Gymnasium env: a pool of copies on the host, reset there
            self.env = GymPhysics(load_user_task(task).gym, self.episode_length)
            self.observation_size, self.action_size = self.env.observation_size, self.env.action_size
            self._batch_reset, self._batch_step = self.env.reset, self.env.step
        elif self.physics == "native" or spec.backend == "native":
            # Native tasks' models on MuJoCo's C engine or on MJX: both take the whole batch
            # in one call; Brax envs are vmapped.
            if self.physics == "native":
                self.env = NativePhysics(task, physics_threads)
            else:
                self.env = MjxPhysics(task, native_task(task), mujoco_model(task))
            self.observation_size, self.action_size = self.env.observation_size, self.env.action_size
            self._batch_reset, self._batch_step = self.env.reset, self.env.step
        else:
            self.env = make_brax_env(task)
            self.observation_size, self.action_size = env_sizes(self.env)
            self._batch_reset, self._batch_step = jax.vmap(self.env.reset), jax.vmap(self.env.step)
        self.dt = float(self.env.dt)
        # The task terminates exactly at its goal: rollouts log the fraction that reach it.
        self.goal = spec.goal

    def _reset_physics(self, key: jax.Array):
        return self._batch_reset(jax.random.split(key, self.num_envs))

    def reset(self, key: jax.Array) -> EnvState:
        """Starts `num_envs` fresh episodes."""
        key, reset_key = jax.random.split(key)
        physics = self._reset_physics(reset_key)
        n = self.num_envs
        return EnvState(
            physics=physics,
            obs=physics.obs,
            first=jnp.ones((n,), bool),
            step=jnp.zeros((n,), jnp.int32),
            episode_return=jnp.zeros((n,), jnp.float32),
            key=key,
        )

    def step(self, state: EnvState, action: jax.Array) -> tuple[EnvState, StepOutcome]:
        """Steps every env with `action` [n, action_size] (clipped to [-1, 1])."""
        chex.assert_shape(action, (self.num_envs, self.action_size))
        action = jnp.clip(action, -1.0, 1.0)
        physics = self._batch_step(state.physics, action)
        reward = physics.reward.astype(jnp.float32)
        terminated = physics.done > 0.5
        step = state.step + 1
        truncated = jnp.logical_and(step >= self.episode_length, ~terminated)
        host_resets = isinstance(physics, GymState)  # the host reset the envs whose episode ended
        if host_resets:  # the env may truncate on its own too
            truncated = jnp.logical_or(truncated, physics.truncated)
        done = jnp.logical_or(terminated, truncated)
        ep_return = state.episode_return + reward
        outcome = StepOutcome(
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            final_obs=physics.final_obs if host_resets else physics.obs,
            episode_return=jnp.where(done, ep_return, 0.0),
        )

        key, reset_key = jax.random.split(state.key)

        def with_resets(phys):
            fresh = self._reset_physics(reset_key)
            return jax.tree.map(lambda f, p: _select(done, f, p), fresh, phys)

        if not host_resets:
            physics = jax.lax.cond(any_point(jnp.any(done)), with_resets, lambda p: p, physics)
        new_state = EnvState(
            physics=physics,
            obs=physics.obs,
            first=done,
            step=jnp.where(done, 0, step),
            episode_return=jnp.where(done, 0.0, ep_return),
            key=key,
        )
        return new_state, outcome


def _select(mask: jax.Array, on_true: jax.Array, on_false: jax.Array) -> jax.Array:
    """Per-env select broadcasting the [n] mask over trailing axes."""
    mask = jnp.reshape(mask, mask.shape + (1,) * (on_true.ndim - 1))
    return jnp.where(mask, on_true, on_false)
