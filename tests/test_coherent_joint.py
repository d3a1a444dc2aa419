"""The parallel (joint-Gaussian / Cholesky) form of the coherent marginals.

Checked against the sequential filter, which tests/test_coherent_filter.py holds to
the thesis's dense recursion: same per-step log-probabilities, predictive variances
and end-of-segment belief, from an arbitrary stored belief, across episode resets.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.exploration.chain import chain_params
from coherent_jax.exploration.coherent import filter as C
from coherent_jax.exploration.coherent import joint as J


def random_problem(rng, T, p, q, resets):
    x = rng.normal(size=(T, q))
    a = rng.normal(size=(T, p))
    first = np.zeros(T, bool)
    first[list(resets)] = True
    mu = rng.normal(size=(p, q + 1))
    w_std = rng.uniform(0.2, 1.0, (p, q + 1))
    action_std = rng.uniform(0.1, 0.5, p)
    root = rng.normal(size=(p, q + 1, q + 1))
    cov0 = root @ root.transpose(0, 2, 1) / (q + 1) + 0.05 * np.eye(q + 1)
    belief0 = C.Belief(jnp.asarray(rng.normal(size=(p, q + 1))), jnp.asarray(cov0))
    return belief0, x, a, first, mu, w_std, action_std


@pytest.mark.parametrize("beta", [0.0, 0.01, 0.5, 1.0])
@pytest.mark.parametrize("resets", [(), (0,), (5,), (0, 7), (11,)])
def test_joint_equals_filter_float64(x64, beta, resets):
    rng = np.random.default_rng(hash((beta, resets)) % 2**32)
    belief0, x, a, first, *heads = random_problem(rng, T=12, p=3, q=4, resets=resets)
    args = (belief0, x, a, first, chain_params(*heads, beta))
    logp_f, belief_f, var_f = C.segment_marginals(*args)
    logp_j, belief_j, var_j = J.segment_marginals_joint(*args)
    assert logp_j.dtype == jnp.float64
    np.testing.assert_allclose(logp_j, logp_f, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(var_j, var_f, rtol=1e-10)
    np.testing.assert_allclose(belief_j.mean, belief_f.mean, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(belief_j.cov, belief_f.cov, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("beta", [0.0, 0.3, 1.0])
@pytest.mark.slow
def test_joint_gradients_equal_filter_gradients(x64, beta):
    rng = np.random.default_rng(1)
    belief0, x, a, first, mu, w_std, action_std = random_problem(rng, T=9, p=2, q=3, resets=(4,))
    weights = jnp.asarray(rng.normal(size=9))

    def loss(fn, x, mu, w_std, action_std):
        logp, _, _ = fn(belief0, x, a, first, chain_params(mu, w_std, action_std, beta))
        return jnp.sum(weights * logp)

    args = (jnp.asarray(x), jnp.asarray(mu), jnp.asarray(w_std), jnp.asarray(action_std))
    g_f = jax.grad(lambda *v: loss(C.segment_marginals, *v), argnums=(0, 1, 2, 3))(*args)
    g_j = jax.grad(lambda *v: loss(J.segment_marginals_joint, *v), argnums=(0, 1, 2, 3))(*args)
    for gf, gj in zip(g_f, g_j, strict=True):
        np.testing.assert_allclose(gj, gf, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("beta", [0.0, 0.01, 1.0])
@pytest.mark.slow
def test_joint_float32_consecutive_segments_match_float64(beta):
    """Realistic sizes in float32: 4 chained 64-step segments of one 256-step episode."""
    rng = np.random.default_rng(2)
    p, q, T = 6, 64, 64
    mu = jnp.asarray(0.1 * rng.normal(size=(p, q + 1)), jnp.float32)
    w_std = jnp.full((p, q + 1), 0.3, jnp.float32)
    action_std = jnp.full((p,), 0.1, jnp.float32)
    x = jnp.asarray(np.tanh(np.cumsum(rng.normal(size=(4 * T, q)), 0) * 0.1), jnp.float32)
    a = jnp.asarray(rng.normal(size=(4 * T, p)) * 0.5, jnp.float32)
    first = jnp.zeros((4 * T,), bool).at[0].set(True)
    chain = chain_params(mu, w_std, action_std, beta)
    ref = C.log_marginals(x, a, first, chain)
    belief = C.prior_belief(mu, w_std)
    logps = []
    for k in range(4):
        sl = slice(k * T, (k + 1) * T)
        logp, belief, _ = J.segment_marginals_joint(belief, x[sl], a[sl], first[sl], chain)
        logps.append(logp)
    logp = jnp.concatenate(logps)
    assert logp.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(logp)))
    np.testing.assert_allclose(logp, ref, rtol=2e-3, atol=2e-2)


@pytest.mark.parametrize("size", [1, *(pytest.param(n, marks=pytest.mark.slow) for n in (7, 16, 33))])
def test_whiten_reverse_pass_equals_jaxs_own(x64, size):
    """`linalg.whiten` (products with L^-1, forward and reverse) against JAX's generic
    Cholesky and triangular-solve rules, float64: cotangents on z alone (the loss), on z
    and log L_tt (the marginals), and on Y = L^-1 C as well (the chained beliefs), for a
    non-symmetric perturbation of K (symmetrised before the factorisation, as the joint
    form does), sizes on and off a power of two; and `tril_inverse` is the inverse."""
    from coherent_jax.exploration.linalg import tril_inverse, whiten

    rng = np.random.default_rng(size)
    root = rng.normal(size=(2, 3, size, size))
    cov = root @ root.transpose(0, 1, 3, 2) + 0.5 * np.eye(size) + 0.1 * rng.normal(size=(2, 3, size, size))
    resid = rng.normal(size=(2, 3, size))
    cross = rng.normal(size=(2, 3, size, 5))
    g, weights = rng.normal(size=(2, 3, size)), rng.normal(size=(2, 3, size, 5))

    def generic(k, r, c):
        chol = jnp.linalg.cholesky(k)
        z = jax.scipy.linalg.solve_triangular(chol, r[..., None], lower=True)[..., 0]
        y = jax.scipy.linalg.solve_triangular(chol, c, lower=True)
        return z, jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), y

    # Which outputs the loss reads: z alone; z and log L_tt (the marginals); Y as well
    # (the chained beliefs), also quadratically as the belief's covariance does.
    for reads in ("z", "z+logdiag", "z+logdiag+Y", "z+YY"):

        def loss(factor, k, r, c, reads=reads):
            z, log_diag, y = factor(0.5 * (k + jnp.swapaxes(k, -1, -2)), r, c)
            out = jnp.sum(g * (-0.5 * z**2)) + jnp.sum(jnp.sin(z))
            if "logdiag" in reads:
                out = out - jnp.sum(g * log_diag) + jnp.sum(jnp.exp(2.0 * log_diag))
            if "+Y" in reads:
                out = out + jnp.sum(weights * y)
            if "YY" in reads:
                out = out + jnp.sum(jnp.einsum("...tk,...tl->...kl", y, y) ** 2) + jnp.sum(y * z[..., None])
            return out

        want = jax.grad(lambda k, r, c: loss(generic, k, r, c), argnums=(0, 1, 2))(cov, resid, cross)
        got = jax.grad(lambda k, r, c: loss(whiten, k, r, c), argnums=(0, 1, 2))(cov, resid, cross)
        for w, v in zip(want, got, strict=True):
            np.testing.assert_allclose(v, w, rtol=1e-10, atol=1e-12, err_msg=reads)
    sym = 0.5 * (cov + cov.transpose(0, 1, 3, 2))
    for got, want in zip(whiten(sym, resid, cross), generic(sym, resid, cross), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    chol = np.linalg.cholesky(sym)
    np.testing.assert_allclose(
        tril_inverse(jnp.asarray(chol)) @ chol, np.broadcast_to(np.eye(size), chol.shape), atol=1e-12
    )


def test_masked_gram_reverse_pass_equals_a_loop_reference(x64):
    """`linalg.masked_gram`'s reverse pass (one product per matrix, from the symmetry of
    X D X') against the gradient of an independent elementwise formula written with
    explicit sums, float64, for a symmetric mask and a non-symmetric cotangent, with
    respect to every input (the mask carries beta's gradient)."""
    from coherent_jax.exploration.linalg import masked_gram

    rng = np.random.default_rng(3)
    t, n, p = 9, 5, 3
    x, var = rng.normal(size=(t, n)), rng.uniform(0.1, 2.0, (p, n))
    root = rng.normal(size=(t, t))
    mask, noise = root + root.T, rng.uniform(0.1, 1.0, p)
    weights = rng.normal(size=(p, t, t))  # not symmetric

    def reference(x, var, mask, noise):
        rows = []
        for i in range(p):
            gram = jnp.sum(x[:, None, :] * x[None, :, :] * var[i], axis=-1)
            rows.append(mask * gram + noise[i] * jnp.eye(t))
        return jnp.stack(rows)

    args = (x, var, mask, noise)
    np.testing.assert_allclose(masked_gram(*args), reference(*args), rtol=1e-13, atol=1e-13)
    want = jax.grad(lambda *v: jnp.sum(weights * reference(*v)), argnums=(0, 1, 2, 3))(*args)
    got = jax.grad(lambda *v: jnp.sum(weights * masked_gram(*v)), argnums=(0, 1, 2, 3))(*args)
    for name, w, g in zip(("x", "var", "mask", "noise_var"), want, got, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12, err_msg=name)
