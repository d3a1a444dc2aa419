"""Lattice (explore=lattice): its density against an independent float64 numpy reference,
its noise's covariance and resampling period, its switches, and its SAC behaviour.

The reference builds Sigma(x) = alpha^2 W' diag(sigma_x^2' x^2) W + diag(sigma_a^2' x^2)
+ std_reg^2 I (plus the 1e-6 floor) from the parameters in float64 and scores with
numpy's slogdet and solve, not a Cholesky factor. The head's kernel is set to a large
random matrix so that the latent term (and the correlation it induces) is not
negligible, as it is at initialisation.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.agents.registry import make_behaviour, make_strategy
from coherent_jax.config import ConfigError, parse_overrides
from coherent_jax.exploration.base import Segment
from coherent_jax.networks import SquashedGaussianActor
from coherent_jax.run.training import train

OBS_SIZE, ACTIONS, HIDDEN = 5, 3, 8


def segment_of(obs, actions) -> Segment:
    """One env's segment of these steps, none of them an episode start (lattice reads neither)."""
    obs, actions = jnp.asarray(obs), jnp.asarray(actions)
    return Segment(obs, actions, jnp.zeros(obs.shape[:1], bool))


def build(*overrides):
    cfg = parse_overrides(
        ["env=pointmass", f"policy_hidden=[{HIDDEN},{HIDDEN}]", "explore=lattice", *overrides]
    )
    return make_strategy(cfg, ACTIONS)


def params_with_big_kernel(strategy, seed=0):
    """Initial parameters with the mean head's kernel N(0, 0.7^2) and unequal stds."""
    k_init, k_w, k_s = jax.random.split(jax.random.PRNGKey(seed), 3)
    params = strategy.init(k_init, OBS_SIZE)
    head = params["net"]["params"]["Dense_0"]
    head["kernel"] = 0.7 * jax.random.normal(k_w, head["kernel"].shape)
    params["log_std"] = params["log_std"] + 0.3 * jax.random.normal(k_s, params["log_std"].shape)
    return params


def reference_cov(strategy, params, x, alpha=1.0, action_noise=True, std_reg=0.0):
    """Sigma(x) in float64 from the raw parameters, x [d]."""
    d = x.shape[-1]
    std = np.exp(np.clip(np.asarray(params["log_std"], np.float64), np.log(1e-3), np.log(10.0))) / np.sqrt(d)
    w = np.asarray(params["net"]["params"]["Dense_0"]["kernel"], np.float64)  # [d, p]
    latent_var = (x[:, None] ** 2 * std[:, :d] ** 2).sum(0)
    cov = alpha**2 * w.T @ np.diag(latent_var) @ w
    diag = np.full(w.shape[1], std_reg**2 + 1e-6)
    if action_noise:
        diag += (x[:, None] ** 2 * std[:, d:] ** 2).sum(0)
    return cov + np.diag(diag)


def reference_log_prob(a, mean, cov):
    r = a - mean
    _, logdet = np.linalg.slogdet(cov)
    return -0.5 * r @ np.linalg.solve(cov, r) - 0.5 * logdet - 0.5 * len(r) * np.log(2 * np.pi)


def features(strategy, params, obs):
    x, mean = strategy.net.apply(params["net"], obs)
    return np.asarray(x, np.float64), np.asarray(mean, np.float64)


SWITCHES = [
    dict(alpha=1.0, action_noise=True, std_reg=0.0),
    dict(alpha=0.5, action_noise=True, std_reg=0.2),
    dict(alpha=1.5, action_noise=False, std_reg=0.0),
    dict(alpha=0.0, action_noise=True, std_reg=0.0),  # gSDE's noise alone
]


def overrides_of(sw):
    return [f"lattice.alpha={sw['alpha']}", f"lattice.action_noise={str(sw['action_noise']).lower()}",
            f"lattice.std_reg={sw['std_reg']}"]  # fmt: skip


