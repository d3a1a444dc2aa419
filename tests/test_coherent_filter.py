"""Tests of the exact coherent filter (coherent_jax.exploration.coherent.filter).

Every reference here is plain numpy float64 written from the thesis's equations
(4.1-4.5, 4.29-4.49) and from the joint Gaussian of an episode's actions; none calls
the module under test (the float32 accuracy check alone compares with the module run
in float64, which the other tests hold to these references). Comparisons that need
float64 run inside the ``x64`` fixture, which restores JAX's default afterwards so
other test files still run in float32.
"""

import math

import coherent_samplers
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from references import dense_thesis_logp, joint_episode_logp, x64_enabled

from coherent_jax.exploration.chain import ChainParams, chain_params
from coherent_jax.exploration.coherent import filter as coherent_filter

_LOG_2PI = math.log(2.0 * math.pi)

# One compiled program per input shape and dtype; beta is a traced argument.
_log_marginals = jax.jit(coherent_filter.log_marginals)
_log_marginals_from = jax.jit(coherent_samplers.log_marginals_from, static_argnames="remat")


# ---------------------------------------------------------------- numpy references


def np_log_normal_diag(y, mean, var):
    return np.sum(-0.5 * (_LOG_2PI + np.log(var) + (y - mean) ** 2 / var))


def make_problem(seed, num_steps, p, q, beta, resets=(), first0=True):
    """Random parameters and inputs, with actions sampled from the model in numpy."""
    rng = np.random.default_rng(seed)
    x = np.tanh(rng.normal(size=(num_steps, q)))
    mu = 0.5 * rng.normal(size=(p, q + 1))
    w_std = rng.uniform(0.3, 1.0, size=(p, q + 1))
    action_std = rng.uniform(0.1, 0.5, size=p)
    first = np.zeros(num_steps, dtype=bool)
    first[0] = first0
    first[list(resets)] = True
    innovation = math.sqrt(max(2.0 * beta - beta**2, 0.0))
    a = np.zeros((num_steps, p))
    w = mu
    for t in range(num_steps):
        eps = rng.normal(size=mu.shape)
        if t == 0 or first[t]:
            w = mu + w_std * eps
        else:
            w = (1.0 - beta) * w + beta * mu + innovation * w_std * eps
        a[t] = w @ np.append(x[t], 1.0) + action_std * rng.normal(size=p)
    return dict(x=x, a=a, first=first, mu=mu, w_std=w_std, action_std=action_std)


def episode_bounds(first):
    starts = [0] + [t for t in range(1, len(first)) if first[t]]
    return list(zip(starts, starts[1:] + [len(first)], strict=True))


def call_log_marginals(problem, beta, fn=_log_marginals):
    return np.asarray(
        fn(
            jnp.asarray(problem["x"]),
            jnp.asarray(problem["a"]),
            jnp.asarray(problem["first"]),
            chain_params(
                jnp.asarray(problem["mu"]),
                jnp.asarray(problem["w_std"]),
                jnp.asarray(problem["action_std"]),
                jnp.asarray(beta),
            ),
        )
    )


# ------------------------------------------------------------ agreement with the thesis


@pytest.mark.parametrize("beta", [0.0, 0.01, 0.5, 1.0])
@pytest.mark.parametrize("p,q", [(1, 2), (1, 5), (3, 2), (3, 5)])
def test_matches_dense_thesis_recursion(x64, p, q, beta):
    """The per-dimension filter equals the dense (pq+p)-dim recursion (4.33)-(4.49).

    Resets at t = 0 and two interior steps; first[0] is False for p = 1 to check that
    t = 0 starts from the prior whatever it says.
    """
    problem = make_problem(10 * p + q, 12, p, q, beta, resets=(5, 9), first0=p > 1)
    expected = dense_thesis_logp(**problem, beta=beta)
    np.testing.assert_allclose(call_log_marginals(problem, beta), expected, rtol=1e-9)


@pytest.mark.parametrize("beta", [0.0, 0.3, 1.0])
def test_episode_sum_equals_joint_gaussian(x64, beta):
    """Per episode, sum_t log p(a_t | a_<t) is the log-density of all its actions,
    whose covariance has Cov(w_s, w_t) = (1-beta)^|s-t| diag(w_std^2)."""
    problem = make_problem(3, 14, 2, 4, beta, resets=(6,))
    logp = call_log_marginals(problem, beta)
    for start, stop in episode_bounds(problem["first"]):
        expected = joint_episode_logp(
            problem["x"][start:stop],
            problem["a"][start:stop],
            problem["mu"],
            problem["w_std"],
            problem["action_std"],
            beta,
        )
        np.testing.assert_allclose(logp[start:stop].sum(), expected, rtol=1e-10)


