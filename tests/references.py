"""Shared float64 references of the coherent marginals and the helpers their tests use.

The reference is the joint Gaussian of a whole episode's actions under the thesis's
model (eqs. 4.1-4.5 and 4.29): one dense covariance per action dimension over every step
since the episode start, its Cholesky factor in time order giving log p(a_t | a_<t,
s_<=t) for every t. It shares no code with the library: no beliefs, no blocks, no
filter, no custom derivatives. It describes the process whose chain restarts exactly
where ``first`` is True (and at step 0).
"""

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np

_LOG_2PI = math.log(2.0 * math.pi)


@contextlib.contextmanager
def x64_enabled():
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


# ---------------------------------------------------------------- the reference


def reference_log_marginals(x, a, first, mu, w_std, action_std, beta):
    """log p(a_t | a_<t, s_<=t) for every step, from each episode's dense joint Gaussian.

    Cov(a_s,i, a_t,i) = [same episode] (1-beta)^|s-t| xh_s' diag(w_std_i^2) xh_t
                        + [s = t] action_std_i^2,   E[a_t,i] = mu_i . xh_t,
    the first step always starting an episode. L L' = Cov in time order; with
    r = L^-1 (a - E a): log p(a_t,i | a_<t,i) = -0.5 (log 2 pi + r_t^2) - log L_tt.
    """
    num_steps = x.shape[0]
    xh = jnp.concatenate([x, jnp.ones((num_steps, 1), x.dtype)], axis=1)
    episode = jnp.cumsum(jnp.asarray(first).at[0].set(True).astype(jnp.int32))
    same = episode[:, None] == episode[None, :]
    idx = jnp.arange(num_steps)
    lag = jnp.abs(idx[:, None] - idx[None, :]).astype(x.dtype)
    decay = jnp.where(same, (1.0 - beta) ** lag, 0.0)
    total = jnp.zeros(num_steps, x.dtype)
    for i in range(mu.shape[0]):
        cov = decay * ((xh * w_std[i] ** 2) @ xh.T) + action_std[i] ** 2 * jnp.eye(num_steps)
        chol = jnp.linalg.cholesky(cov)
        r = jax.scipy.linalg.solve_triangular(chol, a[:, i] - xh @ mu[i], lower=True)
        total = total - 0.5 * (_LOG_2PI + r**2) - jnp.log(jnp.diagonal(chol))
    return total


# ------------------------------------------- numpy references (test_coherent_filter.py)
# The thesis's dense recursion in information form and the joint Gaussian of one episode,
# both plain numpy float64: the process whose chain restarts where ``first`` is True.


def np_log_normal(y, mean, cov):
    """log N(y; mean, cov) for a full covariance, via slogdet and solve."""
    d = y - mean
    sign, logdet = np.linalg.slogdet(cov)
    assert sign > 0
    return -0.5 * (len(y) * _LOG_2PI + logdet + d @ np.linalg.solve(cov, d))


def thesis_flatten(m):
    """(4.30): the rows of W one after another, then the p biases. m is [p, q+1]."""
    return np.concatenate([m[:, :-1].reshape(-1), m[:, -1]])


def thesis_stack(x, p):
    """X_t of (4.31), [p, pq+p], so that X_t w_t = W_t x_t + b_t."""
    q = len(x)
    big_x = np.zeros((p, p * q + p))
    for i in range(p):
        big_x[i, i * q : (i + 1) * q] = x
        big_x[i, p * q + i] = 1.0
    return big_x


def dense_thesis_logp(x, a, first, mu, w_std, action_std, beta):
    """The dense recursion (4.33)-(4.49) in information form, as the thesis writes it."""
    num_steps, p = a.shape
    mu_flat = thesis_flatten(mu)
    lam_inv = np.diag(thesis_flatten(w_std) ** 2)  # Lambda^-1
    lam_a_inv = np.diag(action_std**2)  # Lambda_a^-1
    lam_a = np.diag(action_std**-2.0)
    logp = np.zeros(num_steps)
    v, l_inv = mu_flat, lam_inv
    for t in range(num_steps):
        if t == 0 or first[t]:
            v, l_inv = mu_flat, lam_inv  # (4.33)
        big_x = thesis_stack(x[t], p)
        logp[t] = np_log_normal(a[t], big_x @ v, lam_a_inv + big_x @ l_inv @ big_x.T)  # (4.49)
        l_mat = np.linalg.inv(l_inv)
        sigma = np.linalg.inv(l_mat + big_x.T @ lam_a @ big_x)  # (4.42)
        u = sigma @ (big_x.T @ lam_a @ a[t] + l_mat @ v)  # (4.41)
        v = (1.0 - beta) * u + beta * mu_flat  # (4.45)
        l_inv = (2.0 * beta - beta**2) * lam_inv + (1.0 - beta) ** 2 * sigma  # (4.46)
    return logp


