"""Networks: the policy trunk, the value network and observation normalisation.

The policy is split as in the thesis (§4.1): a trunk ``x_t = f_theta(s_t)`` whose
output feeds a linear last layer. The last layer belongs to the exploration
strategy (`coherent_jax.exploration`), because that is the part a strategy
perturbs, samples or integrates out.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "tanh": jnp.tanh,
    "relu": jax.nn.relu,
    "elu": jax.nn.elu,
    "swish": jax.nn.swish,
}
#: the orthogonal init's gain of a policy's linear mean head: small, so initial actions are near zero
HEAD_GAIN = 0.01


class MLP(nn.Module):
    """Dense layers with an activation after each, orthogonal init (gain sqrt 2)."""

    hidden: Sequence[int]
    activation: str = "tanh"
    layer_norm: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        for size in self.hidden:
            x = nn.Dense(size, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0)))(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = act(x)
        return x


class MeanHead(nn.Module):
    """The trunk x = f_theta(s), then the linear mean head W x + b of a Gaussian policy (eq. 2.1).

    The head starts small (orthogonal, ``head_gain`` 0.01, as in CleanRL/SB3) so that
    initial actions are near zero; a strategy whose noise passes through the head (Lattice)
    may start it larger. Returns (x [..., q], mean [..., p]): strategies whose noise is a
    function of the features (gSDE) need x as well.
    """

    hidden: tuple[int, ...]
    activation: str
    action_size: int
    layer_norm: bool = False
    head_gain: float = HEAD_GAIN

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = MLP(self.hidden, self.activation, layer_norm=self.layer_norm)(obs)
        return x, nn.Dense(self.action_size, kernel_init=nn.initializers.orthogonal(self.head_gain))(x)


def augment(x: jax.Array) -> jax.Array:
    """xh = [x; 1] along the last axis: the last layer's input with the bias folded in."""
    return jnp.concatenate([x, jnp.ones(x.shape[:-1] + (1,), x.dtype)], axis=-1)


class ValueNetwork(nn.Module):
    """V_phi(s): an MLP and a scalar head."""

    hidden: Sequence[int]
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = MLP(self.hidden, self.activation)(obs)
        return nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0))(x)[..., 0]


