"""Collection: a `lax.scan` of one actor step over the vectorized environments."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from coherent_jax.envs.vec_env import EnvState, VecEnv
from coherent_jax.exploration.base import ActOutput


class Transition(NamedTuple):
    """One step of every env; stacked by `unroll` into time-major [T, n, ...].

    Attributes:
      obs: s_t, raw (unnormalised).
      first: s_t is the first state of an episode (the strategy resets there).
      action: a_t before clipping to the action bounds.
      log_prob: log pi_behaviour(a_t | history).
      reward: r_t.
      terminated: s'_t is terminal.
      truncated: the time limit ended the episode at s'_t.
      final_obs: s'_t, the state the step reached, before any auto-reset.
      episode_return: return of the episode that ended here, else 0.
      extras: the strategy's per-step noise (`ActOutput.extras`), for its `log_prob`.
    """

    obs: jax.Array
    first: jax.Array
    action: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    final_obs: jax.Array
    episode_return: jax.Array
    extras: Any = ()

    @property
    def done(self) -> jax.Array:
        return jnp.logical_or(self.terminated, self.truncated)


class EpisodeHistory(NamedTuple):
    """Each env's last H steps before the current segment, time-major [H, n, ...].

    What a strategy with ``history_length = H > 0`` reads before each segment (coherent's
    episode prefix, ``coherent.gradient=episode``). Observations are raw, so that the
    trainer normalises them with the statistics of the iteration that reads them. Before
    any step was taken the rows are padding: ``first`` is True there, so each padding
    step is an episode of its own and changes nothing after it.

    Attributes:
      obs: [H, n, o] s_t, raw.
      action: [H, n, p] a_t.
      first: [H, n] bool, s_t starts an episode.
    """

    obs: jax.Array
    action: jax.Array
    first: jax.Array

    @classmethod
    def empty(cls, length: int, num_envs: int, obs_size: int, action_size: int) -> EpisodeHistory:
        return cls(
            obs=jnp.zeros((length, num_envs, obs_size), jnp.float32),
            action=jnp.zeros((length, num_envs, action_size), jnp.float32),
            first=jnp.ones((length, num_envs), bool),
        )

    def extend(self, data: Transition) -> EpisodeHistory:
        """The last H steps once the segment ``data`` [T, n] has been taken."""
        length = self.first.shape[0]
        join = lambda old, new: jnp.concatenate([old, new.astype(old.dtype)])[-length:]  # noqa: E731
        obs, action = join(self.obs, data.obs), join(self.action, data.action)
        return EpisodeHistory(obs=obs, action=action, first=join(self.first, data.first))


# act(key, carry, raw_obs, first) -> ActOutput
ActFn = Callable[[jax.Array, Any, jax.Array, jax.Array], ActOutput]


def unroll(
    env: VecEnv, act: ActFn, env_state: EnvState, carry: Any, key: jax.Array, length: int
) -> tuple[EnvState, Any, Transition]:
    """Runs `length` steps of `num_envs` envs; returns final states and [T, n] data."""

    def step(state, step_key):
        env_state, carry = state
        out = act(step_key, carry, env_state.obs, env_state.first)
        next_env_state, outcome = env.step(env_state, out.action)
        transition = Transition(
            obs=env_state.obs,
            first=env_state.first,
            action=out.action,
            log_prob=out.log_prob,
            reward=outcome.reward,
            terminated=outcome.terminated,
            truncated=outcome.truncated,
            final_obs=outcome.final_obs,
            episode_return=outcome.episode_return,
            extras=out.extras,
        )
        return (next_env_state, out.carry), transition

    (env_state, carry), data = jax.lax.scan(step, (env_state, carry), jax.random.split(key, length))
    return env_state, carry, data


def evaluate_policy(
    env: VecEnv, policy: Callable[[jax.Array], jax.Array], key: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Runs one episode in each of ``env.num_envs`` envs with a deterministic policy.

    Returns (episode returns [n], episode lengths [n]); an env that neither
    terminates nor truncates within ``episode_length`` steps cannot exist, since
    the time limit always ends it.
    """
    returns, lengths, _ = evaluate_episodes(env, policy, key)
    return returns, lengths


def evaluate_episodes(
    env: VecEnv, policy: Callable[[jax.Array], jax.Array], key: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`evaluate_policy`'s episodes: (returns [n], lengths [n], terminated [n]), the last True
    where the episode ended in a terminal state rather than at the time limit."""
    n = env.num_envs

    def step(state, _):
        env_state, returns, lengths, terminated, running = state
        env_state, outcome = env.step(env_state, policy(env_state.obs))
        returns = returns + jnp.where(running, outcome.reward, 0.0)
        lengths = lengths + running.astype(jnp.int32)
        terminated = jnp.logical_or(terminated, jnp.logical_and(running, outcome.terminated))
        running = jnp.logical_and(running, ~outcome.done)
        return (env_state, returns, lengths, terminated, running), None

    zeros = jnp.zeros((n,), bool)
    init = (env.reset(key), jnp.zeros((n,)), jnp.zeros((n,), jnp.int32), zeros, ~zeros)
    (_, returns, lengths, terminated, _), _ = jax.lax.scan(step, init, None, length=env.episode_length)
    return returns, lengths, terminated


def episode_metrics(data: Transition, goal: bool = False) -> dict[str, jax.Array]:
    """``train/*`` episode figures of one collected segment [T, n].

    episode_return: mean return of the episodes that ended in the segment (NaN if none).
    goal_reached (a task whose termination is its goal, `TaskSpec.goal`, only): the fraction
    of those episodes that reached it (NaN if none ended).
    """
    n_done = data.done.sum()

    def per_episode(total: jax.Array) -> jax.Array:
        return jnp.where(n_done > 0, total / jnp.maximum(n_done, 1), jnp.nan)

    metrics = {
        "train/episode_return": per_episode(jnp.sum(data.episode_return)),
        "train/episodes": n_done.astype(jnp.float32),
        "train/reward_mean": data.reward.mean(),
    }
    if goal:
        metrics["train/goal_reached"] = per_episode(data.terminated.sum().astype(jnp.float32))
    return metrics


def evaluation_metrics(
    env: VecEnv, policy: Callable[[jax.Array], jax.Array], key: jax.Array
) -> dict[str, jax.Array]:
    """``eval/*`` figures of one deterministic episode per env (`evaluate_policy`); on a task
    whose termination is its goal (`VecEnv.goal`) also ``eval/goal_reached``, the fraction
    of the episodes that reached it."""
    returns, lengths, terminated = evaluate_episodes(env, policy, key)
    metrics = {
        "eval/episode_return": returns.mean(),
        "eval/episode_return_std": returns.std(),
        "eval/episode_length": lengths.astype(jnp.float32).mean(),
    }
    if env.goal:
        metrics["eval/goal_reached"] = terminated.astype(jnp.float32).mean()
    return metrics
