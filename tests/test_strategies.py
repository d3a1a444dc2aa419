"""Exploration strategies: noise statistics, resampling, stored log-probs.

Statistics are checked against independent float64 numpy references (the chain's
stationary autocorrelation, the coloured spectrum's autocorrelation, gSDE's
variance formula, NoisyNet's explicit weight matrix) on many envs held at one
state, so the behaviour noise is exactly the strategy's noise.
"""

import functools
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import child_env

from coherent_jax.agents.onpolicy import OnPolicyTrainer
from coherent_jax.agents.registry import make_behaviour, make_strategy
from coherent_jax.agents.rollout import unroll
from coherent_jax.config import parse_overrides
from coherent_jax.envs import VecEnv
from coherent_jax.exploration.base import SEGMENT_AXES, Segment
from coherent_jax.exploration.noisynet import factorised, noisy_dense
from coherent_jax.exploration.pink import autocorrelation, coloured_noise
from coherent_jax.exploration.psne import perturb
from coherent_jax.networks import SquashedGaussianActor

OBS_SIZE = 6


def build(*overrides, action_size=2):
    cfg = parse_overrides(["env=pointmass", "policy_hidden=[16,16]", *overrides])
    return make_strategy(cfg, action_size), cfg


def build_behaviour(*overrides, action_size=2):
    cfg = parse_overrides(["env=pointmass", "algo=sac", "policy_hidden=[16,16]", *overrides])
    return make_behaviour(cfg, action_size)


def run_fixed_state(strategy, num_envs, steps, first_every=0, seed=0):
    """Acts ``steps`` times in ``num_envs`` envs held at one state; returns noise, extras, carries.

    Behaviour noise = action - mean_action at that state. ``first`` is True at t = 0
    and every ``first_every`` steps (0: only at t = 0).
    """
    key = jax.random.PRNGKey(seed)
    k_p, k_c, k_o, k_run = jax.random.split(key, 4)
    params = strategy.init(k_p, OBS_SIZE)
    hp = strategy.init_hparams()
    carry = strategy.init_carry(k_c, params, hp, num_envs)
    obs = jnp.broadcast_to(jax.random.normal(k_o, (OBS_SIZE,)), (num_envs, OBS_SIZE))
    t = jnp.arange(steps)
    firsts = t == 0 if first_every == 0 else t % first_every == 0

    @jax.jit
    def go(carry):
        def step(c, inp):
            k, f = inp
            out = strategy.act(k, params, hp, c, obs, jnp.full((num_envs,), f))
            return out.carry, (out.action, out.extras, out.carry)

        return jax.lax.scan(step, carry, (jax.random.split(k_run, steps), firsts))[1]

    actions, extras, carries = go(carry)
    noise = np.asarray(actions, np.float64) - np.asarray(strategy.mean_action(params, obs), np.float64)
    return noise, extras, carries, params, obs


def lag1(noise, start=0):
    """Lag-1 autocorrelation pooled over envs and action dims, noise [T, n, p] (zero mean)."""
    x = noise[start:]
    return float(np.sum(x[1:] * x[:-1]) / np.sqrt(np.sum(x[1:] ** 2) * np.sum(x[:-1] ** 2)))


# ---------------------------------------------------------------- white / coherent


def test_action_noise_is_white_with_its_std():
    strategy, _ = build("explore=action", "init_std=0.3")
    noise, *_ = run_fixed_state(strategy, 512, 64)
    assert noise.std() == pytest.approx(0.3, rel=0.03)
    assert abs(lag1(noise)) < 0.03


@pytest.mark.parametrize("integration", ["analytic", "mc"])
def test_coherent_noise_autocorrelation_is_one_minus_beta(integration):
    """Noise n_t = (w_std z_t).xh + action_std eps_t: Corr(n_t, n_t+1) = (1-beta) V / (V + action_std^2).

    V = sum_k w_std_k^2 xh_k^2 is computed in float64 from the parameters; the
    stationary variance V + action_std^2 is checked too. Same chain for both
    integrations (only the loss differs).
    """
    beta, action_std = 0.2, 0.05
    strategy, _ = build(
        "explore=coherent",
        f"coherent.integration={integration}",
        f"coherent.beta={beta}",
        f"coherent.action_std={action_std}",
        "coherent.w_std_init=0.3",
    )
    noise, _, _, params, obs = run_fixed_state(strategy, 256, 200)
    x = np.asarray(strategy.layer.features(params, obs[:1]), np.float64)[0]
    xh = np.append(x, 1.0)
    w_std = np.exp(np.asarray(params["log_w_std"], np.float64))
    v = (w_std**2 * xh**2).sum(axis=1)  # [p]
    expected = (1 - beta) * v / (v + action_std**2)
    for i in range(noise.shape[-1]):
        assert lag1(noise[..., i : i + 1]) == pytest.approx(expected[i], abs=0.03)
        assert noise[..., i].var() == pytest.approx(v[i] + action_std**2, rel=0.1)


