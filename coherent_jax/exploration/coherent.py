"""Exact inference over the coherent last-layer weights (thesis §4.1–4.2).

Deep Coherent Exploration perturbs only the policy's last layer. With ``x`` in R^q the
last-layer input, ``xh = [x; 1]`` and one weight row ``w_i = [W_i, b_i]`` in R^(q+1)
per action dimension i (p of them):

    a_t,i | w_t ~ N(w_t,i . xh_t, action_std_i^2)                                (4.29)
    w_0   ~ N(mu, diag(w_std^2))                                                  (4.5)
    w_t   = (1 - beta) w_{t-1} + beta mu + sqrt(2 beta - beta^2) w_std * eps     (4.1-4.4)

so every w_t has marginal N(mu, diag(w_std^2)); beta = 1 is step-based exploration
(fresh weights each step), beta = 0 trajectory-based (one draw per episode).

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

from coherent_jax.exploration.adaptive import SigmaRule, adapt_sigma, policy_distance
from coherent_jax.exploration.base import ActOutput, OffPolicyBehaviour, OnPolicyStrategy, SegmentLogProb
from coherent_jax.exploration.chain import chain_step, innovation_var
from coherent_jax.exploration.linalg import masked_gram, whiten
from coherent_jax.networks import MLP, augment, squash

_LOG_2PI = math.log(2.0 * math.pi)
#: largest w_std / action_std per action dimension that the strategy runs with (see
#: `CoherentExploration._head`)
MAX_W_STD_RATIO = 10.0


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


def _check_params(mu: chex.Array, w_std: chex.Array, action_std: chex.Array) -> tuple[int, int]:
    """Asserts mu, w_std [p, q+1] and action_std [p]; returns (p, q+1)."""
    chex.assert_rank([mu, w_std, action_std], [2, 2, 1])
    chex.assert_equal_shape([mu, w_std])
    p, n = mu.shape
    chex.assert_shape(action_std, (p,))
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
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
) -> tuple[Belief, chex.Array]:
    """One step of the exact filter (see `filter_step_with_variance`); returns (belief, logp)."""
    new_belief, logp, _ = filter_step_with_variance(belief, x, a, first, mu, w_std, action_std, beta)
    return new_belief, logp


def filter_step_with_variance(
    belief: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
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
      mu: [p, q+1] weight mean, bias in the last column.
      w_std: [p, q+1] weight standard deviation.
      action_std: [p] action noise standard deviation (Lambda_a^-1/2).
      beta: scalar in [0, 1], the chain's mixing rate.

    Returns:
      (belief over w_{t+1} before a_{t+1}, log p(a_t | a_<t, s_<=t) as a scalar,
      the predictive variances s [p]).
    """
    p, n = _check_params(mu, w_std, action_std)
    chex.assert_shape([belief.mean], (p, n))
    chex.assert_shape([belief.cov], (p, n, n))
    chex.assert_shape(x, (n - 1,))
    chex.assert_shape(a, (p,))
    chex.assert_rank([first, beta], 0)

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