@pytest.mark.parametrize("sw", SWITCHES, ids=lambda s: "-".join(f"{k}{v}" for k, v in s.items()))
def test_log_prob_and_entropy_equal_float64_reference(sw):
    strategy = build(*overrides_of(sw))
    params = params_with_big_kernel(strategy)
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(7, OBS_SIZE)).astype(np.float32)
    actions = rng.normal(size=(7, ACTIONS)).astype(np.float32)
    got = strategy.log_prob(params, {}, segment_of(obs, actions))
    x, mean = features(strategy, params, obs)
    for t in range(7):
        cov = reference_cov(strategy, params, x[t], **sw)
        want = reference_log_prob(actions[t].astype(np.float64), mean[t], cov)
        np.testing.assert_allclose(got.log_prob[t], want, rtol=1e-4, atol=1e-3)
        entropy = 0.5 * np.linalg.slogdet(cov)[1] + 0.5 * ACTIONS * (1 + np.log(2 * np.pi))
        np.testing.assert_allclose(got.entropy[t], entropy, rtol=1e-4, atol=1e-3)


def run_fixed_state(strategy, params, num_envs, steps, first_every, seed=0):
    """Noise a - mean(s) at one state in ``num_envs`` envs, [T, n, p]; ``first`` every ``first_every``."""
    k_c, k_o, k_run = jax.random.split(jax.random.PRNGKey(seed), 3)
    carry = strategy.init_carry(k_c, params, {}, num_envs)
    obs = jnp.broadcast_to(jax.random.normal(k_o, (OBS_SIZE,)), (num_envs, OBS_SIZE))
    firsts = jnp.arange(steps) % first_every == 0

    @jax.jit
    def go(carry):
        def step(c, inp):
            k, f = inp
            out = strategy.act(k, params, {}, c, obs, jnp.full((num_envs,), f))
            return out.carry, (out.action, out.log_prob)

        return jax.lax.scan(step, carry, (jax.random.split(k_run, steps), firsts))[1]

    actions, log_prob = go(carry)
    mean = strategy.mean_action(params, obs)
    return np.asarray(actions - mean[None], np.float64), np.asarray(log_prob), np.asarray(obs[:1])


@pytest.mark.parametrize("sw", SWITCHES[:3], ids=lambda s: "-".join(f"{k}{v}" for k, v in s.items()))
def test_noise_covariance_is_sigma_and_stored_log_prob_is_its_density(sw):
    """Many envs at one state, each with fresh matrices: the noise's covariance is the
    reference Sigma(x) (correlated across action dimensions), and the stored
    log-probability of each action is the reference density."""
    strategy = build(*overrides_of(sw))
    params = params_with_big_kernel(strategy)
    noise, log_prob, obs = run_fixed_state(strategy, params, 8192, 1, first_every=1)
    x, mean = features(strategy, params, obs)
    cov = reference_cov(strategy, params, x[0], **sw)
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.abs(corr - np.eye(ACTIONS)).max() > 0.2  # the latent noise correlates the actions
    emp = np.cov(noise[0].T)
    np.testing.assert_allclose(emp, cov, atol=0.06 * np.diag(cov).max())
    for i in range(5):
        want = reference_log_prob(noise[0, i] + mean[0], mean[0], cov)
        np.testing.assert_allclose(log_prob[0, i], want, rtol=1e-4, atol=1e-3)


@pytest.mark.slow
def test_noise_matrices_held_for_n_steps_and_redrawn_at_n_and_episode_starts():
    every, first_every, steps = 4, 11, 25
    strategy = build(f"lattice.resample_every={every}")
    params = params_with_big_kernel(strategy)
    noise, _, _ = run_fixed_state(strategy, params, 64, steps, first_every=first_every)
    change = np.abs(np.diff(noise, axis=0)).max(axis=(1, 2)) > 1e-6  # between t-1 and t
    # Steps since the last redraw restart at each episode start.
    redraw = [t for t in range(1, steps) if (t % first_every) % every == 0]
    assert [t for t in range(1, steps) if change[t - 1]] == redraw
    assert 11 in redraw and 12 not in redraw and 15 in redraw  # the period restarts at the reset