def test_coherent_all_layers_chain_statistics_and_resets():
    """layers=all: every weight's z chain is N(0, 1) with lag-1 autocorrelation 1 - beta;
    a new episode draws z afresh (independent of the last step)."""
    beta = 0.3
    strategy, _ = build(
        "explore=coherent", "coherent.integration=mc", "coherent.layers=all", f"coherent.beta={beta}"
    )
    noise, extras, _, _, _ = run_fixed_state(strategy, 64, 120, first_every=40)
    z = np.concatenate([np.asarray(v).reshape(120, 64, -1) for v in jax.tree.leaves(extras)], axis=-1)
    assert z.var() == pytest.approx(1.0, rel=0.03)
    within = [t for t in range(1, 120) if t % 40 != 0]
    across = [t for t in range(1, 120) if t % 40 == 0]
    corr = lambda ts: float(np.mean(z[ts] * z[[t - 1 for t in ts]]))  # noqa: E731
    assert corr(within) == pytest.approx(1 - beta, abs=0.02)
    assert abs(corr(across)) < 0.02
    assert lag1(noise) > 0.3  # the action noise inherits the coherence


# --------------------------------------------------------------------------- pink


def test_coloured_noise_matches_its_spectrum():
    """Unit variance at every exponent; lag-1 and lag-5 autocorrelations match the float64 formula."""
    length = 200
    for exponent in (0.0, 1.0, 2.0):
        xi = np.asarray(coloured_noise(jax.random.PRNGKey(1), exponent, length, (2000,)), np.float64)
        assert xi.var() == pytest.approx(1.0, rel=0.03)
        for lag in (1, 5):
            sample = float(np.mean(xi[lag:] * xi[:-lag]))
            assert sample == pytest.approx(autocorrelation(length, exponent, lag), abs=0.03)
    assert abs(autocorrelation(length, 0.0, 1)) < 0.01  # -1/(2L-3): no DC term
    assert autocorrelation(length, 1.0, 1) > 0.3 and autocorrelation(length, 2.0, 1) > 0.9


@pytest.mark.parametrize("exponent,low,high", [(0.0, -0.04, 0.04), (1.0, 0.3, 0.9)])
def test_pink_behaviour_noise(exponent, low, high):
    """Behaviour noise has the policy's std, white at exponent 0, clearly positive at 1,
    and each episode draws a new sequence (uncorrelated across the reset)."""
    strategy, _ = build("explore=pink", f"pink.exponent={exponent}", "init_std=0.4", "episode_length=50")
    noise, _, carries, _, _ = run_fixed_state(strategy, 256, 100, first_every=50)
    assert noise.std() == pytest.approx(0.4, rel=0.05)
    assert low < lag1(noise[:50]) < high
    assert lag1(noise[:50]) == pytest.approx(autocorrelation(50, exponent, 1), abs=0.05)
    assert abs(float(np.mean(noise[50] * noise[49])) / 0.16) < 0.1
    np.testing.assert_array_equal(
        np.asarray(carries.step)[[0, 49, 50, 99]], [[1] * 256, [50] * 256, [1] * 256, [50] * 256]
    )


# --------------------------------------------------------------------------- gsde


def test_gsde_noise_resamples_every_n_and_has_its_variance():
    """The noise matrix is held for n steps (noise constant at a fixed state), redrawn at
    multiples of n and at episode starts; its variance is sum_i x_i^2 sigma_ij^2 (float64)."""
    every = 5
    strategy, _ = build("explore=gsde", f"gsde.resample_every={every}", "init_std=0.5")
    noise, _, _, params, obs = run_fixed_state(strategy, 2048, 23, first_every=13)
    change = np.abs(np.diff(noise, axis=0)).max(axis=(1, 2)) > 1e-6  # between t-1 and t
    redraw = [t for t in range(1, 23) if t % 13 == 0 or (t % 13) % every == 0]
    assert [t for t in range(1, 23) if change[t - 1]] == redraw
    x = np.asarray(strategy.net.apply(params["net"], obs[:1])[0], np.float64)[0]
    sigma = np.exp(np.asarray(params["log_sigma"], np.float64))
    var = (x[:, None] ** 2 * sigma**2).sum(axis=0)
    np.testing.assert_allclose(noise[0].var(axis=0), var, rtol=0.1)


