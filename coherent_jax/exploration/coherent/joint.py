"""The coherent marginals in parallel form: the joint Gaussian of a segment's actions.

`segment_marginals_joint` gives what the filter (`filter.segment_marginals`) gives, the per-step
marginals (4.37)/(4.49), the predictive variances and the belief that starts the next
segment, from one Cholesky factor per action dimension instead of a sequential loop
(docs/design.md §4).
"""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp

from coherent_jax.exploration.chain import ChainParams
from coherent_jax.exploration.coherent.filter import Belief, segment_inputs
from coherent_jax.exploration.linalg import masked_gram, whiten
from coherent_jax.networks import augment

_LOG_2PI = math.log(2.0 * math.pi)


def segment_marginals_joint(
    belief0: Belief,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    params: ChainParams,
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
    belief0, x, a, first, params = segment_inputs(belief0, x, a, first, params)
    mu, w_std, action_std, beta = params
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
