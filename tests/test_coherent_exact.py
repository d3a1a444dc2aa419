"""The thesis's estimator for segments of long episodes (coherent_jax.exploration.coherent.exact).

The reference is written here, in float64, from the joint Gaussian of a whole episode's
actions (the thesis's model, eqs. 4.1-4.5 and 4.29): one dense covariance per action
dimension over every step since the episode start, its Cholesky factor in time order
giving log p(a_t | a_<t, s_<=t) for every t. It shares no code with the module: no
beliefs, no blocks, no filter. Gradients are those of the same loss terms through a
small tanh trunk, with respect to the trunk, mu, log w_std and action_std.
"""

import json

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from references import (
    assert_trees_close,
    cosine,
    heads,
    perturb,
    problem,
    reference_log_marginals,
    trunk,
    x64_enabled,
)

from coherent_jax.exploration.base import SEGMENT_AXES, Segment
from coherent_jax.exploration.chain import ChainParams
from coherent_jax.exploration.coherent import exact as E
from coherent_jax.exploration.coherent import filter as C
from coherent_jax.exploration.coherent import joint as J

# ---------------------------------------------------------------- tests


def _weighted(logp_fn):
    """(params, obs, a, first, weights, beta) -> (sum_t weights_t logp_t, logp), jitted with its gradient."""

    def loss(params, obs, a, first, weights, beta):
        mu, w_std, action_std = heads(params)
        logp = logp_fn(trunk(params["theta"], obs), a, first, mu, w_std, action_std, beta)
        return jnp.sum(weights * logp[-weights.shape[0] :]), logp[-weights.shape[0] :]

    return jax.jit(jax.value_and_grad(loss, has_aux=True))


def _chained_8(x, a, first, mu, w_std, action_std, beta):
    return E.chained_marginals(
        C.prior_belief(mu, w_std), x, a, first, ChainParams(mu, w_std, action_std, beta), 8
    )[0]


def _chained_8_from_prior(x, a, first, mu, w_std, action_std, beta):
    # A belief of junk: with from_prior it must not be read.
    junk = C.Belief(jnp.full_like(mu, jnp.nan), jnp.full(mu.shape + mu.shape[-1:], jnp.nan, mu.dtype))
    return E.chained_marginals(
        junk, x, a, first, ChainParams(mu, w_std, action_std, beta), 8, from_prior=True
    )[0]


def refiltered_marginals(
    history_x: chex.Array,
    history_a: chex.Array,
    history_first: chex.Array,
    x: chex.Array,
    a: chex.Array,
    first: chex.Array,
    mu: chex.Array,
    w_std: chex.Array,
    action_std: chex.Array,
    beta: chex.Array,
    block: int | None = None,
) -> tuple[chex.Array, chex.Array]:
    """log p(a_t | a_<t, s_<=t) of a segment, the episode prefix re-inferred from its start.

    The prefix (H steps before the segment) and the segment are one chain of
    `E.chained_marginals` (`coherent_jax.exploration.coherent.exact`) that starts from the prior at
    the first prefix step (4.33), so
    the segment's terms are exactly the thesis's marginals (4.37)/(4.49) of an episode
    filtered from its beginning under the given parameters, and differentiate through
    the prefix's inputs. The prefix must start at an episode start, or at a step before
    one: ``history_first`` (and ``first``) reset the chain wherever an episode starts,
    so steps of earlier episodes in the window only cost time.

    Args:
      history_x, history_a, history_first: [H, q], [H, p], [H] the steps before the
        segment; H may be 0.
      x, a, first: [T, q], [T, p], [T] the segment.
      mu, w_std, action_std, beta: as `E.chained_marginals`.
      block: steps per block, a divisor of H + T; by default blocks of `E.MAX_BLOCK` steps,
        the front padded with one-step episodes to a whole number of blocks.

    Returns:
      (logp [T], predictive variances s [T, p]) of the segment's steps.
    """
    chex.assert_rank([history_x, history_a, history_first, x, a, first], [2, 2, 1, 2, 2, 1])
    num_steps = x.shape[0]
    # The chain starts at the window's first step whatever its flag says (4.33).
    history_first = jnp.asarray(history_first, bool)
    first = jnp.asarray(first, bool)
    if history_x.shape[0]:
        history_first = history_first.at[0].set(True)
    else:
        first = first.at[0].set(True)
    # Without a given block size, pad the front to whole blocks of MAX_BLOCK steps: each
    # padding step is an episode of its own (first = True), so it changes nothing after it.
    pad = 0 if block is not None else -(history_x.shape[0] + num_steps) % E.MAX_BLOCK
    all_x = jnp.concatenate([jnp.zeros((pad, x.shape[1]), x.dtype), jnp.asarray(history_x, x.dtype), x])
    all_a = jnp.concatenate([jnp.zeros((pad, a.shape[1]), a.dtype), jnp.asarray(history_a, a.dtype), a])
    all_first = jnp.concatenate([jnp.ones((pad,), bool), history_first, first])
    logp, _, pred_var = E.chained_marginals(
        C.prior_belief(mu, w_std), all_x, all_a, all_first, ChainParams(mu, w_std, action_std, beta), block
    )
    return logp[-num_steps:], pred_var[-num_steps:]