# ----------------------------------------------------------------------- noisynet


def test_noisy_dense_equals_explicit_weights():
    """The factorised layer equals x (mu_W + sigma_W * f(eps_in) f(eps_out)^T) + mu_b + sigma_b f(eps_out)."""
    rng = np.random.default_rng(0)
    m, k = 5, 3
    layer = {
        name: rng.normal(size=s)
        for name, s in [("w_mu", (m, k)), ("b_mu", k), ("w_sigma", (m, k)), ("b_sigma", k)]
    }
    x, e_in, e_out = rng.normal(size=m), rng.normal(size=m), rng.normal(size=k)
    f = lambda e: np.sign(e) * np.sqrt(np.abs(e))  # noqa: E731
    w = layer["w_mu"] + layer["w_sigma"] * np.outer(f(e_in), f(e_out))
    expected = x @ w + layer["b_mu"] + layer["b_sigma"] * f(e_out)
    got = noisy_dense({n: jnp.asarray(v, jnp.float32) for n, v in layer.items()}, x, e_in, e_out)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(factorised(jnp.array([-4.0, 0.0, 9.0])), [-2.0, 0.0, 3.0])


def test_noisynet_noise_is_fixed_per_episode_with_initial_sigma():
    strategy, _ = build("explore=noisynet", "noisynet.sigma0=0.5")
    noise, extras, _, params, _ = run_fixed_state(strategy, 64, 30, first_every=10)
    for leaf in jax.tree.leaves(extras):
        leaf = np.asarray(leaf)
        for t in range(1, 30):
            same = np.array_equal(leaf[t], leaf[t - 1])
            assert same == (t % 10 != 0), t
    for layer in params["layers"]:
        fan_in = layer["w_mu"].shape[0]
        np.testing.assert_allclose(layer["w_sigma"], 0.5 / np.sqrt(fan_in), rtol=1e-6)
    # The sampled network shows in the behaviour noise: positively correlated within an episode.
    assert lag1(noise) > 0.05


# --------------------------------------------------------------------------- psne


def test_psne_perturbation_scale_and_layer_norm_untouched():
    params = {
        "params": {
            "Dense_0": {"kernel": jnp.zeros((200, 100)), "bias": jnp.zeros(100)},
            "LayerNorm_0": {"scale": jnp.ones(100), "bias": jnp.zeros(100)},
        }
    }
    out = perturb(params, jax.random.PRNGKey(0), 0.3)
    assert float(jnp.std(out["params"]["Dense_0"]["kernel"])) == pytest.approx(0.3, rel=0.02)
    assert float(jnp.std(out["params"]["Dense_0"]["bias"])) == pytest.approx(0.3, rel=0.25)
    np.testing.assert_array_equal(out["params"]["LayerNorm_0"]["scale"], 1.0)
    np.testing.assert_array_equal(out["params"]["LayerNorm_0"]["bias"], 0.0)
    again = perturb(params, jax.random.PRNGKey(0), 0.3)
    np.testing.assert_array_equal(again["params"]["Dense_0"]["kernel"], out["params"]["Dense_0"]["kernel"])


def test_psne_perturbation_is_fixed_per_episode():
    strategy, _ = build("explore=psne", "psne.sigma_init=0.5", "init_std=0.01")
    noise, extras, _, _, _ = run_fixed_state(strategy, 32, 30, first_every=10)
    keys = np.asarray(extras)
    for t in range(1, 30):
        assert np.array_equal(keys[t], keys[t - 1]) == (t % 10 != 0)
    # With a tiny action std the noise is the perturbed network's offset: nearly constant.
    assert lag1(noise[:10]) > 0.9
    assert noise.std() > 0.05


