"""On-policy loss terms against plain-Python loops and hand-computed values."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.agents import losses


def gae_loop(rewards, values, next_values, terminated, truncated, gamma, lam):
    """CleanRL-style reference: an explicit backward loop, one env at a time."""
    T, n = rewards.shape
    adv = np.zeros((T, n))
    for e in range(n):
        running = 0.0
        for t in reversed(range(T)):
            done = terminated[t, e] or truncated[t, e]
            bootstrap = 0.0 if terminated[t, e] else next_values[t, e]
            delta = rewards[t, e] + gamma * bootstrap - values[t, e]
            running = delta + (0.0 if done else gamma * lam * running)
            adv[t, e] = running
    return adv, adv + values


@pytest.mark.parametrize("gamma,lam", [(0.99, 0.95), (0.9, 1.0), (0.5, 0.0)])
def test_gae_matches_python_loop(gamma, lam):
    rng = np.random.default_rng(0)
    T, n = 23, 5
    rewards = rng.normal(size=(T, n))
    values = rng.normal(size=(T, n))
    next_values = rng.normal(size=(T, n))
    terminated = rng.random((T, n)) < 0.1
    truncated = (rng.random((T, n)) < 0.1) & ~terminated
    ref_adv, ref_ret = gae_loop(rewards, values, next_values, terminated, truncated, gamma, lam)
    adv, ret = losses.gae(
        jnp.asarray(rewards, jnp.float32),
        jnp.asarray(values, jnp.float32),
        jnp.asarray(next_values, jnp.float32),
        jnp.asarray(terminated),
        jnp.asarray(terminated | truncated),
        gamma,
        lam,
    )
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret, ref_ret, rtol=1e-5, atol=1e-5)


def test_gae_truncation_bootstraps_termination_does_not():
    """Same step, same values: truncation adds gamma V(s'), termination adds nothing."""
    r = jnp.array([[1.0]])
    v = jnp.array([[0.5]])
    nv = jnp.array([[10.0]])
    adv_trunc, _ = losses.gae(r, v, nv, jnp.array([[False]]), jnp.array([[True]]), 0.9, 0.95)
    adv_term, _ = losses.gae(r, v, nv, jnp.array([[True]]), jnp.array([[True]]), 0.9, 0.95)
    assert float(adv_trunc[0, 0]) == pytest.approx(1.0 + 0.9 * 10.0 - 0.5)
    assert float(adv_term[0, 0]) == pytest.approx(1.0 - 0.5)


def test_ppo_clip_loss_hand_computed():
    # ratios e^{0.5}=1.6487 (A=+1, clipped to 1.2), e^{-0.5}=0.6065 (A=+2, unclipped
    # min picks 0.6065*2), e^{0.1}=1.1052 (A=-1, min(-1.1052, -1.1052)).
    logp = jnp.array([0.5, -0.5, 0.1])
    old = jnp.zeros(3)
    adv = jnp.array([1.0, 2.0, -1.0])
    loss, info = losses.ppo_clip_loss(logp, old, adv, 0.2)
    expected = -(1.2 * 1.0 + math.exp(-0.5) * 2.0 + -math.exp(0.1)) / 3
    assert float(loss) == pytest.approx(expected, rel=1e-6)
    ratios = np.exp([0.5, -0.5, 0.1])
    assert float(info.clip_fraction) == pytest.approx(2 / 3)
    assert float(info.approx_kl) == pytest.approx(np.mean(ratios - 1 - np.log(ratios)), rel=1e-5)


def test_ppo_clip_loss_negative_advantage_clips_below():
    # ratio 0.5 < 1 - eps with A = -1: min(-0.5, -0.8) = -0.8 (pessimistic bound).
    loss, _ = losses.ppo_clip_loss(jnp.log(jnp.array([0.5])), jnp.zeros(1), jnp.array([-1.0]), 0.2)
    assert float(loss) == pytest.approx(0.8, rel=1e-6)


def test_a2c_loss_hand_computed():
    logp = jnp.array([-1.0, -2.0])
    adv = jnp.array([3.0, -1.0])
    loss, info = losses.a2c_loss(logp, logp, adv)
    assert float(loss) == pytest.approx(-((-1.0 * 3.0) + (-2.0 * -1.0)) / 2)
    assert float(info.approx_kl) == pytest.approx(0.0)


def test_value_loss_and_standardize():
    assert float(losses.value_loss(jnp.array([1.0, 2.0]), jnp.array([0.0, 4.0]))) == pytest.approx(
        0.5 * (1 + 4) / 2
    )
    z = losses.standardize(jnp.array([1.0, 2.0, 3.0, 4.0]))
    assert float(z.mean()) == pytest.approx(0.0, abs=1e-6)
    assert float(z.std()) == pytest.approx(1.0, rel=1e-5)
