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
import flax.linen as nn
import jax
import jax.numpy as jnp

from coherent_jax.exploration.action import gaussian_log_prob
from coherent_jax.exploration.base import ActOutput, Exploration, SegmentLogProb
from coherent_jax.networks import MLP, ActorDist, squash

_LOG_2PI = math.log(2.0 * math.pi)
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


class _Trunk(nn.Module):
    hidden: tuple[int, ...]
    activation: str
    action_size: int

    @nn.compact
    def __call__(self, obs):
        x = MLP(self.hidden, self.activation)(obs)
        mean = nn.Dense(self.action_size, kernel_init=nn.initializers.orthogonal(0.01))(x)
        return x, mean


class GeneralizedSDE(Exploration):
    """gSDE for A2C/PPO, and its noise function for SAC's behaviour.

    ``log_sigma`` starts at log(init_std / sqrt(q)): with features of unit mean square
    the initial action std is init_std.
    """

    name = "gsde"

    def __init__(self, action_size: int, hidden, activation: str, init_std: float, resample_every: int):
        self.action_size = int(action_size)
        self.feature_size = int(hidden[-1])
        self.net = _Trunk(tuple(hidden), activation, self.action_size)
        self.init_std = float(init_std)
        self.resample_every = int(resample_every)

    def init(self, key, obs_size):
        q, p = self.feature_size, self.action_size
        return {
            "net": self.net.init(key, jnp.zeros((1, obs_size))),
            "log_sigma": jnp.full((q, p), math.log(self.init_std / math.sqrt(q)), jnp.float32),
        }

    def init_carry(self, key, params, hparams, num_envs):
        return self._init_carry(key, num_envs)

    def _init_carry(self, key, num_envs):
        z = jax.random.normal(key, (num_envs, self.feature_size, self.action_size), jnp.float32)
        return GsdeCarry(z=z, step=jnp.zeros((num_envs,), jnp.int32))

    def _next_z(self, key, carry: GsdeCarry, first):
        """The z of this step: redrawn at an episode start and every ``resample_every`` steps."""
        chex.assert_rank(first, 1)
        redraw = jnp.logical_or(first, carry.step % self.resample_every == 0)
        fresh = jax.random.normal(key, carry.z.shape, carry.z.dtype)
        z = jnp.where(redraw[:, None, None], fresh, carry.z)
        step = jnp.where(redraw, 0, carry.step) + 1
        return z, GsdeCarry(z=z, step=step)

    def _dist(self, params, obs):
        x, mean = self.net.apply(params["net"], obs)
        sigma = jnp.exp(params["log_sigma"])
        return x, mean, gsde_log_std(jax.lax.stop_gradient(x), sigma)

    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        x, mean, log_std = self._dist(params, obs)
        z, carry = self._next_z(key, carry, first)
        noise = jnp.einsum("nq,nqp->np", x, jnp.exp(params["log_sigma"]) * z)
        action = mean + noise
        return ActOutput(action, gaussian_log_prob(action, mean, log_std), carry)

    def log_prob(self, params, hparams, carry0, obs, actions, first, extras=()):
        chex.assert_rank([obs, actions], 2)
        _, mean, log_std = self._dist(params, obs)
        entropy = jnp.sum(log_std + 0.5 * (_LOG_2PI + 1.0), axis=-1)
        return SegmentLogProb(gaussian_log_prob(actions, mean, log_std), entropy)

    def mean_action(self, params, obs):
        return self.net.apply(params["net"], obs)[1]

    def metrics(self, params, hparams):
        return {"gsde_sigma": jnp.mean(jnp.exp(params["log_sigma"]))}

    # ---------------------------------------------------- off-policy (SAC)
    # SAC's actor keeps its own state-dependent std; gSDE supplies the xi of its
    # sample tanh(mean + std xi) as the normalised noise function
    # xi_j(s) = z_j . x(s) / |x(s)|, which is N(0, 1) for each state and, with z held
    # for n steps, smooth along the trajectory (Raffin et al. §3 with sigma_ij = 1/|x|).
    def offpolicy_init_carry(self, key, actor, actor_params, hparams, num_envs):
        z = jax.random.normal(key, (num_envs, actor.feature_size, actor.action_size), jnp.float32)
        return GsdeCarry(z=z, step=jnp.zeros((num_envs,), jnp.int32))

    def offpolicy_act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        z, carry = self._next_z(key, carry, first)
        x = actor.features(actor_params, obs)
        xi = jnp.einsum("nq,nqp->np", x, z) / jnp.sqrt(jnp.sum(jnp.square(x), -1, keepdims=True) + _VAR_FLOOR)
        dist: ActorDist = actor.dist_from_features(actor_params, x)
        action, _ = squash(key, dist, noise=xi)
        return action, carry
