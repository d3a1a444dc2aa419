"""The coherent chain's per-step samplers and a segment shorthand, as the tests use them.

The library draws the chain in standardised coordinates inside each strategy
(`coherent_jax.exploration.chain.chain_step`); these are the same draws in weight
coordinates, one env and one step at a time, which the filter's tests check against
the thesis's equations (4.1)-(4.5) and (4.29).
"""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.chain import ChainParams, chain_step
from coherent_jax.exploration.coherent.filter import Belief, segment_marginals
from coherent_jax.networks import augment


def log_marginals_from(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
    remat: bool = False,
) -> tuple[chex.Array, Belief]:
    """log p(a_t | a_<t, s_<=t) over a segment that starts from ``belief0``.

    `coherent_jax.exploration.coherent.filter.segment_marginals` without the predictive variances; returns
    (logp [T], final belief).
    """
    logp, final_belief, _ = segment_marginals(
        belief0, x, a, first, ChainParams(mu, w_std, action_std, beta), remat
    )
    return logp, final_belief


def sample_initial_weights(key: chex.PRNGKey, mu: chex.Array, w_std: chex.Array) -> chex.Array:
    """w_0 = mu + w_std * eps, eps ~ N(0, I) (4.5): `step_weights` at an episode start.

    Args:
      key: PRNG key.
      mu: [p, q+1] weight mean.
      w_std: [p, q+1] weight standard deviation.

    Returns:
      w [p, q+1].
    """
    chex.assert_rank([mu, w_std], 2)
    chex.assert_equal_shape([mu, w_std])
    return chain_step(key, mu, True, 0.0, mean=mu, std=w_std)


def sample_next_weights(
    key: chex.PRNGKey,
    w_prev: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    beta: chex.Array,
) -> chex.Array:
    """w_t = (1 - beta) w_{t-1} + beta mu + sqrt(2 beta - beta^2) w_std * eps (4.1-4.4).

    Leaves N(mu, diag(w_std^2)) invariant. beta = 0 returns ``w_prev`` exactly and
    beta = 1 ignores it: mu + w_std * eps with the eps `sample_initial_weights` draws
    from the same key.

    Args:
      key: PRNG key.
      w_prev: [p, q+1] w_{t-1}.
      mu: [p, q+1] weight mean.
      w_std: [p, q+1] weight standard deviation.
      beta: scalar in [0, 1].

    Returns:
      w_t [p, q+1].
    """
    chex.assert_rank([w_prev, mu, w_std], 2)
    chex.assert_equal_shape([w_prev, mu, w_std])
    return chain_step(key, w_prev, False, beta, mean=mu, std=w_std)


def step_weights(
    key: chex.PRNGKey,
    w_prev: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    beta: chex.Array,
) -> chex.Array:
    """The chain's next draw: from the prior (4.5) if ``first``, else (4.1-4.4).

    Both branches use the same eps, so with ``first`` this equals
    ``sample_initial_weights(key, mu, w_std)``.

    Args:
      key: PRNG key.
      w_prev: [p, q+1] the env's previous weights (ignored if ``first``).
      first: bool scalar, True if an episode starts at this step.
      mu: [p, q+1] weight mean.
      w_std: [p, q+1] weight standard deviation.
      beta: scalar in [0, 1].

    Returns:
      w_t [p, q+1].
    """
    chex.assert_rank(first, 0)
    chex.assert_rank([w_prev, mu, w_std], 2)
    return chain_step(key, w_prev, first, beta, mean=mu, std=w_std)


def sample_action(key: chex.PRNGKey, w: chex.Array, x: chex.Array, action_std: chex.Array) -> chex.Array:
    """a_t ~ N(w_t xh_t, diag(action_std^2)) (4.29).

    Args:
      key: PRNG key.
      w: [p, q+1] the sampled last-layer weights w_t, bias last.
      x: [q] last-layer input x_t.
      action_std: [p] action noise standard deviation.

    Returns:
      a_t [p].
    """
    chex.assert_rank([w, x, action_std], [2, 1, 1])
    p, n = w.shape
    chex.assert_shape(x, (n - 1,))
    chex.assert_shape(action_std, (p,))
    mean = w @ augment(x)
    eps = jax.random.normal(key, (p,), dtype=jnp.result_type(mean, action_std))
    return mean + action_std * eps