@struct.dataclass
class RunningStats:
    """Running mean and variance of observations (parallel Welford update)."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def create(cls, size: int) -> RunningStats:
        return cls(
            mean=jnp.zeros((size,), jnp.float32),
            var=jnp.ones((size,), jnp.float32),
            count=jnp.zeros((), jnp.float32),
        )


def update_stats(stats: RunningStats, batch: jax.Array) -> RunningStats:
    """Merges a batch [..., size] into the running statistics (Chan et al. 1979)."""
    chex.assert_axis_dimension(batch, -1, stats.mean.shape[0])
    batch = batch.reshape(-1, batch.shape[-1]).astype(jnp.float32)
    n = jnp.asarray(batch.shape[0], jnp.float32)
    b_mean = batch.mean(axis=0)
    b_var = batch.var(axis=0)
    total = stats.count + n
    delta = b_mean - stats.mean
    mean = stats.mean + delta * n / total
    m2 = stats.var * stats.count + b_var * n + delta**2 * stats.count * n / total
    return RunningStats(mean=mean, var=m2 / total, count=total)


def normalize(stats: RunningStats, obs: jax.Array, enabled: bool = True, clip: float = 10.0):
    """(obs - mean) / std, clipped to [-clip, clip]; identity when disabled."""
    if not enabled:
        return obs
    return jnp.clip((obs - stats.mean) / jnp.sqrt(stats.var + 1e-8), -clip, clip)


def scale_rewards(stats: RunningStats, rewards: jax.Array, clip: float = 10.0) -> jax.Array:
    """r / sqrt(Var[G] + 1e-8), clipped to [-clip, clip]: reward scaling by the running
    variance of the discounted return G (``stats`` of size 1; no mean is subtracted, so
    the sign of every reward, and with it termination's incentive, is kept)."""
    chex.assert_shape(stats.var, (1,))
    return jnp.clip(rewards / jnp.sqrt(stats.var[0] + 1e-8), -clip, clip)


LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
_HALF_LOG_2PI = 0.5 * float(jnp.log(2.0 * jnp.pi))


class ActorDist(NamedTuple):
    """The pre-squash Gaussian of SAC's actor for a batch of states.

    Attributes:
      mean: [..., p] mean of u before tanh.
      log_std: [..., p] log standard deviation of u, in [LOG_STD_MIN, LOG_STD_MAX].
    """

    mean: jax.Array
    log_std: jax.Array


def squash(key: jax.Array, dist: ActorDist, noise: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """a = tanh(mean + std xi), xi ~ N(0, I) (eq. 2.50), and log pi(a|s).

    log pi(a|s) = sum_i [log N(u_i; mean_i, std_i^2) - log(1 - tanh(u_i)^2)], with
    log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)) for stability. ``noise``, if
    given, is used as xi (coloured noise, or a test's fixed draw) instead of a draw
    from ``key``.
    """
    xi = jax.random.normal(key, dist.mean.shape, dist.mean.dtype) if noise is None else noise
    u = dist.mean + jnp.exp(dist.log_std) * xi
    log_det = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    log_prob = jnp.sum(-0.5 * xi**2 - dist.log_std - _HALF_LOG_2PI - log_det, axis=-1)
    return jnp.tanh(u), log_prob


class SquashedGaussianActor:
    """SAC's actor pi(a|s) = tanh(N(W xh + b, std(s)^2)) (thesis eq. 2.50).

    Split as the thesis splits every policy (§4.1): a trunk x = f_theta(s), then a
    linear *mean head* ``mu`` [p, q+1] (weights, bias last, acting on xh = [x; 1])
    that exploration strategies may perturb, and a state-dependent log-std head.
    Parameters: ``{"trunk", "mu", "log_std"}``; ``layer_norm`` puts LayerNorm
    between the trunk's layers (parameter-space noise wants it); ``head_gain`` is the mean
    head's orthogonal init gain (`MeanHead`).
    """

    def __init__(
        self,
        action_size: int,
        hidden: Sequence[int],
        activation: str,
        layer_norm: bool = False,
        head_gain: float = HEAD_GAIN,
    ):
        self.action_size = int(action_size)
        self.head_gain = float(head_gain)
        self.feature_size = int(hidden[-1])
        self.trunk = MLP(tuple(hidden), activation, layer_norm)
        self.log_std_head = nn.Dense(self.action_size, kernel_init=nn.initializers.orthogonal(0.01))

    def init(self, key: jax.Array, obs_size: int) -> dict:
        k_trunk, k_mu, k_std = jax.random.split(key, 3)
        q, p = self.feature_size, self.action_size
        w = nn.initializers.orthogonal(self.head_gain)(k_mu, (q, p), jnp.float32).T
        return {
            "trunk": self.trunk.init(k_trunk, jnp.zeros((1, obs_size))),
            "mu": jnp.concatenate([w, jnp.zeros((p, 1), jnp.float32)], axis=1),
            "log_std": self.log_std_head.init(k_std, jnp.zeros((1, q))),
        }

    def features(self, params: dict, obs: jax.Array) -> jax.Array:
        """x = f_theta(s), [..., q]."""
        return self.trunk.apply(params["trunk"], obs)

    def dist_from_features(self, params: dict, x: jax.Array, mu: jax.Array | None = None) -> ActorDist:
        """The Gaussian of u given features x [..., q] and a mean head ``mu``.

        ``mu`` defaults to the learned head [p, q+1]; a perturbed head may carry
        the batch dims of x in front ([..., p, q+1], one head per env).
        """
        mu = params["mu"] if mu is None else mu
        mean = jnp.einsum("...pk,...k->...p", mu, augment(x))
        raw = jnp.tanh(self.log_std_head.apply(params["log_std"], x))
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (raw + 1.0)
        return ActorDist(mean, log_std)

    def dist(self, params: dict, obs: jax.Array) -> ActorDist:
        return self.dist_from_features(params, self.features(params, obs))

    def mode(self, params: dict, obs: jax.Array) -> jax.Array:
        """The deterministic action tanh(mean) used for evaluation and (4.50)."""
        return jnp.tanh(self.dist(params, obs).mean)


class QNetwork(nn.Module):
    """Q_phi(s, a): an MLP on [s; a] and a scalar head."""

    hidden: Sequence[int]
    activation: str = "relu"

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = MLP(self.hidden, self.activation)(jnp.concatenate([obs, action], axis=-1))
        return nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0))(x)[..., 0]
