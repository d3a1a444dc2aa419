"""The thesis's estimator for segments of long episodes (coherent_jax.exploration.coherent_exact).

The reference is written here, in float64, from the joint Gaussian of a whole episode's
actions (the thesis's model, eqs. 4.1-4.5 and 4.29): one dense covariance per action
dimension over every step since the episode start, its Cholesky factor in time order
giving log p(a_t | a_<t, s_<=t) for every t. It shares no code with the module: no
beliefs, no blocks, no filter. Gradients are those of the same loss terms through a
small tanh trunk, with respect to the trunk, mu, log w_std and action_std.
"""

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.exploration import coherent as C
from coherent_jax.exploration import coherent_exact as E

_LOG_2PI = math.log(2.0 * math.pi)


@contextlib.contextmanager
def x64_enabled():
    previous = jax.config.read("jax_enable_x64")
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


@pytest.fixture
def x64():
    with x64_enabled():
        yield


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


def trunk(theta, obs):
    return jnp.tanh(obs @ theta["w"] + theta["b"])


def sample_episode(rng, obs, theta, mu, w_std, action_std, beta, first):
    """Actions drawn from the chain (4.1-4.5) and (4.29) in numpy."""
    x = np.asarray(trunk(theta, obs))
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


# ---------------------------------------------------------------- tests


def _weighted(logp_fn):
    """(params, obs, a, first, weights, beta) -> (sum_t weights_t logp_t, logp), jitted with its gradient."""

    def loss(params, obs, a, first, weights, beta):
        mu, w_std, action_std = heads(params)
        logp = logp_fn(trunk(params["theta"], obs), a, first, mu, w_std, action_std, beta)
        return jnp.sum(weights * logp[-weights.shape[0] :]), logp[-weights.shape[0] :]

    return jax.jit(jax.value_and_grad(loss, has_aux=True))


def _chained_8(x, a, first, mu, w_std, action_std, beta):
    return E.chained_marginals(C.prior_belief(mu, w_std), x, a, first, mu, w_std, action_std, beta, 8)[0]


def _refiltered_20_4(x, a, first, mu, w_std, action_std, beta):
    h = 20
    return E.refiltered_marginals(
        x[:h], a[:h], first[:h], x[h:], a[h:], first[h:], mu, w_std, action_std, beta, block=4
    )[0]


chained_loss = _weighted(_chained_8)
refiltered_loss = _weighted(_refiltered_20_4)
reference_loss = _weighted(reference_log_marginals)


@pytest.mark.parametrize("beta", [0.0, 0.05, 1.0])
@pytest.mark.parametrize("resets", [(), (11,), (8, 17)])
def test_chained_blocks_equal_dense_episode_reference(x64, beta, resets):
    """Values and gradients over 24 steps in 3 blocks of 8, resets on and off block edges."""
    params, obs, a, first = problem(1, 24, resets=resets, beta=beta)
    weights = jnp.asarray(np.random.default_rng(2).normal(size=24))
    for point in (params, perturb(params, 3)):
        (_, logp), grad = chained_loss(point, obs, a, first, weights, beta)
        (_, ref), grad_ref = reference_loss(point, obs, a, first, weights, beta)
        np.testing.assert_allclose(logp, ref, rtol=1e-10, atol=1e-10)
        assert_trees_close(grad, grad_ref, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("beta", [0.0, 0.01, 0.3])
def test_refiltered_segment_gradient_equals_full_episode_reference(x64, beta):
    """A segment that starts mid-episode, its prefix re-inferred: the thesis's gradient.

    An earlier episode's tail (steps 0-4), then the current episode from step 5; the
    segment is steps 20-27 and the loss is sum_t A_t log p(a_t | ...) over it. Checked
    at the collection parameters and after a parameter update.
    """
    params, obs, a, first = problem(4, 28, resets=(5,), beta=beta)
    adv = jnp.asarray(np.random.default_rng(5).normal(size=8))
    for point in (params, perturb(params, 6)):
        (_, logp), grad = refiltered_loss(point, obs, a, first, adv, beta)
        (_, ref), grad_ref = reference_loss(point, obs, a, first, adv, beta)
        np.testing.assert_allclose(logp, ref, rtol=1e-10, atol=1e-10)
        assert_trees_close(grad, grad_ref, rtol=1e-8, atol=1e-10)
        assert np.abs(np.asarray(grad["theta"]["w"])).max() > 0


def test_stored_belief_gives_the_right_values_but_not_the_thesis_gradient(x64):
    """The defect the exact forms remove, on a narrow last layer at beta = 0.01.

    The belief at the segment start, computed at collection and held fixed in
    standardised coordinates, reproduces the reference's values at the collection
    parameters, but its gradient is far from the reference's.
    """
    beta, h = 0.01, 32
    params, obs, a, first = problem(7, 40, p=1, q=4, beta=beta)
    adv = jnp.asarray(np.random.default_rng(8).normal(size=8))
    mu0, w_std0, action_std0 = heads(params)
    x0 = trunk(params["theta"], obs)
    _, stored, _ = C.segment_marginals(
        C.prior_belief(mu0, w_std0), x0[:h], a[:h], first[:h], mu0, w_std0, action_std0, beta
    )
    z_mean, z_cov = (stored.mean - mu0) / w_std0, stored.cov / (w_std0[:, :, None] * w_std0[:, None, :])

    @jax.jit
    @jax.value_and_grad
    def held(params):
        mu, w_std, action_std = heads(params)
        belief = C.Belief(mu + w_std * z_mean, w_std[:, :, None] * z_cov * w_std[:, None, :])
        x = trunk(params["theta"], obs)
        logp, _, _ = C.segment_marginals_joint(belief, x[h:], a[h:], first[h:], mu, w_std, action_std, beta)
        return jnp.sum(adv * logp)

    value, grad = held(params)
    (value_ref, _), grad_ref = reference_loss(params, obs, a, first, adv, beta)
    np.testing.assert_allclose(value, value_ref, rtol=1e-9)
    assert cosine(grad, grad_ref) < 0.99


def test_block_size_divides():
    assert E.block_size(64) == 64
    assert E.block_size(1000) == 50
    assert E.block_size(7) == 7
    assert E.block_size(67) == 1
    with pytest.raises(ValueError):
        E.chained_marginals(
            *([None] * 1),
            jnp.zeros((6, 2)),
            jnp.zeros((6, 1)),
            jnp.zeros(6, bool),
            jnp.zeros((1, 3)),
            jnp.ones((1, 3)),
            jnp.ones(1),
            0.1,
            block=4,
        )
