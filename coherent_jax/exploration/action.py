"""Gaussian action noise: the diagonal Gaussian policy of thesis eq. 2.1.

    pi(a | s) = N(W f_theta(s) + b, diag(exp(log_std)^2))                 (2.1)

with a state-independent, learned ``log_std``. Every step's noise is independent
(step-based exploration in action space, Figure 4.1 left).

It stands alone, small, because each strategy is a module of its own
(docs/strategies.md: a strategy is its module, one registry row, its settings group, its tests).
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.base import ActOutput, OnPolicyStrategy, SegmentLogProb
from coherent_jax.networks import MeanHead

_LOG_2PI = math.log(2.0 * math.pi)


def gaussian_log_prob(x: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """sum_i log N(x_i; mean_i, exp(log_std_i)^2) over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * _LOG_2PI, axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    """sum_i (log_std_i + 0.5 log(2 pi e)) over the last axis."""
    return jnp.sum(log_std + 0.5 * (_LOG_2PI + 1.0), axis=-1)


class ActionNoise(OnPolicyStrategy):
    """Diagonal Gaussian policy with state-independent learned log-std."""

    name = "action"

    def __init__(self, action_size: int, hidden, activation: str, init_std: float):
        self.action_size = int(action_size)
        self.net = MeanHead(tuple(hidden), activation, self.action_size)
        self.init_std = float(init_std)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std)

    def _mean(self, params, obs):
        return self.net.apply(params["mean"], obs)[1]

    def init(self, key, obs_size):
        return {
            "mean": self.net.init(key, jnp.zeros((1, obs_size))),
            "log_std": jnp.full((self.action_size,), math.log(self.init_std), jnp.float32),
        }

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank(obs, 2)
        mean = self._mean(params, obs)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        action = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape, mean.dtype)
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), carry)

    def log_prob(self, params, hparams, segment):
        segment.check()
        mean = self._mean(params, segment.obs)
        log_std = jnp.broadcast_to(params["log_std"], mean.shape)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        return self._mean(params, obs)

    def metrics(self, params, hparams):
        return {"action_std": jnp.mean(jnp.exp(params["log_std"]))}