def _segment_inputs(belief0, x, a, first, mu, w_std, action_std, beta):
    """Checks the shapes of a segment's inputs and casts them to one dtype.

    One dtype for the whole computation (and a scan's carry): float64 under x64 if
    any input is, else float32. Returns the inputs in the order given.
    """
    p, n = _check_params(mu, w_std, action_std)
    chex.assert_rank([x, a, first], [2, 2, 1])
    num_steps = x.shape[0]
    chex.assert_shape(x, (num_steps, n - 1))
    chex.assert_shape(a, (num_steps, p))
    chex.assert_shape(first, (num_steps,))
    chex.assert_shape([belief0.mean], (p, n))
    chex.assert_shape([belief0.cov], (p, n, n))
    dtype = jnp.result_type(x, a, mu, w_std, action_std, belief0.mean, belief0.cov)
    cast = lambda v: jnp.asarray(v).astype(dtype)  # noqa: E731
    x, a, mu, w_std, action_std, beta = map(cast, (x, a, mu, w_std, action_std, beta))
    belief0 = Belief(mean=cast(belief0.mean), cov=cast(belief0.cov))
    return belief0, x, a, jnp.asarray(first, dtype=bool), mu, w_std, action_std, beta


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

    See `segment_marginals`; returns (logp [T], final belief).
    """
    logp, final_belief, _ = segment_marginals(belief0, x, a, first, mu, w_std, action_std, beta, remat)
    return logp, final_belief


def predictive_entropy(pred_var: chex.Array) -> chex.Array:
    """Entropy of the predictive Gaussian of each step, 0.5 sum_i log(2 pi e s_i); [T, p] -> [T]."""
    return 0.5 * jnp.sum(_LOG_2PI + 1.0 + jnp.log(pred_var), axis=-1)


def segment_marginals(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
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
      mu: [p, q+1] weight mean, bias in the last column.
      w_std: [p, q+1] weight standard deviation.
      action_std: [p] action noise standard deviation.
      beta: scalar in [0, 1].
      remat: if True the scan body is ``jax.checkpoint``ed: the backward pass
        recomputes each step's intermediates from the stored belief instead of keeping
        several [p, q+1, q+1] arrays per step.

    Returns:
      (logp [T], the belief over w_T before a_T to start the next segment, the
      predictive variances s [T, p] of every step).
    """
    belief0, x, a, first, mu, w_std, action_std, beta = _segment_inputs(
        belief0, x, a, first, mu, w_std, action_std, beta
    )

    def body(belief, step):
        x_t, a_t, first_t = step
        new_belief, logp, pred_var = filter_step_with_variance(
            belief, x_t, a_t, first_t, mu, w_std, action_std, beta
        )
        return new_belief, (logp, pred_var)

    if remat:
        body = jax.checkpoint(body)
    final_belief, (logp, pred_var) = jax.lax.scan(body, belief0, (x, a, first))
    return logp, final_belief, pred_var