@pytest.mark.slow
def test_psne_minibatch_log_prob_draws_each_episode_once_and_equals_per_segment():
    """`batch_log_prob` equals `log_prob` segment by segment, values and gradients, at two
    parameter points, both when the minibatch's episodes fit the chunked layout and when
    they do not (every step draws its own): too many chunks, or too many draws. A
    segment's first episode takes its eps from the carry, except where the segment
    starts with a new episode (segment 2, whose carry holds a wrong eps to show it)."""
    strategy, _ = build("explore=psne")
    T, m, p = 16, 4, 2
    # Chunks of L = 8 steps: 2 per segment, plus one per episode start off the grid (5; 9;
    # 3, 6, 9, 12, 15; segment 2's start at 0 is on it): C = 8 + 7 = 15 chunks, F = 8 draws.
    starts = [[], [5], [9], [3, 6, 9, 12, 15]]
    first = np.zeros((T, m), bool)
    keys = np.zeros((T, m, 2), np.uint32)
    for i, s in enumerate(starts):
        first[s, i] = True
        runs = np.cumsum(first[:, i]) + 10 * i
        keys[:, i] = np.asarray(jax.vmap(lambda r: jax.random.fold_in(jax.random.PRNGKey(7), r))(runs))
    first[0, 2] = True  # a segment that starts with its episode
    k_p, k_q, k_o, k_a = jax.random.split(jax.random.PRNGKey(0), 4)
    params0 = strategy.init(k_p, OBS_SIZE)
    leaves, tree = jax.tree.flatten(params0)
    noise = jax.random.split(k_q, len(leaves))
    params1 = tree.unflatten(
        [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, noise, strict=True)]
    )
    hp = strategy.init_hparams()
    held = jnp.asarray(keys[0]).at[2].set(jax.random.PRNGKey(99))  # segment 2: the old episode's
    carry0 = strategy.init_carry(k_p, params0, hp, m)._replace(
        key=jnp.asarray(keys[0]), sigma=jnp.arange(1.0, 5.0) / 10, eps=strategy._draw(params0, held)
    )
    obs = jax.random.normal(k_o, (T, m, OBS_SIZE))
    actions = jax.random.normal(k_a, (T, m, p))
    weights = jnp.linspace(-1.0, 1.0, T * m).reshape(T, m)
    first, keys = jnp.asarray(first), jnp.asarray(keys)

    def reference(params):
        segment = Segment(obs, actions, first, carry0, keys)
        return jax.vmap(strategy.log_prob, in_axes=(None, None, SEGMENT_AXES), out_axes=1)(
            params, hp, segment
        ).log_prob

    @functools.partial(jax.jit, static_argnums=1)
    def batched(params, capacities, carry0):
        """The values and the gradient of sum(weights * values), in one compile per capacity."""
        capacity, draw_capacity = capacities

        def weighted(q):
            segment = Segment(obs, actions, first, carry0, keys)
            values = strategy.batch_log_prob(
                q, hp, segment, capacity=capacity, draw_capacity=draw_capacity
            ).log_prob
            return jnp.sum(weights * values), values

        (_, values), grad = jax.value_and_grad(weighted, has_aux=True)(params)
        return values, grad

    # Capacities (chunks, draws): chunked; per-step (too many chunks); per-step (too many draws).
    capacities = ((15, 8), (14, 8), (15, 7))
    for params in (params0, params1):
        want = jax.jit(reference)(params)
        want_grad = jax.jit(jax.grad(lambda q: jnp.sum(weights * reference(q))))(params)
        for capacity in capacities:
            got, grad = batched(params, capacity, carry0)
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
            for g, w in zip(jax.tree.leaves(grad), jax.tree.leaves(want_grad), strict=True):
                np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6 * float(np.max(np.abs(w))))
    assert not np.allclose(jax.jit(reference)(params0), jax.jit(reference)(params1))
    # Which path ran: only the chunked one reads segment 0's eps from the carry.
    wrong = carry0._replace(eps=carry0.eps.at[0].multiply(-1.0))
    want = jax.jit(reference)(params0)
    for capacity, chunked in zip(capacities, (True, False, False), strict=True):
        got, _ = batched(params0, capacity, wrong)
        assert np.allclose(got[:, 1:], want[:, 1:], rtol=1e-6, atol=1e-6)
        assert np.allclose(got[:, 0], want[:, 0], rtol=1e-6, atol=1e-6) != chunked


