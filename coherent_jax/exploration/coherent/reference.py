"""The thesis's dense filter (4.33)-(4.49) over the flattened last-layer weights, the
reference the block filter is timed and checked against, and inputs drawn from the
model for comparing the two.

Training never runs it: it is in the package because both the benchmarks' ``coherent``
suite (``benchmarks/filter_cost.py`` times the block filter against it) and the tests
(``tests/test_bench.py``) import it, and the package is what both may import."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from coherent_jax.exploration.chain import ChainParams

_LOG_2PI = math.log(2.0 * math.pi)


def dense_log_marginals(x, a, first, params: ChainParams, checkpoint_chunk: int = 0):
    """The thesis's filter (4.33)-(4.49) on the flattened weights, as a reference.

    The weights are one vector w in R^(p(q+1)) laid out as in (4.30), the p rows of
    W row by row and then the p biases, and X_t in R^(p x p(q+1)) is (4.31),
    [I_p (x) x_t', I_p], so a_t | w_t ~ N(X_t w_t, Lambda_a^-1) (4.32). The belief
    alpha(w_t) = N(v_t, L_t^-1) is kept in covariance form, P = L_t^-1, and
    conditioning on a_t uses the Woodbury form of (4.41)-(4.42):

        S = Lambda_a^-1 + X P X'           log p(a_t | history) = log N(a_t; X v, S)   (4.37/4.49)
        u = v + P X' S^-1 (a_t - X v)      Sigma = P - P X' S^-1 X P                   (4.41-4.42)
        v <- (1-beta) u + beta mu          P <- (2beta - beta^2) Lambda^-1 + (1-beta)^2 Sigma  (4.45-4.46)

    with an O(p^3) solve of S and O(p (p(q+1))^2) matrix products per step, and, as
    in the thesis, no re-symmetrisation of P (a transpose of the p(q+1)-square matrix
    per step made it about four times slower on CPU). That is the cheapest dense form
    (the information form of (4.42) inverts a p(q+1)-square matrix per step), so it
    flatters the dense side, except where its gradient must be checkpointed to fit
    in memory, which costs about one more forward pass (the bench records this).

    Same contract as `coherent_jax.exploration.coherent.filter.log_marginals`: x [T, q],
    a [T, p], first [T], the chain's mu and w_std [p, q+1] (bias last), action_std [p]
    and beta; t = 0 always starts from the prior.
    ``checkpoint_chunk > 0`` rematerialises the scan in chunks of that many steps
    (only the belief at each chunk start is kept for the backward pass), so the
    gradient fits in memory when p(q+1) is large.

    Returns:
      logp [T].
    """
    mu, w_std, action_std, beta = params
    num_steps, q = x.shape
    p = a.shape[-1]
    eye_p = jnp.eye(p, dtype=x.dtype)
    mean0 = jnp.concatenate([mu[:, :q].reshape(-1), mu[:, q]])  # (4.30)
    cov0 = jnp.diag(jnp.concatenate([w_std[:, :q].reshape(-1), w_std[:, q]]) ** 2)  # Lambda^-1
    noise_cov = jnp.diag(action_std**2)  # Lambda_a^-1
    decay = 1.0 - beta
    innovation = beta * (2.0 - beta)

    def step(belief, inputs):
        x_t, a_t, reset = inputs
        mean = jnp.where(reset, mean0, belief[0])  # (4.33) at an episode start
        cov = jnp.where(reset, cov0, belief[1])
        big_x = jnp.concatenate([jnp.kron(eye_p, x_t[None, :]), eye_p], axis=1)  # (4.31)
        x_cov = big_x @ cov  # X P, [p, D]
        s = noise_cov + x_cov @ big_x.T
        err = a_t - big_x @ mean
        _, logdet = jnp.linalg.slogdet(s)
        logp = -0.5 * (p * _LOG_2PI + logdet + err @ jnp.linalg.solve(s, err))
        s_inv_x_cov = jnp.linalg.solve(s, x_cov)  # S^-1 X P
        post_mean = mean + s_inv_x_cov.T @ err
        post_cov = cov - x_cov.T @ s_inv_x_cov
        new_mean = decay * post_mean + beta * mean0
        new_cov = innovation * cov0 + decay**2 * post_cov
        return (new_mean, new_cov), logp

    reset = jnp.asarray(first, bool).at[0].set(True)
    belief0 = (mean0, cov0)
    if checkpoint_chunk <= 0 or checkpoint_chunk >= num_steps:
        _, logp = jax.lax.scan(step, belief0, (x, a, reset))
        return logp
    chunk = checkpoint_chunk
    while num_steps % chunk:  # largest divisor of T not above the request
        chunk -= 1
    split = lambda z: z.reshape((num_steps // chunk, chunk) + z.shape[1:])

    @jax.checkpoint
    def run_chunk(belief, inputs):
        return jax.lax.scan(step, belief, inputs)

    _, logp = jax.lax.scan(run_chunk, belief0, (split(x), split(a), split(reset)))
    return logp.reshape(num_steps)


def sample_segments(key, batch, num_steps, q, p, w_std_init, action_std, beta):
    """Inputs for the filter benchmark: actions drawn from the model (4.1-4.5, 4.29).

    x = tanh(N(0, 1)) like a tanh trunk's output, two episodes per sequence (a
    reset at T/2 exercises the prior reset), weights following the chain.
    """
    k_x, k_mu, k_run = jax.random.split(key, 3)
    x = jnp.tanh(jax.random.normal(k_x, (batch, num_steps, q)))
    mu = 0.1 * jax.random.normal(k_mu, (p, q + 1))
    w_std = jnp.full((p, q + 1), w_std_init)
    sigma = jnp.full((p,), action_std)
    first = jnp.zeros((num_steps,), bool).at[0].set(True).at[num_steps // 2].set(True)
    innovation_std = math.sqrt(max(beta * (2.0 - beta), 0.0))

    def one(k, xs):
        def step(w, inputs):
            k_t, x_t, first_t = inputs
            k_w, k_a = jax.random.split(k_t)
            eps = jax.random.normal(k_w, w.shape)
            chained = (1.0 - beta) * w + beta * mu + innovation_std * w_std * eps
            w = jnp.where(first_t, mu + w_std * eps, chained)
            a_t = w @ jnp.append(x_t, 1.0) + sigma * jax.random.normal(k_a, (p,))
            return w, a_t

        _, actions = jax.lax.scan(step, mu, (jax.random.split(k, num_steps), xs, first))
        return actions

    a = jax.vmap(one)(jax.random.split(k_run, batch), x)
    return x, a, jnp.broadcast_to(first, (batch, num_steps)), mu, w_std, sigma, jnp.float32(beta)