def _refiltered_20_4(x, a, first, mu, w_std, action_std, beta):
    h = 20
    return refiltered_marginals(
        x[:h], a[:h], first[:h], x[h:], a[h:], first[h:], mu, w_std, action_std, beta, block=4
    )[0]


chained_loss = _weighted(_chained_8)
chained_from_prior_loss = _weighted(_chained_8_from_prior)
refiltered_loss = _weighted(_refiltered_20_4)
reference_loss = _weighted(reference_log_marginals)


@pytest.mark.parametrize("beta", [0.0, 0.05, 1.0])
@pytest.mark.parametrize("resets", [(), (11,), (8, 17)])
def test_chained_blocks_equal_dense_episode_reference(x64, beta, resets):
    """Values and gradients over 24 steps in 3 blocks of 8, resets on and off block edges."""
    params, obs, a, first = problem(1, 24, resets=resets, beta=beta)
    weights = jnp.asarray(np.random.default_rng(2).normal(size=24))
    for point in (params, perturb(params, 3)):
        (_, ref), grad_ref = reference_loss(point, obs, a, first, weights, beta)
        for loss in (chained_loss, chained_from_prior_loss):
            (_, logp), grad = loss(point, obs, a, first, weights, beta)
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


@pytest.mark.parametrize("beta", [0.01, 0.3])
def test_skipped_blocks_before_the_episode_start_change_nothing_kept(x64, beta):
    """32 steps in 4 blocks of 8, an episode from step 19 (block 2): with ``start_block=2``
    that episode's log-probabilities and the gradient of their weighted sum equal the
    dense reference's, before and after an update, and the skipped block scores 0 with
    variance 1. Starting at block 3, past the episode start, changes them."""
    params, obs, a, first = problem(7, 32, resets=(19,), beta=beta)
    weights = jnp.asarray(np.random.default_rng(8).normal(size=13))  # steps 19-31

    def from_block(start):
        def logp_fn(x, a, first, mu, w_std, action_std, beta):
            prior = C.prior_belief(mu, w_std)
            return E.chained_marginals(
                prior,
                x,
                a,
                first,
                ChainParams(mu, w_std, action_std, beta),
                8,
                from_prior=True,
                start_block=start,
            )[0]

        return _weighted(logp_fn)

    for point in (params, perturb(params, 9)):
        (_, ref), grad_ref = reference_loss(point, obs, a, first, weights, beta)
        (_, logp), grad = from_block(jnp.asarray(2))(point, obs, a, first, weights, beta)
        np.testing.assert_allclose(logp, ref, rtol=1e-10, atol=1e-10)
        assert_trees_close(grad, grad_ref, rtol=1e-8, atol=1e-10)
        (_, late), _ = from_block(jnp.asarray(3))(point, obs, a, first, weights, beta)
        assert np.max(np.abs(np.asarray(late) - np.asarray(ref))) > 1e-3
    mu, w_std, action_std = heads(params)
    x = trunk(params["theta"], obs)
    logp, _, pred_var = E.chained_marginals(
        C.prior_belief(mu, w_std),
        x,
        a,
        first,
        ChainParams(mu, w_std, action_std, beta),
        8,
        start_block=jnp.asarray(2),
    )
    assert np.all(np.asarray(logp[8:16]) == 0.0) and np.all(np.asarray(pred_var[8:16]) == 1.0)
    assert np.all(np.asarray(logp[16:]) != 0.0)


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
        C.prior_belief(mu0, w_std0), x0[:h], a[:h], first[:h], ChainParams(mu0, w_std0, action_std0, beta)
    )
    z_mean, z_cov = (stored.mean - mu0) / w_std0, stored.cov / (w_std0[:, :, None] * w_std0[:, None, :])

    @jax.jit
    @jax.value_and_grad
    def held(params):
        mu, w_std, action_std = heads(params)
        belief = C.Belief(mu + w_std * z_mean, w_std[:, :, None] * z_cov * w_std[:, None, :])
        x = trunk(params["theta"], obs)
        logp, _, _ = J.segment_marginals_joint(
            belief, x[h:], a[h:], first[h:], ChainParams(mu, w_std, action_std, beta)
        )
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
            ChainParams(jnp.zeros((1, 3)), jnp.ones((1, 3)), jnp.ones(1), 0.1),
            block=4,
        )