def test_beta_one_is_history_free(x64):
    """At beta = 1 every step is N(mu xh, action_std^2 + xh' diag(w_std_i^2) xh)."""
    problem = make_problem(4, 10, 3, 4, 1.0, resets=(4,))
    xh = np.concatenate([problem["x"], np.ones((10, 1))], axis=1)
    var = problem["action_std"] ** 2 + (xh**2) @ (problem["w_std"] ** 2).T
    expected = [np_log_normal_diag(problem["a"][t], problem["mu"] @ xh[t], var[t]) for t in range(10)]
    np.testing.assert_allclose(call_log_marginals(problem, 1.0), expected, rtol=1e-12)


def test_first_step_always_starts_from_prior(x64):
    """first[0] does not matter; filter_step with first=True ignores the belief it gets."""
    problem = make_problem(5, 6, 2, 3, 0.2)
    with_flag = call_log_marginals(problem, 0.2)
    problem["first"][0] = False
    np.testing.assert_array_equal(call_log_marginals(problem, 0.2), with_flag)

    mu, w_std = jnp.asarray(problem["mu"]), jnp.asarray(problem["w_std"])
    junk = coherent_filter.Belief(mean=mu + 3.0, cov=jnp.ones((2, 4, 4)) * 7.0)
    args = (problem["x"][0], problem["a"][0], True, chain_params(mu, w_std, problem["action_std"], 0.2))
    from_junk, logp_junk = coherent_filter.filter_step(junk, *args)
    from_prior, logp_prior = coherent_filter.filter_step(coherent_filter.prior_belief(mu, w_std), *args)
    np.testing.assert_allclose(logp_junk, logp_prior, rtol=1e-14)
    np.testing.assert_allclose(from_junk.cov, from_prior.cov, rtol=1e-14)
    np.testing.assert_allclose(from_junk.mean, from_prior.mean, rtol=1e-14)


# ------------------------------------------------------------------------ gradients


@pytest.mark.parametrize("beta", [0.0, 0.3, 1.0])
def test_gradients_match_finite_differences(x64, beta):
    """jax.grad of a weighted sum of log_marginals w.r.t. x, mu, w_std, action_std
    equals central differences of the dense numpy reference, element by element."""
    problem = make_problem(6, 8, 3, 3, beta, resets=(5,))
    weights = np.random.default_rng(7).uniform(0.5, 1.5, size=8)
    names = ("x", "mu", "w_std", "action_std")

    def objective(x, mu, w_std, action_std):
        chain = chain_params(mu, w_std, action_std, beta)
        logp = coherent_filter.log_marginals(x, problem["a"], problem["first"], chain)
        return jnp.sum(weights * logp)

    grads = jax.grad(objective, argnums=(0, 1, 2, 3))(*(jnp.asarray(problem[n]) for n in names))

    def reference(**overrides):
        kwargs = {**problem, **overrides}
        return np.sum(weights * dense_thesis_logp(**kwargs, beta=beta))

    step = 1e-6
    for name, grad in zip(names, grads, strict=True):
        numeric = np.zeros_like(problem[name])
        for idx in np.ndindex(numeric.shape):
            plus, minus = problem[name].copy(), problem[name].copy()
            plus[idx] += step
            minus[idx] -= step
            numeric[idx] = (reference(**{name: plus}) - reference(**{name: minus})) / (2 * step)
        np.testing.assert_allclose(grad, numeric, rtol=1e-6, atol=1e-7, err_msg=name)


def test_remat_gives_same_values_and_gradients(x64):
    """coherent.remat=True only changes what the backward pass stores."""
    problem = make_problem(8, 10, 2, 3, 0.3, resets=(4,))
    mu, w_std = jnp.asarray(problem["mu"]), jnp.asarray(problem["w_std"])
    belief0 = coherent_filter.prior_belief(mu, w_std)

    def objective(mu, w_std, action_std, x, remat):
        logp, final = coherent_samplers.log_marginals_from(
            belief0, x, problem["a"], problem["first"], mu, w_std, action_std, 0.3, remat=remat
        )
        return jnp.sum(logp) + jnp.sum(final.cov) + jnp.sum(final.mean)

    args = (mu, w_std, jnp.asarray(problem["action_std"]), jnp.asarray(problem["x"]))
    plain = jax.value_and_grad(objective, argnums=(0, 1, 2, 3))(*args, False)
    remat = jax.value_and_grad(objective, argnums=(0, 1, 2, 3))(*args, True)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(remat), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------- float32 robustness