@pytest.mark.parametrize("delta,factor", [(1e3, 1.5), (1e-6, 1 / 1.5)])
def test_psne_sigma_adapts_by_rule_451(delta, factor):
    """adapt applies (4.51): sigma * alpha if the distance (4.50) < delta, else sigma / alpha;
    scoring the segment leaves PSNE's log-probabilities as collection stored them."""
    strategy, _ = build(
        "explore=psne", "psne.sigma_init=0.2", f"psne.sigma_delta={delta}", "psne.sigma_alpha=1.5"
    )
    params = strategy.init(jax.random.PRNGKey(0), OBS_SIZE)
    hp = strategy.init_hparams()
    carry = strategy.init_carry(jax.random.PRNGKey(1), params, hp, 4)
    obs = jax.random.normal(jax.random.PRNGKey(2), (8, 4, OBS_SIZE))
    logp = jnp.zeros((8, 4))
    new = jax.jit(lambda c, o: strategy.adapt(params, hp, c, o))(carry, obs)
    np.testing.assert_allclose(new.sigma, 0.2 * factor, rtol=1e-6)
    np.testing.assert_array_equal(new.key, carry.key)
    actions = jnp.zeros((8, 4, 2))
    segment = Segment(obs, actions, jnp.zeros((8, 4), bool), carry)
    out_logp, same = strategy.score_segment(params, hp, segment, carry, logp)
    np.testing.assert_array_equal(out_logp, logp)
    np.testing.assert_array_equal(same.sigma, carry.sigma)


# ----------------------------------------------- stored log-prob equals the recompute

TINY = ["env=pointmass", "num_envs=4", "ppo.num_minibatches=2", "eval_episodes=2", "policy_hidden=[16,16]"]
NEW_STRATEGIES = [
    ["explore=coherent", "coherent.integration=mc", "coherent.beta=0.3"],
    ["explore=coherent", "coherent.integration=mc", "coherent.layers=all", "coherent.beta=0.3"],
    ["explore=noisynet"],
    ["explore=psne"],
    ["explore=gsde", "gsde.resample_every=3"],
    ["explore=pink", "episode_length=7"],
    ["explore=lattice", "lattice.resample_every=3", "lattice.std_reg=0.05"],
    ["explore=lattice", "lattice.action_noise=false", "lattice.weight_grad=false"],
]


@pytest.mark.parametrize(
    "overrides", NEW_STRATEGIES, ids=lambda o: " ".join(o).replace("coherent.", "").replace("explore=", "")
)
def test_behaviour_log_prob_equals_segment_recompute(overrides):
    """What collection stored equals the loss's recomputation at the same parameters
    (PPO's first ratio is 1), over two segments with episode resets, and the same key
    gives the same segment."""
    env = VecEnv("pointmass", num_envs=4, episode_length=7)
    cfg = parse_overrides(TINY + overrides)
    trainer = OnPolicyTrainer(cfg, env=env, eval_env=env)
    state = trainer.init(jax.random.PRNGKey(0))
    strategy, params, hp = trainer.strategy, state.params.policy, state.hparams.explore

    def act(k, carry, obs, first):
        return strategy.act(k, params, hp, carry, obs, first)

    @jax.jit
    def collect_and_score(env_state, carry, key):
        env_state, carry_end, data = unroll(env, act, env_state, carry, key, 10)
        segment = Segment(data.obs, data.action, data.first, carry, data.extras)
        log_prob, carry_end = strategy.score_segment(params, hp, segment, carry_end, data.log_prob)
        carry_end = strategy.adapt(params, hp, carry_end, data.obs)
        recomputed = jax.vmap(strategy.log_prob, in_axes=(None, None, SEGMENT_AXES), out_axes=1)(
            params, hp, segment
        )
        # The loss's minibatch form, also with room for every episode (psne: chunked).
        batched = [strategy.batch_log_prob(params, hp, segment)]
        if strategy.name == "psne":
            room = {"capacity": 40, "draw_capacity": 40}
            batched.append(strategy.batch_log_prob(params, hp, segment, **room))
        return env_state, carry_end, data._replace(log_prob=log_prob), recomputed, batched

    env_state, carry = state.env_state, state.carry
    for key in jax.random.split(jax.random.PRNGKey(1), 2):
        env_state, carry, data, recomputed, batched = collect_and_score(env_state, carry, key)
        assert np.asarray(data.first)[1:].any()
        assert np.isfinite(np.asarray(data.log_prob)).all()
        np.testing.assert_allclose(recomputed.log_prob, data.log_prob, rtol=2e-5, atol=2e-4)
        for seg in batched:
            np.testing.assert_allclose(seg.log_prob, data.log_prob, rtol=2e-5, atol=2e-4)
        assert np.isfinite(np.asarray(recomputed.entropy)).all()
    _, _, again, _, _ = collect_and_score(state.env_state, state.carry, jax.random.PRNGKey(5))
    _, _, same, _, _ = collect_and_score(state.env_state, state.carry, jax.random.PRNGKey(5))
    np.testing.assert_array_equal(again.action, same.action)


