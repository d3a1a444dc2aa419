"""The on-policy trainer's state types: `TrainState` and its parts (`HParams`, `AgentParams`,
`RewardNorm`, `SplitOptState`).

Their own module because both the trainer (`coherent_jax.agents.onpolicy`) and its
losses (`coherent_jax.agents.losses`) read them, and the trainer imports the losses.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from coherent_jax.envs.vec_env import EnvState
from coherent_jax.networks import RunningStats


@struct.dataclass
class HParams:
    """Scalars that may vary across the points of a vmapped sweep (all arrays).

    ``vf_lr`` is None (no leaf, so the state of a joint-loss run is what it always was)
    unless the value function has its own optimiser (``vf_iters > 0``).
    """

    lr: jax.Array
    gamma: jax.Array
    gae_lambda: jax.Array
    clip_eps: jax.Array
    target_kl: jax.Array
    vf_coef: jax.Array
    ent_coef: jax.Array
    explore: Any  # the strategy's own hyperparameters (a flax.struct.dataclass)
    vf_lr: jax.Array | None = None


@struct.dataclass
class RewardNorm:
    """Reward scaling's state (``normalize_rewards``).

    Attributes:
      stats: running variance of the discounted return, over every env and step (size 1).
      discounted_return: [n] each env's discounted return so far in its episode.
    """

    stats: RunningStats
    discounted_return: jax.Array

    @classmethod
    def create(cls, num_envs: int) -> RewardNorm:
        return cls(stats=RunningStats.create(1), discounted_return=jnp.zeros((num_envs,), jnp.float32))


@struct.dataclass
class AgentParams:
    policy: Any
    value: Any


@struct.dataclass
class SplitOptState:
    """The optimiser state of a separately trained value function (``vf_iters > 0``).

    Attributes:
      policy: the policy's Adam state (its steps at ``lr``).
      value: the value function's own Adam state (its steps at ``vf_lr``).
    """

    policy: Any
    value: Any


@struct.dataclass
class TrainState:
    """Everything an iteration reads and writes.

    Attributes:
      params: policy (trunk + exploration head) and value parameters.
      opt_state: Adam state: of all parameters (joint loss), or a `SplitOptState`.
      obs_stats: running observation statistics.
      env_state: the vectorized environments.
      carry: per-env exploration state (noise, sampled weights, beliefs).
      reward_norm: reward scaling's statistics (left at their initial values unless
        ``normalize_rewards``).
      hparams: sweepable scalars.
      key: PRNG key.
      iteration: iterations done.
      env_steps: environment steps done.
      history: each env's last ``strategy.history_length`` steps (`EpisodeHistory`), or
        () for a strategy that reads none.
    """

    params: AgentParams
    opt_state: Any
    obs_stats: RunningStats
    env_state: EnvState
    carry: Any
    reward_norm: RewardNorm
    hparams: HParams
    key: jax.Array
    iteration: jax.Array
    env_steps: jax.Array
    history: Any = ()