@pytest.mark.slow
def test_white_std_reg_noise_changes_every_step():
    strategy = build("lattice.resample_every=100", "lattice.std_reg=0.1")
    noise, _, _ = run_fixed_state(strategy, params_with_big_kernel(strategy), 16, 5, first_every=100)
    assert (np.abs(np.diff(noise, axis=0)).max(axis=(1, 2)) > 1e-4).all()


@pytest.mark.parametrize("weight_grad", [True, False])
def test_weight_grad_switch(weight_grad):
    """Detached: the kernel's gradient of log p is the mean's alone, x (Sigma^-1 r)' (float64);
    with the gradient it differs from that by the covariance's part."""
    strategy = build(f"lattice.weight_grad={str(weight_grad).lower()}")
    params = params_with_big_kernel(strategy)
    rng = np.random.default_rng(2)
    obs = jnp.asarray(rng.normal(size=(4, OBS_SIZE)), jnp.float32)
    actions = jnp.asarray(rng.normal(size=(4, ACTIONS)), jnp.float32)

    def total(p):
        return jnp.sum(strategy.log_prob(p, {}, segment_of(obs, actions)).log_prob)

    grad = np.asarray(jax.grad(total)(params)["net"]["params"]["Dense_0"]["kernel"], np.float64)
    x, mean = features(strategy, params, np.asarray(obs))
    mean_part = sum(
        np.outer(
            x[t], np.linalg.solve(reference_cov(strategy, params, x[t]), np.asarray(actions[t]) - mean[t])
        )
        for t in range(4)
    )
    if weight_grad:
        assert np.abs(grad - mean_part).max() > 1e-2
    else:
        np.testing.assert_allclose(grad, mean_part, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("gain", [None, 0.57735])
def test_head_starts_at_its_gain_and_latent_noise_is_its_share_of_the_variance(gain):
    """At the start every std is equal, so with W's columns of norm g (orthogonal init) the
    latent noise adds g^2 of the action noise's variance to each dimension: Sigma_jj with
    alpha = 1 over Sigma_jj with alpha = 0 (gSDE's noise) is 1 + g^2 (1e-4 at the default,
    every strategy's 0.01; 1/3 at the reference's PyTorch init)."""
    given = [] if gain is None else [f"lattice.head_gain={gain}"]
    g = 0.01 if gain is None else gain
    strategy = build(*given)
    params = strategy.init(jax.random.PRNGKey(0), OBS_SIZE)
    kernel = np.asarray(params["net"]["params"]["Dense_0"]["kernel"], np.float64)  # [d, p]
    np.testing.assert_allclose(np.linalg.norm(kernel, axis=0), g, rtol=1e-4)
    obs = jax.random.normal(jax.random.PRNGKey(1), (16, OBS_SIZE))
    with_latent = np.diagonal(np.asarray(strategy._dist(params, obs)[2], np.float64), axis1=-2, axis2=-1)
    gsde_like = build(*given, "lattice.alpha=0")
    without = np.diagonal(np.asarray(gsde_like._dist(params, obs)[2], np.float64), axis1=-2, axis2=-1)
    np.testing.assert_allclose((with_latent - 1e-6) / (without - 1e-6), 1 + g**2, rtol=1e-3)
    # SAC's actor starts its mean head at the same gain; other strategies' at 0.01.
    from coherent_jax.agents.sac import make_actor

    for explore, expected in (("lattice", g), ("gsde", 0.01)):  # gsde ignores lattice.head_gain
        cfg = parse_overrides(["env=pointmass", "algo=sac", f"explore={explore}", *given])
        actor = make_actor(cfg, ACTIONS, make_behaviour(cfg, ACTIONS))
        mu = np.asarray(actor.init(jax.random.PRNGKey(2), OBS_SIZE)["mu"], np.float64)
        np.testing.assert_allclose(np.linalg.norm(mu[:, :-1], axis=1), expected, rtol=1e-4)


def test_no_noise_at_all_is_refused():
    with pytest.raises(ConfigError, match="lattice.alpha"):
        parse_overrides(["explore=lattice", "lattice.action_noise=false", "lattice.alpha=0"])


# ------------------------------------------------------------------------- SAC


def sac_behaviour_run(steps, first_every, num_envs=4096, *overrides):
    cfg = parse_overrides(["env=pointmass", "algo=sac", "explore=lattice", *overrides])
    behaviour = make_behaviour(cfg, ACTIONS)
    actor = SquashedGaussianActor(ACTIONS, (HIDDEN, HIDDEN), "relu")
    k_p, k_w, k_c, k_o, k_run = jax.random.split(jax.random.PRNGKey(0), 5)
    actor_params = actor.init(k_p, OBS_SIZE)
    actor_params["mu"] = (
        actor_params["mu"].at[:, :HIDDEN].set(0.7 * jax.random.normal(k_w, (ACTIONS, HIDDEN)))
    )
    carry = behaviour.init_carry(k_c, actor, actor_params, {}, num_envs)
    obs = jnp.broadcast_to(jax.random.normal(k_o, (OBS_SIZE,)), (num_envs, OBS_SIZE))
    firsts = jnp.arange(steps) % first_every == 0

    @jax.jit
    def go(carry):
        def step(c, inp):
            k, f = inp
            action, c = behaviour.act(k, actor, actor_params, {}, c, obs, jnp.full((num_envs,), f))
            return c, action

        return jax.lax.scan(step, carry, (jax.random.split(k_run, steps), firsts))[1]

    actions = np.asarray(go(carry), np.float64)
    dist = actor.dist(actor_params, obs[:1])
    xi = (np.arctanh(np.clip(actions, -1 + 1e-7, 1 - 1e-7)) - np.asarray(dist.mean)) / np.exp(
        np.asarray(dist.log_std)
    )
    w = np.asarray(actor_params["mu"][:, :HIDDEN], np.float64)  # [p, q]
    return xi, w


@pytest.mark.parametrize("action_noise", [True, False])
def test_sac_xi_unit_variance_correlated_through_the_mean_head(action_noise):
    """xi_j ~ N(0, 1) at a state, with correlation that of alpha^2 W W' + I (float64)."""
    xi, w = sac_behaviour_run(
        1, 1, 4096, f"lattice.action_noise={str(action_noise).lower()}", "lattice.alpha=0.8"
    )
    cov = 0.64 * w @ w.T + (np.eye(ACTIONS) if action_noise else 0.0)
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    np.testing.assert_allclose(np.cov(xi[0].T), corr, atol=0.08)


def test_sac_noise_held_for_n_steps():
    xi, _ = sac_behaviour_run(12, 100, 8, "lattice.resample_every=4")
    change = np.abs(np.diff(xi, axis=0)).max(axis=(1, 2)) > 1e-4
    assert [t for t in range(1, 12) if change[t - 1]] == [4, 8]


@pytest.mark.slow
def test_sac_runs_updates_with_lattice():
    """A few SAC iterations past warm-up: updates applied, losses finite."""
    cfg = parse_overrides(
        [
            "env=pointmass",
            "algo=sac",
            "explore=lattice",
            "num_envs=4",
            "unroll_length=16",
            "episode_length=40",
            "policy_hidden=[16,16]",
            "value_hidden=[16,16]",
            "sac.warmup_steps=64",
            "sac.batch_size=32",
            "sac.buffer_size=1024",
            "total_steps=384",
            "eval_episodes=2",
            "progress=false",
        ]
    )
    rows = []
    train(cfg, None, progress_fn=lambda i, m: rows.append(m))
    updated = [r for r in rows if r.get("train/updates_applied", 0) > 0]
    assert len(updated) >= 3
    for r in updated:
        assert np.isfinite(r["train/critic_loss"]) and np.isfinite(r["train/actor_loss"])
