"""Exact inference over the coherent last-layer weights (thesis §4.1–4.2).

Deep Coherent Exploration perturbs only the policy's last layer. With ``x`` in R^q the
last-layer input, ``xh = [x; 1]`` and one weight row ``w_i = [W_i, b_i]`` in R^(q+1)
per action dimension i (p of them):

    a_t,i | w_t ~ N(w_t,i . xh_t, action_std_i^2)                                (4.29)
    w_0   ~ N(mu, diag(w_std^2))                                                  (4.5)
    w_t   = (1 - beta) w_{t-1} + beta mu + sqrt(2 beta - beta^2) w_std * eps     (4.1-4.4)

so every w_t has marginal N(mu, diag(w_std^2)); beta = 1 is step-based exploration
(fresh weights each step), beta = 0 one draw per chain (per episode, or per segment
where ``coherent.gradient=exact`` restarts the chain at every segment start).

The on-policy objective needs ``log p(a_t | a_<t, s_<=t)`` with w integrated out
(4.18). The thesis computes it with a Kalman filter over the flattened (pq+p)-vector
(4.33–4.49). Because ``diag(w_std^2)`` and ``diag(action_std^2)`` are diagonal and row
i of X_t (4.31) only touches w_i, that Gaussian is block diagonal at every step: the
dense recursion is exactly p independent filters over (q+1)-vectors, each observing
one scalar per step. That is what this module runs, at O(p (q+1)^2) per step instead
of O((p (q+1))^3).

All functions are pure, work on one env (callers ``jax.vmap`` over envs, seeds or
hyperparameters), keep the dtype of their inputs and are differentiable with respect
to ``x``, ``mu``, ``w_std`` and ``action_std``. ``beta`` may be a traced scalar so a
sweep over it is one program; beta = 0 and beta = 1 are exact special cases.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.chain import ChainParams, innovation_var
from coherent_jax.networks import augment

_LOG_2PI = math.log(2.0 * math.pi)


class Belief(NamedTuple):
    """The belief alpha(w_t) = N(mean, cov) over the last layer, before a_t (4.44).

    Row i is the Gaussian over w_t,i, the weights (bias last) of action dimension i;
    different rows are independent, so only the p diagonal (q+1)x(q+1) blocks of the
    thesis's L_t^-1 are stored.

    Attributes:
      mean: [p, q+1] v_t of (4.45), one row per action dimension.
      cov: [p, q+1, q+1] the diagonal blocks of L_t^-1 of (4.46).
    """

    mean: chex.Array
    cov: chex.Array


def _check_params(params: ChainParams) -> tuple[int, int]:
    """Asserts mu, w_std [p, q+1], action_std [p] and a scalar beta; returns (p, q+1)."""
    chex.assert_rank([params.mu, params.w_std, params.action_std, jnp.asarray(params.beta)], [2, 2, 1, 0])
    chex.assert_equal_shape([params.mu, params.w_std])
    p, n = params.mu.shape
    chex.assert_shape(params.action_std, (p,))
    return p, n


def prior_belief(mu: chex.Array, w_std: chex.Array) -> Belief:
    """alpha(w_0) = N(mu, diag(w_std^2)), the belief at an episode start (4.33).

    Args:
      mu: [p, q+1] mean of the last-layer weights, bias in the last column.
      w_std: [p, q+1] prior standard deviation of each weight (Lambda^-1/2).

    Returns:
      Belief with mean [p, q+1] and cov [p, q+1, q+1].
    """
    chex.assert_rank([mu, w_std], 2)
    chex.assert_equal_shape([mu, w_std])
    dtype = jnp.result_type(mu, w_std)
    n = mu.shape[-1]
    cov = jnp.eye(n, dtype=dtype) * jnp.square(w_std).astype(dtype)[:, None, :]
    return Belief(mean=mu.astype(dtype), cov=cov)


def filter_step(
    belief: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
) -> tuple[Belief, chex.Array]:
    """One step of the exact filter (see `filter_step_with_variance`); returns (belief, logp)."""
    new_belief, logp, _ = filter_step_with_variance(belief, x, a, first, params)
    return new_belief, logp


def filter_step_with_variance(
    belief: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
) -> tuple[Belief, chex.Array, chex.Array]:
    """One step of the exact filter: score a_t, condition on it, propagate to t+1.

    With (m_i, P_i) the belief over w_t,i (the prior if ``first``):

        s_i   = action_std_i^2 + xh' P_i xh
        log p(a_t | history) = sum_i log N(a_t,i; m_i . xh, s_i)          (4.37)/(4.49)
        k_i   = P_i xh / s_i                                              (4.40)-(4.42)
        m_i  <- m_i + k_i (a_t,i - m_i . xh)
        P_i  <- (I - k_i xh') P_i (I - k_i xh')' + action_std_i^2 k_i k_i'
        m_i  <- (1 - beta) m_i + beta mu_i                                 (4.45)
        P_i  <- (1 - beta)^2 P_i + (2 beta - beta^2) diag(w_std_i^2)       (4.46)

    The covariance update is Joseph's form: it equals P - k (P xh)' in exact
    arithmetic, but an error in k only enters it at second order, which keeps P
    positive semi-definite while it shrinks like 1/t at beta = 0. It is evaluated as
    two rank-1 corrections, (A P) - (A P xh) k' + r k k', so it costs O((q+1)^2) like
    the short form, and is then symmetrised. s is floored at action_std^2, its
    analytic lower bound, so log s and 1/s are always finite.

    Args:
      belief: alpha(w_t) before a_t, mean [p, q+1], cov [p, q+1, q+1]; ignored if
        ``first``.
      x: [q] last-layer input x_t.
      a: [p] action a_t (before any squashing).
      first: bool scalar, True if an episode starts at t (belief reset to the prior).
      params: the chain's mu [p, q+1] (bias last), w_std [p, q+1], action_std [p]
        (Lambda_a^-1/2) and beta, a scalar in [0, 1].

    Returns:
      (belief over w_{t+1} before a_{t+1}, log p(a_t | a_<t, s_<=t) as a scalar,
      the predictive variances s [p]).
    """
    p, n = _check_params(params)
    mu, w_std, action_std, beta = params
    chex.assert_shape([belief.mean], (p, n))
    chex.assert_shape([belief.cov], (p, n, n))
    chex.assert_shape(x, (n - 1,))
    chex.assert_shape(a, (p,))
    chex.assert_rank(first, 0)

    prior = prior_belief(mu, w_std)
    mean = jnp.where(first, prior.mean, belief.mean)
    cov = jnp.where(first, prior.cov, belief.cov)

    xh = augment(x)
    noise_var = jnp.square(action_std)
    cov_xh = cov @ xh  # [p, n], P_i xh
    pred_mean = mean @ xh  # [p]
    # xh' P xh >= 0 analytically; the floor keeps s >= action_std^2 under rounding.
    pred_var = noise_var + jnp.maximum(cov_xh @ xh, 0.0)  # [p]
    innov = a - pred_mean
    logp = -0.5 * jnp.sum(_LOG_2PI + jnp.log(pred_var) + jnp.square(innov) / pred_var)

    gain = cov_xh / pred_var[:, None]  # [p, n]
    post_mean = mean + gain * innov[:, None]
    # Joseph form: A P A' + r k k' with A = I - k xh', as (A P) - (A P xh) k' + r k k'.
    a_cov = cov - gain[:, :, None] * cov_xh[:, None, :]  # A P (P symmetric)
    a_cov_xh = a_cov @ xh  # A P xh
    post_cov = (
        a_cov
        - a_cov_xh[:, :, None] * gain[:, None, :]
        + noise_var[:, None, None] * gain[:, :, None] * gain[:, None, :]
    )
    post_cov = 0.5 * (post_cov + jnp.swapaxes(post_cov, -1, -2))

    decay = 1.0 - beta
    new_mean = decay * post_mean + beta * mu
    new_cov = jnp.square(decay) * post_cov + innovation_var(beta) * prior.cov
    return Belief(mean=new_mean, cov=new_cov), logp, pred_var


def segment_inputs(belief0: Belief, x, a, first, params: ChainParams):
    """Checks the shapes of a segment's inputs and casts them to one dtype.

    One dtype for the whole computation (and a scan's carry): float64 under x64 if
    any input is, else float32. Returns the inputs in the order given.
    """
    p, n = _check_params(params)
    mu, w_std, action_std, _ = params
    chex.assert_rank([x, a, first], [2, 2, 1])
    num_steps = x.shape[0]
    chex.assert_shape(x, (num_steps, n - 1))
    chex.assert_shape(a, (num_steps, p))
    chex.assert_shape(first, (num_steps,))
    chex.assert_shape([belief0.mean], (p, n))
    chex.assert_shape([belief0.cov], (p, n, n))
    dtype = jnp.result_type(x, a, mu, w_std, action_std, belief0.mean, belief0.cov)
    cast = lambda v: jnp.asarray(v).astype(dtype)  # noqa: E731
    belief0 = Belief(mean=cast(belief0.mean), cov=cast(belief0.cov))
    return belief0, cast(x), cast(a), jnp.asarray(first, dtype=bool), params.astype(dtype)


def predictive_entropy(pred_var: chex.Array) -> chex.Array:
    """Entropy of the predictive Gaussian of each step, 0.5 sum_i log(2 pi e s_i); [T, p] -> [T]."""
    return 0.5 * jnp.sum(_LOG_2PI + 1.0 + jnp.log(pred_var), axis=-1)


def segment_marginals(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
    remat: bool = False,
) -> tuple[chex.Array, Belief, chex.Array]:
    """log p(a_t | a_<t, s_<=t) over a segment that starts from a given belief.

    ``lax.scan`` of `filter_step`. This is what a trainer uses across rollout
    segments: a segment that starts mid-episode starts from the belief stored when it
    was collected, and ``first[t]`` still resets to the prior inside the segment.
    Gradients flow into ``belief0`` if it is traced; a trainer that treats the stored
    belief as a constant (like a recurrent policy's stored hidden state) should pass
    it through ``jax.lax.stop_gradient``.

    Args:
      belief0: alpha(w_0) of the segment, mean [p, q+1], cov [p, q+1, q+1]; used at
        t = 0 unless ``first[0]``.
      x: [T, q] last-layer inputs.
      a: [T, p] actions taken.
      first: [T] bool, True where an episode starts at t.
      params: the chain's mu [p, q+1] (bias last), w_std [p, q+1], action_std [p] and
        beta, a scalar in [0, 1].
      remat: if True the scan body is ``jax.checkpoint``ed: the backward pass
        recomputes each step's intermediates from the stored belief instead of keeping
        several [p, q+1, q+1] arrays per step.

    Returns:
      (logp [T], the belief over w_T before a_T to start the next segment, the
      predictive variances s [T, p] of every step).
    """
    belief0, x, a, first, params = segment_inputs(belief0, x, a, first, params)

    def body(belief, step):
        x_t, a_t, first_t = step
        new_belief, logp, pred_var = filter_step_with_variance(belief, x_t, a_t, first_t, params)
        return new_belief, (logp, pred_var)

    if remat:
        body = jax.checkpoint(body)
    final_belief, (logp, pred_var) = jax.lax.scan(body, belief0, (x, a, first))
    return logp, final_belief, pred_var


def log_marginals(
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
) -> chex.Array:
    """log p(a_t | a_<t, s_<=t) within each episode, w integrated out (4.37, 4.49).

    Exactly the thesis's dense recursion (4.33)-(4.49), run per action dimension.
    t = 0 starts from the prior (4.33) whatever ``first[0]`` says; ``first[t]`` resets
    the belief to the prior at later t. Summed over an episode this is the log-density
    of the joint Gaussian of its actions, Cov(w_s, w_t) = (1-beta)^|s-t| diag(w_std^2).

    Args:
      x: [T, q] last-layer inputs.
      a: [T, p] actions taken (pre-squash).
      first: [T] bool, True where an episode starts at t.
      params: the chain's mu [p, q+1] (bias last), w_std [p, q+1], action_std [p] and
        beta, a scalar in [0, 1].

    Returns:
      logp [T].
    """
    logp, _, _ = segment_marginals(prior_belief(params.mu, params.w_std), x, a, first, params)
    return logp
