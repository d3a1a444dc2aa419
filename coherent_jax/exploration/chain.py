"""The beta-chain of coherent exploration (thesis eqs. 4.1-4.5), written once.

Every strategy that moves weights along the chain (coherent's last layer for A2C/PPO,
its single-sample and all-layer ablations, Coherent-SAC's mean head) calls `chain_step`:

    w_0 = mu + w_std eps                                                        (4.5)
    w_t = (1 - beta) w_{t-1} + beta mu + sqrt(2 beta - beta^2) w_std eps        (4.1-4.4)

so every w_t has marginal N(mu, diag(w_std^2)). With ``mean`` and ``std`` left out it is
the standardised chain z = (w - mu) / w_std: z_0 = eps, z_t = (1 - beta) z_{t-1} +
sqrt(2 beta - beta^2) eps. beta = 1 is step-based exploration (a fresh draw every
step), beta = 0 one draw for as long as the chain runs unbroken: an episode where only
episode starts restart it (``coherent.gradient=episode`` or ``stored``, the Monte Carlo
forms, SAC), a segment of ``unroll_length`` steps under ``coherent.gradient=exact``.
"""

from __future__ import annotations

from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp


class ChainParams(NamedTuple):
    """The parameters of the chain over the last layer, read by every inference function.

    The model they define (thesis eqs. 4.1-4.5 and 4.29), with xh = [x; 1]:

        a_t,i | w_t ~ N(w_t,i . xh_t, action_std_i^2)                              (4.29)
        w_0 ~ N(mu, diag(w_std^2)),  w_t = (1 - beta) w_{t-1} + beta mu
                                          + sqrt(2 beta - beta^2) w_std eps          (4.1-4.5)

    Build it with `chain_params`, which checks the shapes.

    Attributes:
      mu: [p, q+1] mean of the last-layer weights, bias in the last column.
      w_std: [p, q+1] standard deviation of each weight.
      action_std: [p] action noise standard deviation.
      beta: scalar in [0, 1], the chain's mixing rate (may be traced).
    """

    mu: chex.Array
    w_std: chex.Array
    action_std: chex.Array
    beta: chex.Array

    @property
    def shape(self) -> tuple[int, int]:
        """(p, q+1): action dimensions and last-layer inputs with the bias."""
        return self.mu.shape

    def astype(self, dtype) -> ChainParams:
        """Every field as an array of ``dtype``."""
        return ChainParams(*(jnp.asarray(v).astype(dtype) for v in self))


def chain_params(mu: chex.Array, w_std: chex.Array, action_std: chex.Array, beta: chex.Array) -> ChainParams:
    """`ChainParams` after checking mu, w_std [p, q+1], action_std [p] and beta a scalar.

    The values are kept as given (no cast), so building it changes no computation.
    """
    chex.assert_rank([mu, w_std, action_std, jnp.asarray(beta)], [2, 2, 1, 0])
    chex.assert_equal_shape([mu, w_std])
    chex.assert_shape(action_std, (mu.shape[0],))
    return ChainParams(mu, w_std, action_std, beta)


def innovation_var(beta: chex.Array) -> chex.Array:
    """2 beta - beta^2 = beta (2 - beta), clipped at 0 for beta a rounding below 0.

    ``where`` rather than ``maximum`` keeps the derivative 2 - 2 beta at beta = 0.
    """
    v = beta * (2.0 - beta)
    return jnp.where(v >= 0.0, v, jnp.zeros_like(v))


def innovation_std(beta: chex.Array) -> chex.Array:
    """sqrt(2 beta - beta^2) with a finite (zero) gradient at beta = 0."""
    v = innovation_var(beta)
    positive = v > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, v, jnp.ones_like(v))), 0.0)


def chain_step(
    key: chex.PRNGKey,
    prev: chex.Array,
    first: chex.Array,
    beta: chex.Array,
    mean: chex.Array | None = None,
    std: chex.Array | None = None,
) -> chex.Array:
    """The chain's next draw: (4.5) where ``first``, else (4.1-4.4); one eps for both.

    Args:
      key: PRNG key of eps ~ N(0, I) (one draw of ``prev``'s shape).
      prev: [*b, ...] the previous draw w_{t-1} (ignored where ``first``).
      first: [*b] bool, True where an episode starts at this step (rank 0 for one chain).
      beta: scalar in [0, 1].
      mean: mu, broadcast against ``prev``; None for the standardised chain (mu = 0).
      std: w_std, broadcast against ``prev``; None for the standardised chain (w_std = 1).

    Returns:
      w_t, shaped like ``prev``. beta = 0 returns ``prev`` exactly where not ``first``;
      beta = 1 returns the draw of an episode start.
    """
    chex.assert_rank(jnp.asarray(beta), 0)
    dtype = jnp.result_type(*(v for v in (prev, mean, std) if v is not None))
    beta = jnp.asarray(beta).astype(dtype)
    eps = jax.random.normal(key, prev.shape, dtype)
    noise = eps if std is None else std * eps
    initial = noise if mean is None else mean + noise
    drift = (1.0 - beta) * prev if mean is None else (1.0 - beta) * prev + beta * mean
    following = drift + innovation_std(beta) * noise
    first = jnp.asarray(first)
    return jnp.where(first.reshape(first.shape + (1,) * (prev.ndim - first.ndim)), initial, following)
