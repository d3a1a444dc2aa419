"""On-policy loss terms against plain-Python loops and hand-computed values."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.agents import losses
from coherent_jax.exploration.base import Segment


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


# ------------------------------------------- the whole losses, at module level, typed batches


def _onpolicy_setup(dtype=np.float32, clipped=True):
    import jax

    from coherent_jax.agents.onpolicy_state import AgentParams, HParams
    from coherent_jax.exploration.action import ActionNoise
    from coherent_jax.networks import ValueNetwork

    T, m, o, p = 5, 3, 4, 2
    strategy = ActionNoise(p, (8,), "tanh", init_std=0.5)
    value_net = ValueNetwork((8,), "tanh")
    k = jax.random.split(jax.random.PRNGKey(0), 8)
    params = AgentParams(policy=strategy.init(k[0], o), value=value_net.init(k[1], jnp.zeros((1, o))))
    params = jax.tree.map(lambda x: jnp.asarray(x, dtype), params)
    obs = jax.random.normal(k[2], (T, m, o), dtype)
    action = jax.random.normal(k[3], (T, m, p), dtype)
    first = jnp.zeros((T, m), bool)
    current = strategy.log_prob(
        params.policy, {}, Segment(obs.reshape(-1, o), action.reshape(-1, p), first.reshape(-1))
    )
    batch = losses.SegmentBatch(
        segment=Segment(obs=obs, action=action, first=first),
        # near the current policy, so the ratios stay inside the clipping range
        behaviour_log_prob=current.log_prob.reshape(T, m) + 0.05 * jax.random.normal(k[4], (T, m), dtype),
        advantages=jax.random.normal(k[5], (T, m), dtype),
        targets=jax.random.normal(k[6], (T, m), dtype),
    )
    f = lambda v: jnp.asarray(v, dtype)  # noqa: E731
    hp = HParams(
        lr=f(0.0), gamma=f(0.9), gae_lambda=f(0.9), clip_eps=f(0.2), target_kl=f(0.0),
        vf_coef=f(0.5), ent_coef=f(0.01), explore={},
    )  # fmt: skip
    kwargs = dict(strategy=strategy, value_net=value_net, clipped=clipped, normalize_advantages=True)
    return params, hp, batch, kwargs


@pytest.mark.parametrize("clipped", [True, False], ids=["ppo", "a2c"])
def test_onpolicy_loss_against_float64_reference(clipped):
    """L = L_pi + vf_coef L_V - ent_coef H from the networks' outputs, recomputed in numpy float64."""
    import jax

    params, hp, batch, kwargs = _onpolicy_setup(clipped=clipped)
    loss, metrics = jax.jit(lambda pr, b: losses.onpolicy_loss(pr, hp, b, **kwargs))(params, batch)
    strategy, value_net = kwargs["strategy"], kwargs["value_net"]
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    mean = f64(strategy.mean_action(params.policy, batch.segment.obs))
    log_std = f64(params.policy["log_std"])
    a = f64(batch.segment.action)
    logp = np.sum(-0.5 * ((a - mean) / np.exp(log_std)) ** 2 - log_std - 0.5 * math.log(2 * math.pi), -1)
    adv = f64(batch.advantages)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    ratio = np.exp(logp - f64(batch.behaviour_log_prob))
    if clipped:
        pi = -np.mean(np.minimum(ratio * adv, np.clip(ratio, 0.8, 1.2) * adv))
    else:
        pi = -np.mean(logp * adv)
    v = 0.5 * np.mean((f64(value_net.apply(params.value, batch.segment.obs)) - f64(batch.targets)) ** 2)
    entropy = np.sum(log_std + 0.5 * math.log(2 * math.pi * math.e))
    np.testing.assert_allclose(float(metrics["policy_loss"]), pi, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["value_loss"]), v, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["entropy"]), entropy, rtol=1e-6)
    np.testing.assert_allclose(float(loss), pi + 0.5 * v - 0.01 * entropy, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["approx_kl"]), np.mean(ratio - 1 - np.log(ratio)), rtol=1e-4)


@pytest.mark.slow
def test_onpolicy_loss_gradient_matches_finite_differences():
    """In float64: the gradient along a random direction equals a central difference."""
    import jax

    with jax.enable_x64(True):
        params, hp, batch, kwargs = _onpolicy_setup(dtype=np.float64)
        leaves, treedef = jax.tree.flatten(params)
        keys = jax.random.split(jax.random.PRNGKey(5), len(leaves))
        direction = jax.tree.unflatten(
            treedef, [jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys, strict=True)]
        )
        h = 1e-6

        @jax.jit
        def derivatives(pr):
            loss = lambda q: losses.onpolicy_loss(q, hp, batch, **kwargs)[0]  # noqa: E731
            grad = jax.grad(loss)(pr)
            analytic = sum(
                jnp.sum(g * d) for g, d in zip(*map(jax.tree.leaves, (grad, direction)), strict=True)
            )
            shift = lambda s: jax.tree.map(lambda x, d: x + s * h * d, pr, direction)  # noqa: E731
            return analytic, (loss(shift(1.0)) - loss(shift(-1.0))) / (2 * h)

        analytic, numeric = map(float, derivatives(params))
        assert abs(analytic) > 1e-3
        np.testing.assert_allclose(analytic, numeric, rtol=1e-6)