def test_float32_long_episodes_stay_finite():
    """1000 steps of one episode, q = 64: logp, gradients and the final belief stay
    finite (and the covariance symmetric PSD) at beta = 0, 0.01, 1, in float32.

    beta = 0 is the hard case: the posterior covariance shrinks like 1/t.
    """
    num_steps, p, q = 1000, 3, 64

    def objective(x, mu, w_std, action_std, a, first, beta):
        belief0 = coherent_filter.prior_belief(mu, w_std)
        logp, final = coherent_samplers.log_marginals_from(
            belief0, x, a, first, mu, w_std, action_std, beta, remat=True
        )
        return jnp.sum(logp), (logp, final)

    value_and_grad = jax.jit(jax.value_and_grad(objective, argnums=(0, 1, 2, 3), has_aux=True))
    for beta in (0.0, 0.01, 1.0):
        rng = np.random.default_rng(int(beta * 100))
        # Smooth, tanh-squashed features, like a trunk's output along a trajectory.
        phase = rng.uniform(0.0, 2.0 * np.pi, size=q)
        x = np.tanh(
            2.0 * np.sin(0.02 * np.arange(num_steps)[:, None] + phase) + 0.5 * rng.normal(size=(num_steps, q))
        )
        mu = 0.1 * rng.normal(size=(p, q + 1))
        w_std = rng.uniform(0.3, 1.0, size=(p, q + 1))
        action_std = rng.uniform(0.1, 0.5, size=p)
        innovation = math.sqrt(2.0 * beta - beta**2)
        w = mu + w_std * rng.normal(size=mu.shape)
        a = np.zeros((num_steps, p))
        for t in range(num_steps):
            if t:
                w = (1.0 - beta) * w + beta * mu + innovation * w_std * rng.normal(size=mu.shape)
            a[t] = w @ np.append(x[t], 1.0) + action_std * rng.normal(size=p)
        first = np.zeros(num_steps, dtype=bool)

        args = [jnp.asarray(v, jnp.float32) for v in (x, mu, w_std, action_std, a)]
        (total, (logp, final)), grads = value_and_grad(*args, jnp.asarray(first), jnp.float32(beta))
        assert logp.dtype == jnp.float32 and logp.shape == (num_steps,)
        assert np.isfinite(np.asarray(logp)).all(), beta
        # A model-sampled action is never wildly improbable: about -log(s)/2 per dim.
        assert np.all(np.asarray(logp) > -60.0), beta
        for g in grads:
            assert g.dtype == jnp.float32
            assert np.isfinite(np.asarray(g)).all(), beta
        # Accuracy, not just finiteness: the same filter in float64.
        with x64_enabled():
            exact = call_log_marginals(
                dict(x=x, a=a, first=first, mu=mu, w_std=w_std, action_std=action_std), beta
            )
        error = np.abs(np.asarray(logp, np.float64) - exact)
        print(f"coherent.beta={beta}: float32 logp error max {error.max():.2e}, mean {error.mean():.2e}")
        assert error.max() < 1e-2, beta
        cov = np.asarray(final.cov, np.float64)
        np.testing.assert_array_equal(cov, np.swapaxes(cov, -1, -2))
        eigenvalues = np.linalg.eigvalsh(cov)
        assert eigenvalues.min() > -1e-6 * eigenvalues.max(), beta


# ------------------------------------------------------------- transforms and dtypes