# ------------------------------------------------------------- off-policy (SAC) hooks


def offpolicy_run(behaviour, steps, first_every, num_envs=8, seed=0):
    """SAC's behaviour actions at one fixed state; returns actions [T, n, p], carries, actor."""
    actor = SquashedGaussianActor(2, (16, 16), "relu", layer_norm=behaviour.actor_layer_norm)
    key = jax.random.PRNGKey(seed)
    k_p, k_c, k_o, k_run = jax.random.split(key, 4)
    actor_params = actor.init(k_p, OBS_SIZE)
    hp = behaviour.init_hparams()
    carry = behaviour.init_carry(k_c, actor, actor_params, hp, num_envs)
    obs = jnp.broadcast_to(jax.random.normal(k_o, (OBS_SIZE,)), (num_envs, OBS_SIZE))
    firsts = jnp.arange(steps) % first_every == 0

    @jax.jit
    def go(carry):
        def step(c, inp):
            k, f = inp
            action, c = behaviour.act(k, actor, actor_params, hp, c, obs, jnp.full((num_envs,), f))
            return c, (action, c)

        return jax.lax.scan(step, carry, (jax.random.split(k_run, steps), firsts))[1]

    actions, carries = go(carry)
    return np.asarray(actions), carries, actor, actor_params, hp, obs


def test_sac_pink_uses_the_coloured_sequence():
    """a = tanh(mean + std xi) with xi the episode's sequence at the step index."""
    behaviour = build_behaviour("explore=pink", "episode_length=20", "pink.exponent=1")
    actions, carries, actor, actor_params, _, obs = offpolicy_run(behaviour, 30, first_every=20)
    dist = actor.dist(actor_params, obs)
    noise, step = np.asarray(carries.noise), np.asarray(carries.step)
    for t in (0, 7, 19, 20, 29):
        xi = noise[t][np.arange(8), step[t] - 1]
        expected = np.tanh(np.asarray(dist.mean) + np.exp(np.asarray(dist.log_std)) * xi)
        np.testing.assert_allclose(actions[t], expected, rtol=1e-5, atol=1e-6)
    assert not np.allclose(noise[19], noise[20])  # a new sequence for the new episode


def test_sac_gsde_noise_held_for_n_steps():
    behaviour = build_behaviour("explore=gsde", "gsde.resample_every=4")
    actions, *_ = offpolicy_run(behaviour, 12, first_every=100)
    change = np.abs(np.diff(actions, axis=0)).max(axis=(1, 2)) > 1e-7
    assert [t for t in range(1, 12) if change[t - 1]] == [4, 8]


def test_sac_psne_fixed_per_episode_and_sigma_rule():
    behaviour = build_behaviour(
        "explore=psne", "psne.sigma_init=0.3", "psne.sigma_alpha=1.5", "psne.sigma_delta=1000"
    )
    assert behaviour.actor_layer_norm
    _, keys, actor, actor_params, hp, obs = offpolicy_run(behaviour, 12, first_every=5)
    keys = np.asarray(keys)
    assert [t for t in range(1, 12) if not np.array_equal(keys[t], keys[t - 1])] == [5, 10]
    new_hp, metrics = behaviour.adapt(jax.random.PRNGKey(3), actor, actor_params, hp, obs)
    assert float(new_hp.sigma) == pytest.approx(0.45) and float(metrics["policy_distance"]) > 0
    hp_small = hp.replace(sigma_delta=jnp.asarray(1e-9))
    new_hp, _ = behaviour.adapt(jax.random.PRNGKey(3), actor, actor_params, hp_small, obs)
    assert float(new_hp.sigma) == pytest.approx(0.2)