def log_marginals(
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
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
      mu: [p, q+1] weight mean, bias in the last column.
      w_std: [p, q+1] weight standard deviation.
      action_std: [p] action noise standard deviation.
      beta: scalar in [0, 1].

    Returns:
      logp [T].
    """
    logp, _ = log_marginals_from(prior_belief(mu, w_std), x, a, first, mu, w_std, action_std, beta)
    return logp


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


# --------------------------------------------------------------------------------------
# The same marginals in parallel form: the joint Gaussian of a segment's actions.


def segment_marginals_joint(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
    from_prior: bool = False,
) -> tuple[chex.Array, Belief, chex.Array]:
    """`segment_marginals` computed from the joint Gaussian of the segment's actions.

    Within a segment, action dimension i is jointly Gaussian. With c_s = (1-beta)^s for
    steps s of the episode that continues from the stored belief (m0, P0) (none if
    ``first[0]``) and 0 otherwise, D_i = diag(w_std_i^2) and M the same-episode mask:

        E[a_s,i]       = mu_i . xh_s + c_s (m0_i - mu_i) . xh_s
        K_i[s, t]      = M_st (1-beta)^|s-t| xh_s' D_i xh_t
                         + c_s c_t xh_s' (P0_i - D_i) xh_t + delta_st action_std_i^2

    which follows from w_s = (1-beta) w_{s-1} + ... (4.1-4.4) started at N(m0, P0) or
    at the prior N(mu, D) on a reset (4.5). The Cholesky factor K_i = L_i L_i' in time
    order yields exactly the filter's per-step marginals (4.37)/(4.49): the
    whitened residual z = L^-1 (a - E[a]) has z_t = (a_t - E[a_t | a_<t]) / L_tt, so

        log p(a_t,i | a_<t,i) = log N(z_t; 0, 1) - log L_tt,   s_t,i = L_tt^2.

    The belief over w_T that starts the next segment is the Gaussian conditional of
    w_T on the actions, Cov(w_T, a_s) = (c_T c_s (P0 - D) + g_s D) xh_s with
    g_s = (1-beta)^(T-s) on the last episode of the segment. Cost O(p T^2 (q+1) + p T^3)
    with no sequential loop: on CPU the forward and backward passes are about an order
    of magnitude faster than the scan for segments of tens of steps, but memory grows
    as T^2, so the filter remains the form for long segments.

    With ``from_prior`` (static) the segment starts an episode whatever ``first[0]``
    says: c = 0, ``belief0`` is not read, and the P0 terms, about half the work, are
    never formed.

    Args and returns: as `segment_marginals`.
    """
    belief0, x, a, first, mu, w_std, action_std, beta = _segment_inputs(
        belief0, x, a, first, mu, w_std, action_std, beta
    )
    if from_prior:
        first = first.at[0].set(True)
    num_steps = x.shape[0]
    m0, p0 = belief0.mean, belief0.cov
    dtype = x.dtype

    xh = augment(x)  # [T, n]
    var_w = jnp.square(w_std)  # [p, n]
    decay = 1.0 - beta
    # (1-beta)^k for k = 0..T, gathered below: a power per element of the [T, T]
    # matrices would be recomputed inside XLA's fusions (it cost 50x in the backward).
    steps = jnp.arange(num_steps)
    powers = jnp.power(decay, jnp.arange(num_steps + 1, dtype=dtype))
    episode = jnp.cumsum(first.astype(jnp.int32))  # 0 on the continuing episode
    same_episode = episode[:, None] == episode[None, :]
    c = jnp.where(episode == 0, powers[steps], 0.0)  # [T]
    lag = jnp.abs(steps[:, None] - steps[None, :])
    chain = jnp.where(same_episode, powers[lag], 0.0)  # [T, T]

    xd = xh[None, :, :] * var_w[:, None, :]  # [p, T, n]  D_i xh_s
    # chain * xh_s' D_i xh_t + action_std_i^2 I, symmetric by construction.
    cov_a = masked_gram(xh, var_w, chain, jnp.square(action_std))
    mean_a = xh @ mu.T  # [T, p]
    if not from_prior:
        xp0 = jnp.einsum("ikl,sl->isk", p0, xh)  # [p, T, n]  P0_i xh_s
        gram_p = jnp.einsum("isk,tk->ist", xp0 - xd, xh)  # xh_s' (P0_i - D_i) xh_t
        cov_a = cov_a + (c[:, None] * c[None, :])[None] * gram_p
        mean_a = mean_a + c[:, None] * (xh @ (m0 - mu).T)
    resid = (a - mean_a).T  # [p, T]

    # Belief over w_T (before a_T): condition the prior of w_T on the segment.
    last = episode == episode[-1]
    c_end = jnp.where(episode[-1] == 0, powers[num_steps], 0.0)
    g = jnp.where(last, powers[num_steps - steps], 0.0)  # [T]
    cross = g[None, :, None] * xd  # [p, T, n]
    mean_end = mu
    prior_cov_end = jax.vmap(jnp.diag)(var_w)
    if not from_prior:
        cross = cross + c_end * c[None, :, None] * (xp0 - xd)
        mean_end = mean_end + c_end * (m0 - mu)
        prior_cov_end = c_end**2 * p0 + (1.0 - c_end**2) * prior_cov_end
    # z = L^-1 r and L^-1 Cov(a, w_T); the marginals read L through log L_tt only.
    white, log_diag, proj = whiten(cov_a, resid, cross)  # [p, T], [p, T], [p, T, n]
    logp = jnp.sum(-0.5 * jnp.square(white) - log_diag - 0.5 * _LOG_2PI, axis=0)
    pred_var = jnp.exp(2.0 * log_diag).T  # [T, p]
    mean_end = mean_end + jnp.einsum("itk,it->ik", proj, white)
    cov_end = prior_cov_end - jnp.einsum("itk,itl->ikl", proj, proj)
    cov_end = 0.5 * (cov_end + jnp.swapaxes(cov_end, -1, -2))
    return logp, Belief(mean=mean_end, cov=cov_end), pred_var


# --------------------------------------------------------------------------------------
# The strategy: Coherent-A2C / Coherent-PPO (Algorithms 4 and 5).


class CoherentCarry(NamedTuple):
    """Per-env state of the coherent strategy, in standardised coordinates.

    The chain and the belief are stored for ``z = (w - mu) / w_std`` rather than for
    w itself. Under fixed parameters this is the same chain (w_t = mu + w_std z_t and
    z_t = (1 - beta) z_{t-1} + sqrt(2 beta - beta^2) eps, eqs. 4.1-4.4) and the same
    belief. When an update changes mu or w_std mid-episode, the exploring policy
    follows the new mean instead of keeping weights drawn around the old one (at
    beta = 0 it would otherwise never see the update until the episode ends), and
    the stored belief maps onto the new parameters, so the loss's segment start is a
    differentiable function of mu and w_std.

    Attributes:
      z: [p, q+1] standardised weights z_{t-1} used at the previous step.
      mean: [p, q+1] mean of alpha(z_t), the belief before a_t ([p, 0] where the
        strategy keeps no belief, see `CoherentExploration._keeps_belief`).
      cov: [p, q+1, q+1] covariance of alpha(z_t) ([p, 0, 0] likewise).
      restart: bool, the chain starts afresh at the next step even if its episode
        goes on (``gradient="exact"``: set at the end of every segment).
    """

    z: chex.Array
    mean: chex.Array
    cov: chex.Array
    restart: chex.Array


def _to_weights(carry: CoherentCarry, mu: chex.Array, w_std: chex.Array) -> Belief:
    """alpha(w) from alpha(z): mean mu + w_std m_z, cov diag(w_std_i) P_z diag(w_std_i)."""
    return Belief(
        mean=mu + w_std * carry.mean,
        cov=w_std[:, :, None] * carry.cov * w_std[:, None, :],
    )


def _to_standard(belief: Belief, mu: chex.Array, w_std: chex.Array) -> tuple[chex.Array, chex.Array]:
    return (belief.mean - mu) / w_std, belief.cov / (w_std[:, :, None] * w_std[:, None, :])


def episode_history_length(episode_length: int, unroll_length: int) -> int:
    """Prefix steps a segment's window needs so that it reaches back to the segment's
    episode start: at least ``episode_length - 1`` (a segment may start at the episode's
    last step), rounded up to whole segments so that the window's blocks line up with
    the segment's (``coherent.gradient=episode``)."""
    if episode_length < 1 or unroll_length < 1:
        raise ValueError(f"episode and unroll lengths must be >= 1, got {episode_length}, {unroll_length}")
    return -(-(episode_length - 1) // unroll_length) * unroll_length


class ChainStrategy(OnPolicyStrategy):
    """What the strategies on the beta-chain share: beta, the initial w_std, the action noise.

    ``action_std`` (Lambda_a^-1/2) is a fixed, sweepable hyperparameter as in the thesis,
    or learned (``log_action_std`` in the parameters) with ``learn_action_std``.
    """

    def __init__(
        self, action_size: int, beta: float, w_std_init: float, action_std: float, learn_action_std: bool
    ):
        self.action_size = int(action_size)
        self.beta = float(beta)
        self.w_std_init = float(w_std_init)
        self.action_std = float(action_std)
        self.learn_action_std = bool(learn_action_std)

    @staticmethod
    def chain_settings(cfg) -> dict:
        """The constructor's chain arguments as ``cfg`` gives them."""
        return {
            "beta": cfg.beta,
            "w_std_init": cfg.w_std_init,
            "action_std": cfg.action_std,
            "learn_action_std": cfg.learn_action_std,
        }

    def init_hparams(self):
        hp = {"beta": jnp.asarray(self.beta, jnp.float32)}
        if not self.learn_action_std:
            hp["action_std"] = jnp.full((self.action_size,), self.action_std, jnp.float32)
        return hp

    def _action_std(self, params, hparams):
        if self.learn_action_std:
            return jnp.exp(params["log_action_std"])
        return hparams["action_std"]


class CoherentExploration(ChainStrategy):
    """Deep Coherent Exploration of the policy's last layer (thesis §4.1-4.2).

    Parameters: the trunk f_theta, the last-layer mean ``mu`` [p, q+1] and per-weight
    ``log_w_std`` [p, q+1] (Lambda^-1/2), and ``log_action_std`` [p] when learned
    (otherwise ``action_std`` is a fixed, sweepable hyperparameter, as in the
    thesis). ``beta`` is a hyperparameter (an array, so it can be swept).

    Collection samples w_t from the chain and a_t ~ N(w_t xh_t, action_std^2)
    (Algorithm 5, steps 4-8). The behaviour log-probabilities are the analytic
    marginals (steps 12-14): with ``inference="joint"`` (default) `score_segment`
    scores the whole segment at once from its joint Gaussian and stores the belief
    that starts the next one; with ``"filter"`` `act` runs the filter step by step.
    `log_prob` recomputes the marginals of a stored segment under the current
    parameters in the same form; segments longer than `coherent_exact.MAX_BLOCK` are
    scored as blocks of the joint form chained by differentiable beliefs.

    ``gradient`` chooses what a segment's first step conditions on:

    * ``"exact"`` (default): the chain restarts at the first step of every segment,
      as Algorithm 5 samples w_0 at t = 0 of every buffer (steps 4-5), besides every
      episode start. Every segment is then scored from the prior, each log p(a_t | ...)
      conditions on all that the chain has seen, re-inferred under the current
      parameters, and the loss's gradient is the thesis's estimator (4.14) of the
      process actually run. The chain's correlations span at most ``unroll_length``
      steps: ``unroll_length = episode_length`` keeps them over whole episodes.
    * ``"episode"``: the chain runs on across segments within an episode, and the loss
      re-infers each segment's episode prefix under the current parameters: the trainer
      keeps each env's last `history_length` steps (at least ``episode_length - 1``)
      and `log_prob` scores the window prefix + segment from the prior at its first
      step, every episode start inside it resetting the belief (4.33). The segment's
      log-probabilities are then the thesis's marginals (4.37)/(4.49) of the episode
      filtered from its start, and their gradient the thesis's estimator (4.14) for
      the chain actually run, at a cost that grows with the prefix.
    * ``"stored"``: the chain runs on across segments, and a segment that starts
      mid-episode starts from the belief stored when it was collected, a constant of
      the data mapped onto the current mu and w_std: the right values (the ratio is 1
      at the collection parameters) but not the thesis's gradient (see
      ``python -m coherent_jax.bench gradient``). Kept for the ablation.

    ``episode_restart=False`` lets the chain run across episode starts; only the
    segment starts of ``"exact"`` restart it then, which is Algorithm 5's buffer: w_0
    drawn at t = 0, w_t ~ p(w_t | w_t-1) at every later step, across env resets.
    """

    name = "coherent"

    def __init__(
        self,
        action_size: int,
        hidden,
        activation: str,
        beta: float,
        w_std_init: float,
        action_std: float,
        learn_action_std: bool = False,
        remat: bool = False,
        inference: str = "joint",
        gradient: str = "exact",
        episode_restart: bool = True,
        episode_length: int = 0,
        unroll_length: int = 0,
    ):
        if inference not in ("joint", "filter"):
            raise ValueError(f"inference must be 'joint' or 'filter', got {inference!r}")
        if gradient not in ("exact", "stored", "episode"):
            raise ValueError(f"gradient must be 'exact', 'stored' or 'episode', got {gradient!r}")
        if gradient == "episode" and (inference != "joint" or not episode_restart or unroll_length < 1):
            raise ValueError("gradient='episode' needs inference='joint', episode_restart and unroll_length")
        super().__init__(action_size, beta, w_std_init, action_std, learn_action_std)
        self.feature_size = int(hidden[-1])
        self.trunk = MLP(tuple(hidden), activation)
        self.remat = bool(remat)
        self.inference = inference
        self.gradient = gradient
        self.episode_restart = bool(episode_restart)
        if gradient == "episode":
            from coherent_jax.exploration.coherent_exact import block_size

            self.history_length = episode_history_length(episode_length, unroll_length)
            self.block = block_size(int(unroll_length))

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(
            action_size,
            cfg.policy_hidden,
            cfg.activation,
            **cls.chain_settings(cfg),
            remat=cfg.remat,
            inference=cfg.coherent_inference,
            gradient=cfg.coherent.gradient,
            episode_restart=cfg.coherent.episode_restart,
            episode_length=cfg.episode_length,
            unroll_length=cfg.unroll_length,
        )

    # ---------------------------------------------------------------- params
    def init(self, key, obs_size):
        k_trunk, k_mu = jax.random.split(key)
        p, n = self.action_size, self.feature_size + 1
        # Small initial mean weights (as for a Gaussian policy's last layer), zero bias.
        w = jax.nn.initializers.orthogonal(0.01)(k_mu, (self.feature_size, p), jnp.float32).T
        params = {
            "trunk": self.trunk.init(k_trunk, jnp.zeros((1, obs_size))),
            "mu": jnp.concatenate([w, jnp.zeros((p, 1), jnp.float32)], axis=1),
            "log_w_std": jnp.full((p, n), math.log(self.w_std_init), jnp.float32),
        }
        if self.learn_action_std:
            params["log_action_std"] = jnp.full((p,), math.log(self.action_std), jnp.float32)
        return params

    def _head(self, params, hparams):
        w_std = jnp.exp(params["log_w_std"])
        action_std = self._action_std(params, hparams)
        # The covariance-form marginals keep float32 within about 0.005 nats per step
        # only while the weights' spread is within MAX_W_STD_RATIO of the action noise
        # (beta = 0, 1000-step segments; at 300 they lose every digit and turn NaN).
        # Beyond it the action noise is raised, in collection and in the loss alike, so
        # the process run is still the process scored.
        action_std = jnp.maximum(action_std, jnp.max(w_std, axis=-1) / MAX_W_STD_RATIO)
        return params["mu"], w_std, action_std

    @property
    def _keeps_belief(self) -> bool:
        """Whether the carry holds a belief: not when every segment is scored at once from
        the prior or the episode's start (``inference="joint"``, ``gradient="exact"`` or
        ``"episode"``). The belief is then empty
        ([n, p, 0] and [n, p, 0, 0]) instead of p (q+1)^2 floats per env that the
        rollout's loop would carry and the loss would gather for nothing (at the
        defaults, 6.5 MB per rollout step with 64 envs)."""
        return not (self.inference == "joint" and self.gradient in ("exact", "episode"))

    def _segment_belief(self, carry0: CoherentCarry, mu: chex.Array, w_std: chex.Array) -> Belief:
        """The belief a segment starts from: the stored one in weight coordinates, or the
        prior where the carry holds none (the segment restarts the chain)."""
        if self._keeps_belief:
            return _to_weights(carry0, mu, w_std)
        return prior_belief(mu, w_std)

    def init_carry(self, key, params, hparams, num_envs):
        p, n = self.action_size, self.feature_size + 1
        m = n if self._keeps_belief else 0
        return CoherentCarry(
            z=jnp.zeros((num_envs, p, n), jnp.float32),
            mean=jnp.zeros((num_envs, p, m), jnp.float32),
            cov=jnp.broadcast_to(jnp.eye(m, dtype=jnp.float32), (num_envs, p, m, m)),
            # The chain starts at the first step of training whatever ``first`` says there.
            restart=jnp.ones((num_envs,), bool),
        )

    # ------------------------------------------------------------ collection
    def act(self, key, params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        mu, w_std, action_std = self._head(params, hparams)
        beta = hparams["beta"]
        x = self.trunk.apply(params["trunk"], obs)  # [n, q]
        num_envs = x.shape[0]
        k_w, k_a = jax.random.split(key)
        # The chain in standard coordinates; a fresh draw at an episode start or a restart.
        first = jnp.logical_or(self._chain_first(first), carry.restart)
        z = chain_step(k_w, carry.z, first, beta)
        carry = carry._replace(restart=jnp.zeros_like(carry.restart))
        w = mu + w_std * z  # [n, p, q+1]
        xh = augment(x)
        mean_action = jnp.einsum("npk,nk->np", w, xh)
        action = mean_action + action_std * jax.random.normal(k_a, mean_action.shape, mean_action.dtype)

        if self.inference == "joint":
            # The segment is scored at once in `score_segment`; only the chain moves here.
            logp = jnp.full((num_envs,), jnp.nan, action.dtype)
            return ActOutput(action, logp, carry._replace(z=z))

        def filt(c, x_e, a_e, f_e):
            belief, logp = filter_step(_to_weights(c, mu, w_std), x_e, a_e, f_e, mu, w_std, action_std, beta)
            return _to_standard(belief, mu, w_std), logp

        (mean, cov), logp = jax.vmap(filt)(carry, x, action, first)
        chex.assert_shape(logp, (num_envs,))
        return ActOutput(action, logp, carry._replace(z=z, mean=mean, cov=cov))

    def _chain_first(self, first: chex.Array) -> chex.Array:
        """Where episode starts restart the chain: every ``first``, or none with
        ``episode_restart=False`` (the chain then runs across resets, as through the
        thesis's buffer; only the strategy's own restarts start it afresh)."""
        return first if self.episode_restart else jnp.zeros_like(first)

    def _segment_first(self, first: chex.Array, restart: chex.Array) -> chex.Array:
        """Where the chain starts afresh in a segment: its episode starts (unless
        ``episode_restart`` is off), and its first step if the chain restarted there."""
        first = self._chain_first(first)
        return first.at[0].set(jnp.logical_or(first[0], restart))

    def _score(self, belief0, x, a, first, mu, w_std, action_std, beta):
        """The segment's marginals in the configured form; (logp, end belief, variances)."""
        if self.inference == "filter":
            return segment_marginals(belief0, x, a, first, mu, w_std, action_std, beta, remat=self.remat)
        from coherent_jax.exploration.coherent_exact import MAX_BLOCK, chained_marginals

        # With the exact gradient every segment starts the chain: the stored belief's
        # terms are zero and need not be formed.
        from_prior = self.gradient == "exact"
        if x.shape[0] > MAX_BLOCK:
            return chained_marginals(
                belief0, x, a, first, mu, w_std, action_std, beta, from_prior=from_prior, remat=self.remat
            )
        return segment_marginals_joint(belief0, x, a, first, mu, w_std, action_std, beta, from_prior)

    def score_segment(self, params, hparams, carry0, carry, obs, actions, first, log_prob):
        # With the exact gradient the next segment restarts the chain (Algorithm 5, steps 4-5).
        carry = carry._replace(restart=jnp.full_like(carry.restart, self.gradient == "exact"))
        if self.gradient == "episode":  # windows of prefix + segment, scored as the loss scores them
            return self.batch_log_prob(params, hparams, carry0, obs, actions, first).log_prob, carry
        if self.inference == "filter":
            return log_prob, carry  # scored step by step in `act`
        mu, w_std, action_std = self._head(params, hparams)
        x = self.trunk.apply(params["trunk"], obs)  # [T, n, q]

        def score(c0, x_e, a_e, f_e):
            f_e = self._segment_first(f_e, c0.restart)
            logp, belief, _ = self._score(
                self._segment_belief(c0, mu, w_std), x_e, a_e, f_e, mu, w_std, action_std, hparams["beta"]
            )
            return logp, _to_standard(belief, mu, w_std)

        logp, (mean, cov) = jax.vmap(score, in_axes=(0, 1, 1, 1), out_axes=(1, 0))(carry0, x, actions, first)
        if self.gradient == "exact":
            return logp, carry  # the next segment starts from the prior: no belief to keep
        return logp, carry._replace(mean=mean, cov=cov)

    # ------------------------------------------------------------------ loss
    def log_prob(self, params, hparams, carry0, obs, actions, first, extras=()):
        chex.assert_rank([obs, actions, first], [2, 2, 1])
        mu, w_std, action_std = self._head(params, hparams)
        x = self.trunk.apply(params["trunk"], obs)
        if self.gradient == "episode":
            return self._window_log_prob(x, actions, first, mu, w_std, action_std, hparams["beta"])
        # The stored belief is a constant of the data (like a stored RNN state); its
        # mapping onto the current mu and w_std is not.
        # With gradient="exact" a segment's chain starts at its first step, so the
        # stored belief is never used and nothing is held constant.
        carry0 = jax.tree.map(jax.lax.stop_gradient, carry0)
        first = self._segment_first(first, carry0.restart)
        belief0 = self._segment_belief(carry0, mu, w_std)
        logp, _, pred_var = self._score(belief0, x, actions, first, mu, w_std, action_std, hparams["beta"])
        return SegmentLogProb(logp, predictive_entropy(pred_var))

    def _window_log_prob(self, x, actions, first, mu, w_std, action_std, beta) -> SegmentLogProb:
        """``gradient="episode"``: a window of `history_length` prefix steps and a segment,
        scored from the prior at its first step as blocks of the joint form chained by
        differentiable beliefs (`coherent_exact.chained_marginals`). The window always
        reaches back to the segment's episode start, which resets the belief there (4.33),
        so every earlier step only costs time; the trainer reads the last T steps."""
        from coherent_jax.exploration.coherent_exact import chained_marginals

        first = jnp.asarray(first, bool).at[0].set(True)
        prior = prior_belief(mu, w_std)
        logp, _, pred_var = chained_marginals(
            prior,
            x,
            actions,
            first,
            mu,
            w_std,
            action_std,
            beta,
            self.block,
            from_prior=True,
            remat=self.remat,
        )
        return SegmentLogProb(logp, predictive_entropy(pred_var))

    def mean_action(self, params, obs):
        x = self.trunk.apply(params["trunk"], obs)
        return jnp.einsum("pk,...k->...p", params["mu"], augment(x))

    def metrics(self, params, hparams):
        _, w_std, action_std = self._head(params, hparams)
        return {
            "w_std": jnp.mean(w_std),
            "action_std": jnp.mean(action_std),
            "beta": jnp.asarray(hparams["beta"]),
        }


# --------------------------------------------------------------------------------------
# Coherent-SAC (thesis §4.3 and §4.4.3).


class CoherentBehaviour(OffPolicyBehaviour):
    """The SAC actor's mean head [p, q+1] follows the beta-chain around its learned value.

    One scale instead of per-weight w_std: W_t = W + sigma z_t, with z_t the
    standardised chain (4.1-4.5), and sigma adapts by (4.50)-(4.51). The actor itself
    trains as plain SAC.
    """

    name = "coherent"

    def __init__(self, beta: float, rule: SigmaRule):
        self.beta = float(beta)
        self.rule = rule

    @classmethod
    def from_config(cls, cfg, action_size: int):
        return cls(cfg.beta, SigmaRule.from_config(cfg))

    def init_hparams(self):
        return {"beta": jnp.asarray(self.beta, jnp.float32), **self.rule.hparams()}

    def init_carry(self, key, actor, actor_params, hparams, num_envs):
        # z_0 ~ N(0, I) for every env; `first` at the first step redraws it anyway.
        return jax.random.normal(key, (num_envs,) + actor_params["mu"].shape, jnp.float32)

    def act(self, key, actor, actor_params, hparams, carry, obs, first):
        chex.assert_rank([obs, first], [2, 1])
        chex.assert_shape(carry, (obs.shape[0],) + actor_params["mu"].shape)
        # ``key`` draws xi exactly as plain SAC does, so sigma = 0 reproduces its actions.
        k_z, k_a = jax.random.fold_in(key, 1), key
        z = chain_step(k_z, carry, first, hparams["beta"])
        x = actor.features(actor_params, obs)
        # (mu + sigma z_t) xh = mu xh + sigma z_t xh: the first term is the unperturbed
        # actor's, computed the same way, so sigma = 0 gives its actions bit for bit.
        dist = actor.dist_from_features(actor_params, x)
        dist = dist._replace(mean=dist.mean + hparams["sigma"] * jnp.einsum("npk,nk->np", z, augment(x)))
        action, _ = squash(k_a, dist)
        return action, z

    def adapt(self, key, actor, actor_params, hparams, obs):
        chex.assert_rank(obs, 2)
        x = actor.features(actor_params, obs)
        # One perturbed actor: a draw from the chain's stationary law N(mu, sigma^2 I).
        z = jax.random.normal(key, actor_params["mu"].shape, actor_params["mu"].dtype)
        pre = actor.dist_from_features(actor_params, x).mean
        mean = jnp.tanh(pre)
        perturbed = jnp.tanh(pre + hparams["sigma"] * jnp.einsum("pk,nk->np", z, augment(x)))
        distance = policy_distance(mean, perturbed)
        sigma = adapt_sigma(hparams["sigma"], distance, hparams["sigma_delta"], hparams["sigma_alpha"])
        metrics = {"sigma": hparams["sigma"], "policy_distance": distance, "beta": hparams["beta"]}
        return {**hparams, "sigma": sigma}, metrics