# ------------------------------------------- the trainer's exact mode (coherent.gradient)


def _collect(trainer, env, params, env_state, carry, key, length):
    """One segment as the trainer collects it: unroll, then the strategy's score_segment."""
    from coherent_jax.agents.rollout import unroll

    strategy, hp = trainer.strategy, trainer.init_hparams().explore

    def act(k, c, obs, first):
        return strategy.act(k, params, hp, c, obs, first)

    env_state, carry_end, data = unroll(env, act, env_state, carry, key, length)
    segment = Segment(data.obs, data.action, data.first, carry, data.extras)
    log_prob, carry_end = strategy.score_segment(params, hp, segment, carry_end, data.log_prob)
    return env_state, carry_end, data._replace(log_prob=log_prob)


def _check_segment_against_reference(strategy, hp, params, carry_start, data, seed):
    """Behaviour and loss log-probs of one exact-mode segment, and the loss's gradient in float64."""
    first = np.asarray(data.first).copy()
    first[0] = True  # the chain's restart at the segment start
    with x64_enabled():
        p64 = jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), params)
        obs = jnp.asarray(data.obs, jnp.float64)
        actions = jnp.asarray(data.action, jnp.float64)
        adv = jnp.asarray(np.random.default_rng(seed).normal(size=first.shape))

        def loss(prm):
            segment = Segment(obs, actions, jnp.asarray(data.first), carry_start)
            per_segment = jax.vmap(strategy.log_prob, in_axes=(None, None, SEGMENT_AXES), out_axes=1)
            seg_lp = per_segment(prm, hp, segment)
            return jnp.sum(adv * seg_lp.log_prob), seg_lp.log_prob

        def reference(prm):
            mu, w_std = prm["mu"], jnp.exp(prm["log_w_std"])
            std = jnp.asarray(hp.action_std, jnp.float64)
            logps = []
            for e in range(first.shape[1]):
                x = strategy.layer.features(prm, obs[:, e])
                logps.append(reference_log_marginals(x, actions[:, e], first[:, e], mu, w_std, std, 0.0))
            logp = jnp.stack(logps, axis=1)
            return jnp.sum(adv * logp), logp

        (_, logp), grad = jax.jit(jax.value_and_grad(loss, has_aux=True))(p64)
        (_, ref), grad_ref = jax.jit(jax.value_and_grad(reference, has_aux=True))(p64)
        np.testing.assert_allclose(logp, ref, rtol=1e-9, atol=1e-9)
        assert_trees_close(grad, grad_ref, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(data.log_prob, ref, rtol=1e-4, atol=1e-3)


@pytest.mark.slow
def test_exact_mode_behaviour_and_loss_follow_the_process_across_an_update():
    """coherent.gradient=exact (the default): the chain restarts at each segment start.

    Two segments of 72 steps (chained blocks of 36) in episodes of 30 steps, the
    policy updated in between. Checked: the chain really restarts (at beta = 0 the
    sampled z of an env whose episode goes on changes at the segment start); in each
    segment the behaviour log-probabilities equal the dense reference of the process
    run (chain episodes start at the segment start and at every episode start); and,
    in float64, the loss's log-probabilities and their gradients with respect to the
    whole policy equal the reference's.
    """
    from coherent_jax.agents.onpolicy import OnPolicyTrainer
    from coherent_jax.config import parse_overrides
    from coherent_jax.envs import VecEnv

    env = VecEnv("pointmass", num_envs=2, episode_length=30)
    cfg = parse_overrides(
        ["env=pointmass", "num_envs=2", "ppo.num_minibatches=1", "unroll_length=72", "explore=coherent"]
        + ["coherent.beta=0", "coherent.w_std_init=0.5", "policy_hidden=[8]"]
    )
    assert cfg.coherent.gradient == "exact"
    trainer = OnPolicyTrainer(cfg, env=env, eval_env=env)
    state = trainer.init(jax.random.PRNGKey(0))
    strategy, hp = trainer.strategy, trainer.init_hparams().explore
    collect = jax.jit(lambda prm, es, c, k, n: _collect(trainer, env, prm, es, c, k, n), static_argnums=4)
    keys = jax.random.split(jax.random.PRNGKey(1), 3)

    params0 = state.params.policy
    env_state, carry1, data0 = collect(params0, state.env_state, state.carry, keys[0], 72)
    _check_segment_against_reference(strategy, hp, params0, state.carry, data0, 0)

    params1 = perturb(params0, 9, scale=0.1)
    _, carry2, data1 = collect(params1, env_state, carry1, keys[1], 72)
    assert not np.asarray(data1.first)[0].all(), "the second segment should start mid-episode"
    _check_segment_against_reference(strategy, hp, params1, carry1, data1, 1)

    _, carry_step, _ = collect(params1, env_state, carry1, keys[1], 1)
    going_on = ~np.asarray(env_state.first)
    assert going_on.any()
    assert not np.allclose(np.asarray(carry_step.z)[going_on], np.asarray(carry1.z)[going_on])


def test_float32_loss_stays_finite_and_accurate_at_extreme_weight_to_noise_ratios():
    """w_std / action_std = 1e4, segments of 128 steps (two blocks, each longer than q + 1).

    The strategy bounds the ratio at `MAX_W_STD_RATIO` by raising the action noise
    (in collection and loss alike); its float32 log-probabilities then stay finite and
    within 0.01 nats of the same computation in float64, at beta = 0, 0.01 and 1.
    """
    from coherent_jax.exploration.coherent.layer import MAX_W_STD_RATIO
    from coherent_jax.exploration.coherent.strategy import CoherentExploration

    strategy = CoherentExploration(2, (16,), "tanh", 0.0, w_std_init=100.0, action_std=0.01)
    params = strategy.init(jax.random.PRNGKey(0), 5)
    hp = strategy.init_hparams()
    _, _, action_std = strategy._head(params, hp)
    np.testing.assert_allclose(action_std, 100.0 / MAX_W_STD_RATIO, rtol=1e-6)
    carry = jax.tree.map(lambda v: v[0], strategy.init_carry(jax.random.PRNGKey(1), params, hp, 1))
    rng = np.random.default_rng(0)
    obs = np.cumsum(rng.normal(size=(128, 5)), axis=0) * 0.2
    x = np.asarray(strategy.layer.features(params, jnp.asarray(obs, jnp.float32)), np.float64)
    xh = np.concatenate([x, np.ones((128, 1))], axis=1)
    w = np.asarray(params["mu"]) + 100.0 * rng.normal(size=(2, 17))
    actions = xh @ w.T + 10.0 * rng.normal(size=(128, 2))
    first = jnp.zeros(128, bool).at[0].set(True)
    log_prob = jax.jit(lambda prm, h, o, a: strategy.log_prob(prm, h, Segment(o, a, first, carry)).log_prob)
    for beta in (0.0, 0.01, 1.0):
        hp32 = hp.replace(beta=jnp.asarray(beta, jnp.float32))
        logp32 = log_prob(params, hp32, jnp.asarray(obs, jnp.float32), jnp.asarray(actions, jnp.float32))
        with x64_enabled():
            as64 = lambda v: jnp.asarray(v, jnp.float64)  # noqa: E731
            logp64 = np.asarray(
                log_prob(jax.tree.map(as64, params), jax.tree.map(as64, hp32), as64(obs), as64(actions))
            )
        assert logp32.dtype == jnp.float32 and np.isfinite(np.asarray(logp32)).all()
        np.testing.assert_allclose(logp32, logp64, atol=1e-2)


@pytest.mark.slow
def test_gradient_bench_passes_for_exact_forms_and_exposes_stored(tmp_path, capsys):
    """`python -m benchmarks gradient` on small shapes: the exact and re-filtered forms
    meet the bound (exit 0), the stored form is visibly off once the segment has a history,
    and a bad setting is one line, exit 2, nothing written."""
    from benchmarks.__main__ import main

    out = tmp_path / "gradient.json"
    small = ["q=8", "p=1", "obs_size=3", "segment=8", "w_std=0.3", "action_std=0.1", f"out={out}"]
    assert main(["gradient", "betas=[0,0.1]", "histories=[0,16]", *small]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert {r["mode"]: r["must_equal"] for r in rows} == {
        "exact": "segment",
        "episode": "episode",
        "stored": None,
    }
    assert all(r["ok"] for r in rows) and len(rows) == 12
    for r in rows:  # each mode's own reference, to float64 rounding, at moved parameters
        if r["must_equal"]:
            assert r[f"rel_err_{r['must_equal']}"] < 1e-8 and r[f"value_err_{r['must_equal']}"] < 1e-9, r
    cos = {(r["mode"], r["beta"], r["history"]): r for r in rows}
    # With a history the processes differ: exact is far from the whole episode's gradient,
    # episode from the restarted chain's, and stored from both.
    assert cos[("exact", 0.1, 16)]["cos_episode"] < 0.99
    assert cos[("episode", 0.1, 16)]["cos_segment"] < 0.99
    assert cos[("stored", 0.0, 16)]["cos_episode"] < 0.99 and cos[("stored", 0.0, 0)]["cos_episode"] > 0.9999
    out.unlink()
    capsys.readouterr()
    assert main(["gradient", "betas=[2]", f"out={out}"]) == 2
    err = capsys.readouterr().err
    assert "'betas'" in err and len(err.strip().splitlines()) == 1 and not out.exists()