def test_jit_and_vmap_match_python_loop():
    """vmap over envs (x, a, first batched; parameters shared) and over a beta sweep
    equal a Python loop of single, unjitted calls."""
    batch, num_steps, p, q = 3, 9, 2, 3
    problems = [make_problem(20 + b, num_steps, p, q, 0.4, resets=(b + 3,)) for b in range(batch)]
    stacked = {k: np.stack([pr[k] for pr in problems]) for k in ("x", "a", "first")}
    params = {k: jnp.asarray(problems[0][k], jnp.float32) for k in ("mu", "w_std", "action_std")}
    f32 = lambda v: jnp.asarray(v, jnp.float32) if v.dtype != bool else jnp.asarray(v)

    loop = np.stack(
        [
            coherent_filter.log_marginals(
                f32(stacked["x"][b]),
                f32(stacked["a"][b]),
                f32(stacked["first"][b]),
                chain_params(params["mu"], params["w_std"], params["action_std"], 0.4),
            )
            for b in range(batch)
        ]
    )
    over_envs = jax.jit(jax.vmap(coherent_filter.log_marginals, in_axes=(0, 0, 0, None)))
    batched = over_envs(
        f32(stacked["x"]),
        f32(stacked["a"]),
        f32(stacked["first"]),
        chain_params(params["mu"], params["w_std"], params["action_std"], jnp.float32(0.4)),
    )
    assert batched.shape == (batch, num_steps) and batched.dtype == jnp.float32
    np.testing.assert_allclose(batched, loop, rtol=1e-5, atol=1e-5)

    betas = np.array([0.0, 0.4, 1.0], np.float32)
    # Only beta is swept: the axes of the named parameters are named too.
    beta_axes = ChainParams(mu=None, w_std=None, action_std=None, beta=0)
    over_betas = jax.jit(jax.vmap(coherent_filter.log_marginals, in_axes=(None, None, None, beta_axes)))
    env0 = (f32(stacked["x"][0]), f32(stacked["a"][0]), f32(stacked["first"][0]))
    swept = over_betas(*env0, ChainParams(params["mu"], params["w_std"], params["action_std"], betas))
    for beta, row in zip(betas, swept, strict=True):
        single = coherent_filter.log_marginals(*env0, chain_params(*params.values(), beta))
        np.testing.assert_allclose(row, single, rtol=1e-5, atol=1e-5)


def test_dtype_follows_inputs(x64):
    """float64 in -> float64 out under x64; float32 in stays float32."""
    problem = make_problem(9, 5, 2, 3, 0.5)
    for dtype in (jnp.float64, jnp.float32):
        cast = {k: jnp.asarray(v, dtype) for k, v in problem.items() if k != "first"}
        belief0 = coherent_filter.prior_belief(cast["mu"], cast["w_std"])
        logp, final = _log_marginals_from(
            belief0,
            cast["x"],
            cast["a"],
            jnp.asarray(problem["first"]),
            cast["mu"],
            cast["w_std"],
            cast["action_std"],
            0.5,
        )
        assert logp.dtype == dtype
        assert final.mean.dtype == dtype and final.cov.dtype == dtype
        w = coherent_samplers.step_weights(
            jax.random.key(0), cast["mu"], False, cast["mu"], cast["w_std"], 0.5
        )
        a = coherent_samplers.sample_action(jax.random.key(1), w, cast["x"][0], cast["action_std"])
        assert w.dtype == dtype and a.dtype == dtype


@pytest.mark.parametrize("split", [4, 7, 8])
def test_segment_split_identity(x64, split):
    """Filtering the second part from the belief left by the first part reproduces the
    whole sequence's log_marginals; the reset at t = 7 falls after, at, or before the
    split."""
    problem = make_problem(11, 12, 2, 3, 0.25, resets=(7,))
    whole = call_log_marginals(problem, 0.25)
    mu, w_std = jnp.asarray(problem["mu"]), jnp.asarray(problem["w_std"])
    rest = (mu, w_std, jnp.asarray(problem["action_std"]), jnp.asarray(0.25))

    def segment(belief, lo, hi):
        return _log_marginals_from(
            belief,
            jnp.asarray(problem["x"][lo:hi]),
            jnp.asarray(problem["a"][lo:hi]),
            jnp.asarray(problem["first"][lo:hi]),
            *rest,
        )

    head, belief = segment(coherent_filter.prior_belief(mu, w_std), 0, split)
    tail, _ = segment(belief, split, 12)
    np.testing.assert_allclose(np.concatenate([head, tail]), whole, rtol=1e-12)


# ------------------------------------------------------------------- the sampled chain