def test_registry_matches_the_jax_free_names_and_every_refusal_has_a_reason():
    """The registry of classes and the JAX-free names agree row by row: a class of the right
    base for every algorithm a strategy runs with, none for one it is refused with a
    reason; the config's choices are the names."""
    from coherent_jax import config, strategies
    from coherent_jax.agents import registry

    registry.check_registry()
    assert config.EXPLORES == tuple(r.name for r in registry.REGISTRY) == strategies.EXPLORES
    assert registry.off_policy_classes()["coherent"].__name__ == "CoherentBehaviour"
    assert set(registry.on_policy_classes()) == {*strategies.EXPLORES, "coherent-mc", "coherent-all"}
    # A row that disagrees is named.
    extra = registry.Registered("extra", registry.REGISTRY[0].on_policy, None)
    with pytest.raises(AssertionError, match="registry names"):
        registry.check_registry((*registry.REGISTRY, extra))
    with pytest.raises(AssertionError, match="'noisynet'"):
        registry.check_registry(
            tuple(
                r if r.name != "noisynet" else registry.Registered("noisynet", r.on_policy, r.on_policy)
                for r in registry.REGISTRY
            )
        )
    assert strategies.SUPPORTED_ALGOS["noisynet"] == ("ppo", "a2c")
    assert "score-function" in strategies.REFUSED[("noisynet", "sac")]
    with pytest.raises(config.ConfigError, match="score-function"):
        parse_overrides(["env=pointmass", "algo=sac", "explore=noisynet"])


def test_the_names_the_config_validates_load_without_jax():
    """The JAX-free names, and the config's refusal of a pair they refuse, load no JAX."""
    code = (
        "import sys\n"
        "from coherent_jax.strategies import EXPLORES, SUPPORTED_ALGOS\n"
        "from coherent_jax.config import ConfigError, parse_overrides\n"
        "assert 'noisynet' in EXPLORES and SUPPORTED_ALGOS['noisynet'] == ('ppo', 'a2c')\n"
        "try:\n"
        "    parse_overrides(['env=pointmass', 'algo=sac', 'explore=noisynet'])\n"
        "except ConfigError:\n"
        "    pass\n"
        "else:\n"
        "    raise SystemExit('not refused')\n"
        "assert 'jax' not in sys.modules, sorted(m for m in sys.modules if 'jax' in m)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# Each strategy's hyperparameters as they were stored before each had its own dataclass: a
# string-keyed dict, whose leaves flatten in sorted key order. A checkpoint stores the train
# state's leaves in order, so the dataclasses must give these paths in this order for the
# checkpoints written then to resume (bit for bit).
HPARAMS_BEFORE = {
    ("ppo", "coherent"): ["action_std", "beta"],
    ("ppo", "coherent", "coherent.learn_action_std=true"): ["beta"],
    ("ppo", "coherent", "coherent.integration=mc"): ["action_std", "beta"],
    ("ppo", "coherent", "coherent.integration=mc", "coherent.layers=all"): ["action_std", "beta"],
    ("ppo", "psne"): ["sigma_alpha", "sigma_delta"],
    ("sac", "coherent"): ["beta", "sigma", "sigma_alpha", "sigma_delta"],
    ("sac", "psne"): ["sigma", "sigma_alpha", "sigma_delta"],
    **{("ppo", e): [] for e in ("action", "noisynet", "gsde", "pink", "lattice")},
    **{("sac", e): [] for e in ("action", "gsde", "pink", "lattice")},
}


@pytest.mark.parametrize("case", sorted(HPARAMS_BEFORE), ids="-".join)
def test_hyperparameters_are_a_typed_pytree_with_the_leaves_of_before(case):
    import dataclasses

    algo, explore, *rest = case
    args = [f"explore={explore}", *rest]
    made = build_behaviour(*args) if algo == "sac" else build(f"algo={algo}", *args)[0]
    hp = made.init_hparams()
    assert dataclasses.is_dataclass(hp) and hasattr(hp, "replace"), type(hp)  # a flax.struct.dataclass
    paths = jax.tree_util.tree_flatten_with_path(hp)[0]
    assert all(isinstance(k, jax.tree_util.GetAttrKey) for path, _ in paths for k in path)
    assert [jax.tree_util.keystr(p, simple=True, separator=".") for p, _ in paths] == HPARAMS_BEFORE[case]
    # The same leaves, in the same order, as the dict of before (``jax.tree`` sorts a dict's keys).
    before = {name: getattr(hp, name) for name in reversed(HPARAMS_BEFORE[case])}
    assert [id(x) for x in jax.tree.leaves(before)] == [id(x) for x in jax.tree.leaves(hp)]