def test_sac_losses_against_float64_reference():
    """Critic (2.46), soft target (2.47), actor (2.51) and temperature losses and the temperature's
    gradient, from the networks' outputs and the same noise draws, recomputed in numpy float64."""
    import jax

    from coherent_jax.agents import sac_losses
    from coherent_jax.agents.replay import Experience
    from coherent_jax.networks import QNetwork, SquashedGaussianActor

    B, o, p = 6, 3, 2
    actor = SquashedGaussianActor(p, (8,), "relu")
    critic = QNetwork((8,), "relu")
    k = jax.random.split(jax.random.PRNGKey(1), 10)
    actor_params = actor.init(k[0], o)
    critic_params = jax.vmap(lambda kk: critic.init(kk, jnp.zeros((1, o)), jnp.zeros((1, p))))(
        jax.random.split(k[1])
    )
    target_params = jax.tree.map(lambda x: x + 0.1, critic_params)
    batch = Experience(
        obs=jax.random.normal(k[2], (B, o)),
        action=jax.random.uniform(k[3], (B, p), minval=-1, maxval=1),
        reward=jax.random.normal(k[4], (B,)),
        next_obs=jax.random.normal(k[5], (B, o)),
        terminated=(jax.random.uniform(k[6], (B,)) < 0.3).astype(jnp.float32),
    )
    gamma, alpha = 0.9, 0.3
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731

    draw = jax.jit(lambda key, obs: (actor.dist(actor_params, obs), jax.random.normal(key, (B, p))))
    q_jit = jax.jit(lambda params, obs, action: sac_losses.q_values(critic, params, obs, action))

    def sample(key, obs):  # tanh(mean + std xi) and log pi, with xi as `squash` draws it
        dist, xi = draw(key, obs)
        xi = f64(xi)
        u = f64(dist.mean) + np.exp(f64(dist.log_std)) * xi
        logp = np.sum(
            -0.5 * xi**2 - f64(dist.log_std) - 0.5 * math.log(2 * math.pi) - np.log(1 - np.tanh(u) ** 2), -1
        )
        return np.tanh(u), logp

    def q(params, obs, action):
        return f64(q_jit(params, obs, jnp.asarray(action, jnp.float32)))

    target_entropy = -2.0
    nets = dict(actor=actor, critic=critic)

    @jax.jit
    def outputs():
        y = sac_losses.critic_target(actor_params, target_params, batch, k[7], gamma, alpha, **nets)
        c_loss, _ = sac_losses.critic_loss(critic_params, batch, y, critic=critic)
        a_loss, logp = sac_losses.actor_loss(actor_params, critic_params, batch, k[8], alpha, **nets)
        t_loss, t_grad = jax.value_and_grad(sac_losses.temperature_loss)(jnp.log(alpha), logp, target_entropy)
        return y, c_loss, a_loss, logp, t_loss, t_grad

    y_jax, c_loss, a_loss, logp, t_loss, grad = outputs()
    next_a, next_logp = sample(k[7], batch.next_obs)
    soft = np.min(q(target_params, batch.next_obs, next_a), 0) - alpha * next_logp
    y = f64(batch.reward) + gamma * (1 - f64(batch.terminated)) * soft
    np.testing.assert_allclose(y_jax, y, rtol=1e-5, atol=1e-5)
    ref_c = np.sum(np.mean((q(critic_params, batch.obs, batch.action) - y[None]) ** 2, axis=1))
    np.testing.assert_allclose(float(c_loss), ref_c, rtol=1e-5)

    a, ref_logp = sample(k[8], batch.obs)
    ref_a = np.mean(alpha * ref_logp - np.min(q(critic_params, batch.obs, a), 0))
    np.testing.assert_allclose(logp, ref_logp, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(float(a_loss), ref_a, rtol=1e-4, atol=1e-5)

    ref_t = -math.log(alpha) * np.mean(ref_logp + target_entropy)
    np.testing.assert_allclose(float(t_loss), ref_t, rtol=1e-4)
    np.testing.assert_allclose(float(grad), -np.mean(ref_logp + target_entropy), rtol=1e-4)