def joint_episode_logp(x, a, mu, w_std, action_std, beta):
    """log N(a_flat; mean, C) of one whole episode's actions, flattened (t, i).

    Cov(a_s,i, a_t,j) = delta_ij [(1-beta)^|s-t| xh_s' diag(w_std_i^2) xh_t
                                  + delta_st action_std_i^2].
    """
    num_steps, p = a.shape
    xh = np.concatenate([x, np.ones((num_steps, 1))], axis=1)
    lags = np.abs(np.subtract.outer(np.arange(num_steps), np.arange(num_steps)))
    decay = (1.0 - beta) ** lags.astype(float)  # 0.0 ** 0.0 == 1.0 at beta = 1
    cov = np.zeros((num_steps, p, num_steps, p))
    for i in range(p):
        kernel = (xh * w_std[i] ** 2) @ xh.T
        cov[:, i, :, i] = decay * kernel + np.eye(num_steps) * action_std[i] ** 2
    mean = xh @ mu.T  # [T, p]
    size = num_steps * p
    return np_log_normal(a.reshape(size), mean.reshape(size), cov.reshape(size, size))


# ---------------------------------------------------------------- helpers


def trunk(theta, obs):
    return jnp.tanh(obs @ theta["w"] + theta["b"])


def sample_actions(rng, x, mu, w_std, action_std, beta, first):
    """Actions drawn from the chain (4.1-4.5) and (4.29) in numpy, given the features x [T, q]:
    w drawn from the prior where ``first`` (and at step 0), else moved along the chain."""
    num_steps, p = x.shape[0], mu.shape[0]
    xh = np.concatenate([x, np.ones((num_steps, 1))], axis=1)
    a = np.zeros((num_steps, p))
    w = None
    for t in range(num_steps):
        eps = rng.normal(size=mu.shape)
        if t == 0 or first[t]:
            w = mu + w_std * eps
        else:
            w = (1 - beta) * w + beta * mu + math.sqrt(2 * beta - beta**2) * w_std * eps
        a[t] = w @ xh[t] + action_std * rng.normal(size=p)
    return a


def sample_episode(rng, obs, theta, mu, w_std, action_std, beta, first):
    """`sample_actions` through the small tanh trunk."""
    return sample_actions(rng, np.asarray(trunk(theta, obs)), mu, w_std, action_std, beta, first)


def problem(seed, num_steps, p=2, q=3, obs_size=4, resets=(), beta=0.05):
    rng = np.random.default_rng(seed)
    obs = np.cumsum(rng.normal(size=(num_steps, obs_size)), axis=0) * 0.3
    params = {
        "theta": {"w": rng.normal(size=(obs_size, q)) * 0.7, "b": rng.normal(size=q) * 0.1},
        "mu": rng.normal(size=(p, q + 1)) * 0.5,
        "log_w_std": np.log(rng.uniform(0.2, 0.6, (p, q + 1))),
        "log_action_std": np.log(rng.uniform(0.1, 0.3, p)),
    }
    first = np.zeros(num_steps, bool)
    first[0] = True
    first[list(resets)] = True
    a = sample_episode(
        rng,
        obs,
        params["theta"],
        params["mu"],
        np.exp(params["log_w_std"]),
        np.exp(params["log_action_std"]),
        beta,
        first,
    )
    params = jax.tree.map(jnp.asarray, params)
    return params, jnp.asarray(obs), jnp.asarray(a), jnp.asarray(first)


def heads(params):
    return params["mu"], jnp.exp(params["log_w_std"]), jnp.exp(params["log_action_std"])


def perturb(params, seed, scale=0.05):
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.PRNGKey(seed), len(leaves))
    return jax.tree.unflatten(
        tree, [v + scale * jax.random.normal(k, v.shape, v.dtype) for v, k in zip(leaves, keys, strict=True)]
    )


def assert_trees_close(a, b, rtol, atol):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=rtol, atol=atol)


def cosine(a, b):
    a = np.concatenate([np.ravel(v) for v in jax.tree.leaves(a)])
    b = np.concatenate([np.ravel(v) for v in jax.tree.leaves(b)])
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
