"""Generalized state-dependent exploration, gSDE (Raffin et al. 2021).

The action noise is a linear function of the policy's last-layer features x(s) (the
trunk output, q of them) through a random matrix E [q, p] that is held fixed for
``resample_every`` steps:

    a_t = mean(s_t) + E^T x(s_t),     E_ij ~ N(0, sigma_ij^2)                 (gSDE, eq. 4)

so the noise is smooth along a trajectory (the same E on nearby states gives nearby
noise) and a fresh E is drawn every n steps and at each episode start. sigma [q, p] is
learned (``log_sigma``). For a given state the noise is Gaussian with

    a_t,j | s_t ~ N(mean_j(s_t), sum_i x_i(s_t)^2 sigma_ij^2)                 (gSDE, eq. 5)

which is the log-probability the on-policy losses use, as in the paper. As in its
reference implementation (``learn_features=False``), the features enter the variance
through a stop-gradient, so the variance trains sigma only and the trunk is shaped by
the mean. A small floor (1e-6) on the variance keeps the log-probability finite where
all features vanish.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.action import gaussian_entropy, gaussian_log_prob
from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour, OnPolicyStrategy, SegmentLogProb
from coherent_jax.networks import ActorDist, MeanHead, squash

_VAR_FLOOR = 1e-6


def gsde_log_std(x: chex.Array, sigma: chex.Array) -> chex.Array:
    """The state-dependent log-std (gSDE eq. 5), [..., q] -> [..., p]: log sqrt(sum_i x_i^2 sigma_ij^2)."""
    chex.assert_rank(sigma, 2)
    var = jnp.square(x) @ jnp.square(sigma) + _VAR_FLOOR
    return 0.5 * jnp.log(var)


class GsdeCarry(NamedTuple):
    """Per-env state.

    Attributes:
      z: [n, q, p] the standard-normal draw behind the noise matrix, E = sigma * z
        (kept standardised so an update of sigma applies at once).
      step: [n] int32, steps since z was drawn.
    """

    z: jax.Array
    step: jax.Array


def next_z(key: chex.PRNGKey, carry: GsdeCarry, first: chex.Array, resample_every: int):
    """The z of this step: redrawn at an episode start and every ``resample_every`` steps."""
    chex.assert_rank(first, 1)
    redraw = jnp.logical_or(first, carry.step % resample_every == 0)
    fresh = jax.random.normal(key, carry.z.shape, carry.z.dtype)
    z = jnp.where(redraw[:, None, None], fresh, carry.z)
    step = jnp.where(redraw, 0, carry.step) + 1
    return z, GsdeCarry(z=z, step=step)


def init_gsde_carry(key: chex.PRNGKey, num_envs: int, feature_size: int, action_size: int) -> GsdeCarry:
    z = jax.random.normal(key, (num_envs, feature_size, action_size), jnp.float32)
    return GsdeCarry(z=z, step=jnp.zeros((num_envs,), jnp.int32))


class GeneralizedSDE(OnPolicyStrategy):
    """gSDE for A2C/PPO.

    ``log_sigma`` starts at log(init_std / sqrt(q)): with features of unit mean square
    the initial action std is init_std.
    """

    name = "gsde"

    def __init__(self, action_size: int, hidden, activation: str, init_std: float, resample_every: int):
        self.action_size = int(action_size)
        self.feature_size = int(hidden[-1])
        self.net = MeanHead(tuple(hidden), activation, self.action_size)
        self.init_std = float(init_std)
        self.resample_every = int(resample_every)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(action_size, cfg.policy_hidden, cfg.activation, cfg.init_std, cfg.gsde.resample_every)

    def init(self, key, obs_size):
        q, p = self.feature_size, self.action_size
        return {
            "net": self.net.init(key, jnp.zeros((1, obs_size))),
            "log_sigma": jnp.full((q, p), math.log(self.init_std / math.sqrt(q)), jnp.float32),
        }

    def init_carry(self, key, params, hparams, num_envs):
        return init_gsde_carry(key, num_envs, self.feature_size, self.action_size)

    def _dist(self, params, obs):
        x, mean = self.net.apply(params["net"], obs)
        sigma = jnp.exp(params["log_sigma"])
        return x, mean, gsde_log_std(jax.lax.stop_gradient(x), sigma)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        x, mean, log_std = self._dist(params, obs)
        z, carry = next_z(key, carry, first, self.resample_every)
        noise = jnp.einsum("nq,nqp->np", x, jnp.exp(params["log_sigma"]) * z)
        action = mean + noise
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), carry)

    def log_prob(self, params, hparams, segment):
        segment.check()
        _, mean, log_std = self._dist(params, segment.obs)
        return SegmentLogProb(gaussian_log_prob(segment.action, mean, log_std), gaussian_entropy(log_std))

    def mean_action(self, params, obs):
        return self.net.apply(params["net"], obs)[1]

    def metrics(self, params, hparams):
        return {"gsde_sigma": jnp.mean(jnp.exp(params["log_sigma"]))}


class GsdeBehaviour(OffPolicyBehaviour):
    """gSDE's noise function as the xi of SAC's sample tanh(mean + std xi).

    SAC's actor keeps its own state-dependent std; gSDE supplies its xi as the
    normalised noise function xi_j(s) = z_j . x(s) / |x(s)|, which is N(0, 1) for each
    state and, with z held for n steps, smooth along the trajectory (Raffin et al. §3
    with sigma_ij = 1/|x|).
    """

    name = "gsde"

    def __init__(self, resample_every: int):
        self.resample_every = int(resample_every)

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(cfg.gsde.resample_every)

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        return init_gsde_carry(key, num_envs, actor.feature_size, actor.action_size)

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        z, carry = next_z(key, carry, first, self.resample_every)
        x = actor.features(actor_params, obs)
        xi = jnp.einsum("nq,nqp->np", x, z) / jnp.sqrt(jnp.sum(jnp.square(x), -1, keepdims=True) + _VAR_FLOOR)
        dist: ActorDist = actor.dist_from_features(actor_params, x)
        action, _ = squash(key, dist, noise=xi)
        return action, carry