@pytest.mark.parametrize("beta", [0.1, 0.5])
def test_chain_is_stationary_with_lag_one_correlation(beta):
    """4000 chains of 50 steps from step_weights: at several t each weight has mean mu
    and variance w_std^2, and corr(w_t - mu, w_t+1 - mu) is 1 - beta.

    Tolerances are 5 standard errors of N = 4000 Gaussian samples: mean w_std/sqrt(N),
    variance w_std^2 sqrt(2/(N-1)); the lag-1 statistic mean(z_t z_t+1) of standardised
    weights has variance (1 + rho^2) / n over n independent (chain, weight) pairs.
    """
    num_chains, num_steps = 4000, 50
    mu = jnp.array([[0.5, -1.0, 0.0], [2.0, 0.3, -0.7]], jnp.float32)
    w_std = jnp.array([[0.3, 1.0, 0.6], [0.5, 0.8, 0.4]], jnp.float32)

    def chain(key):
        def body(w, step):
            step_key, first = step
            w = coherent_samplers.step_weights(step_key, w, first, mu, w_std, beta)
            return w, w

        steps = (jax.random.split(key, num_steps), jnp.arange(num_steps) == 0)
        return jax.lax.scan(body, jnp.full_like(mu, 100.0), steps)[1]

    keys = jax.random.split(jax.random.key(int(beta * 10)), num_chains)
    w = np.asarray(jax.jit(jax.vmap(chain))(keys), np.float64)  # [N, T, p, q+1]
    mu, w_std = np.asarray(mu, np.float64), np.asarray(w_std, np.float64)

    for t in (0, 1, 10, 49):
        mean_tol = 5.0 * w_std / math.sqrt(num_chains)
        var_tol = 5.0 * w_std**2 * math.sqrt(2.0 / (num_chains - 1))
        assert np.all(np.abs(w[:, t].mean(0) - mu) < mean_tol), t
        assert np.all(np.abs(w[:, t].var(0, ddof=1) - w_std**2) < var_tol), t

    rho = 1.0 - beta
    z = (w - mu) / w_std
    for t in (0, 20, 48):
        products = (z[:, t] * z[:, t + 1]).reshape(-1)
        tol = 5.0 * math.sqrt((1.0 + rho**2) / products.size)
        assert abs(products.mean() - rho) < tol, t


def test_chain_special_cases_are_exact():
    """beta = 0 keeps the weights; beta = 1 forgets them (a fresh prior draw from the
    same key); step_weights with first draws from the prior; zero action noise gives
    the mean action w xh."""
    key = jax.random.key(3)
    mu = jnp.array([[0.5, -1.0, 0.2]], jnp.float32)
    w_std = jnp.array([[0.3, 1.0, 0.6]], jnp.float32)
    w_prev = jnp.array([[1.5, 2.0, -3.0]], jnp.float32)

    np.testing.assert_array_equal(coherent_samplers.sample_next_weights(key, w_prev, mu, w_std, 0.0), w_prev)
    fresh = coherent_samplers.sample_initial_weights(key, mu, w_std)
    np.testing.assert_array_equal(coherent_samplers.sample_next_weights(key, w_prev, mu, w_std, 1.0), fresh)
    np.testing.assert_array_equal(coherent_samplers.step_weights(key, w_prev, True, mu, w_std, 0.3), fresh)
    np.testing.assert_array_equal(
        coherent_samplers.step_weights(key, w_prev, False, mu, w_std, 0.3),
        coherent_samplers.sample_next_weights(key, w_prev, mu, w_std, 0.3),
    )

    x = jnp.array([0.2, -0.4], jnp.float32)
    a = coherent_samplers.sample_action(key, w_prev, x, jnp.zeros(1, jnp.float32))
    np.testing.assert_allclose(a, [1.5 * 0.2 - 2.0 * 0.4 - 3.0], rtol=1e-6)
    # Gradients through the sampler stay finite at the beta = 0 edge of the sqrt.
    grad = jax.grad(lambda b: jnp.sum(coherent_samplers.sample_next_weights(key, w_prev, mu, w_std, b)))
    assert np.isfinite(grad(jnp.float32(0.0)))


def test_sample_action_moments():
    """a ~ N(w xh, action_std^2): 40000 draws, mean and variance within 5 standard errors
    (the variance to about 3.5%)."""
    n = 40000
    w = jnp.array([[0.5, -1.0, 0.2], [1.0, 0.0, -0.5]], jnp.float32)
    x = jnp.array([0.3, 0.9], jnp.float32)
    action_std = jnp.array([0.1, 0.5], jnp.float32)
    keys = jax.random.split(jax.random.key(4), n)
    a = np.asarray(
        jax.vmap(coherent_samplers.sample_action, in_axes=(0, None, None, None))(keys, w, x, action_std)
    )
    mean = np.asarray(w) @ np.array([0.3, 0.9, 1.0])
    std = np.asarray(action_std, np.float64)
    assert np.all(np.abs(a.mean(0) - mean) < 5.0 * std / math.sqrt(n))
    assert np.all(np.abs(a.var(0, ddof=1) - std**2) < 5.0 * std**2 * math.sqrt(2.0 / (n - 1)))
