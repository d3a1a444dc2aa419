"""The chain's processes: ``coherent.gradient=episode`` and ``coherent.episode_restart``.

References (tests/references.py) are float64 dense joint Gaussians of every action since
the chain's last start, sharing no code with the library's filter or blocks:

* ``episode``: one chain through the whole episode, restarted only at its start. The
  segment's log-probabilities and their gradient must equal that reference's terms for
  the same steps, at parameters moved away from the collection parameters, for segments
  that start mid-episode, and with the window reaching back past an earlier episode.
* ``exact`` with ``episode_restart=false``: the thesis's buffer (Algorithm 5): the chain
  drawn at the segment's first step and running on across environment resets.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from references import reference_log_marginals, sample_actions

from coherent_jax.agents import losses
from coherent_jax.agents.rollout import EpisodeHistory, Transition
from coherent_jax.exploration.base import Segment
from coherent_jax.exploration.coherent.layer import CoherentHParams
from coherent_jax.exploration.coherent.strategy import (
    CoherentExploration,
    episode_history_length,
    window_start_block,
)
from coherent_jax.sweep_axis import vmap_points

P, Q, OBS = 2, 3, 4


def make(gradient, beta, episode_length=48, unroll=16, episode_restart=True):
    return CoherentExploration(
        P,
        [Q],
        "tanh",
        beta=beta,
        w_std_init=0.3,
        action_std=0.2,
        learn_action_std=True,
        gradient=gradient,
        episode_restart=episode_restart,
        episode_length=episode_length,
        unroll_length=unroll,
    )


def params64(strategy, seed):
    """The strategy's own parameter tree in float64, spread away from its initial values."""
    params = strategy.init(jax.random.PRNGKey(seed), OBS)
    rng = np.random.default_rng(seed)
    params = jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), params)
    return {
        **params,
        "mu": jnp.asarray(rng.normal(size=(P, Q + 1)) * 0.5),
        "log_w_std": jnp.asarray(np.log(rng.uniform(0.2, 0.6, (P, Q + 1)))),
        "log_action_std": jnp.asarray(np.log(rng.uniform(0.1, 0.3, P))),
    }


def heads(params):
    return params["mu"], jnp.exp(params["log_w_std"]), jnp.exp(params["log_action_std"])


def trajectory(strategy, params, beta, seed, lengths):
    """Episodes of the given lengths back to back, drawn from the chain (4.1-4.5, 4.29)."""
    rng = np.random.default_rng(seed)
    num_steps = sum(lengths)
    obs = np.cumsum(rng.normal(size=(num_steps, OBS)), axis=0) * 0.3
    first = np.zeros(num_steps, bool)
    first[np.cumsum([0, *lengths[:-1]])] = True
    x = np.asarray(strategy.layer.features(params, jnp.asarray(obs)))
    mu, w_std, action_std = (np.asarray(v) for v in heads(params))
    a = sample_actions(rng, x, mu, w_std, action_std, beta, first)
    return jnp.asarray(obs), jnp.asarray(a), jnp.asarray(first)


def window(obs, a, first, end, length):
    """The trainer's window of ``length`` steps ending at ``end``, padded in front as the
    trainer's empty history is (first=True, zeros)."""
    pad = max(length - end, 0)
    cut = lambda v, fill: jnp.concatenate(
        [jnp.full((pad,) + v.shape[1:], fill, v.dtype), v[max(end - length, 0) : end]]
    )  # noqa: E731
    return cut(obs, 0.0), cut(a, 0.0), cut(first, True)


def reference_segment(strategy, params, obs, a, first, start, end, beta):
    """The whole-episode reference's terms for steps [start, end): the episode's chain from
    its own first step (the last reset at or before ``start``)."""
    episode_start = int(np.flatnonzero(np.asarray(first[: start + 1]))[-1])
    x = strategy.layer.features(params, obs[episode_start:end])
    mu, w_std, action_std = heads(params)
    f = first[episode_start:end]
    return reference_log_marginals(x, a[episode_start:end], f, mu, w_std, action_std, beta)[
        start - episode_start :
    ]


@pytest.mark.parametrize("beta", [0.01, 0.1])
@pytest.mark.slow
def test_episode_gradient_equals_the_whole_episode_reference_after_an_update(x64, beta):
    """Segments 2 and 3 of a 48-step episode (the window reaching back into an earlier
    episode and into padding): log-probabilities and the gradient of sum_t A_t log p equal
    the one-chain-per-episode reference at parameters one gradient step away."""
    strat = make("episode", beta)
    hp = CoherentHParams(action_std=None, beta=jnp.asarray(beta))
    assert strat.history_length == 48
    params0 = params64(strat, 0)
    obs, a, first = trajectory(strat, params0, beta, 1, [20, 48])
    adv = jnp.asarray(np.random.default_rng(2).normal(size=16))
    for segment in (1, 2):
        start = 20 + 16 * segment
        w_obs, w_a, w_first = window(obs, a, first, start + 16, strat.history_length + 16)

        def loss(prm, w_obs=w_obs, w_a=w_a, w_first=w_first):
            return jnp.sum(adv * strat.log_prob(prm, hp, Segment(w_obs, w_a, w_first)).log_prob[-16:])

        def ref_loss(prm, start=start):
            return jnp.sum(adv * reference_segment(strat, prm, obs, a, first, start, start + 16, beta))

        grad0 = jax.grad(loss)(params0)
        params1 = jax.tree.map(lambda p, g: p - 0.05 * g, params0, grad0)  # the update
        for prm in (params0, params1):
            got = strat.log_prob(prm, hp, Segment(w_obs, w_a, w_first)).log_prob[-16:]
            want = reference_segment(strat, prm, obs, a, first, start, start + 16, beta)
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)
            for g, r in zip(
                jax.tree.leaves(jax.grad(loss)(prm)), jax.tree.leaves(jax.grad(ref_loss)(prm)), strict=True
            ):
                np.testing.assert_allclose(g, r, rtol=1e-8, atol=1e-10)
        # It could fail: the chain restarted at the segment start scores other values.
        cut = reference_log_marginals(
            strat.layer.features(params1, obs[start : start + 16]),
            a[start : start + 16],
            jnp.zeros(16, bool),
            *heads(params1),
            beta,
        )
        assert np.max(np.abs(np.asarray(cut) - np.asarray(want))) > 1e-3


@pytest.mark.slow
def test_the_trainers_loss_reads_each_segment_with_its_own_history(x64):
    """`losses.segment_log_prob` on a minibatch of two envs in different episode phases,
    the context being what `EpisodeHistory.extend` kept: each env's terms equal its
    whole-episode reference."""
    beta = 0.05
    strat = make("episode", beta, episode_length=24, unroll=8)
    hp = CoherentHParams(action_std=None, beta=jnp.asarray(beta))
    h = strat.history_length
    assert h == 24
    params = params64(strat, 3)
    envs = [
        trajectory(strat, params, beta, seed, lengths) for seed, lengths in ((4, [24, 24]), (5, [7, 13, 28]))
    ]
    history = EpisodeHistory.empty(h, 2, OBS, P)
    history = history._replace(obs=history.obs.astype(jnp.float64), action=history.action.astype(jnp.float64))
    for k in range(6):  # six segments of 8 steps: the history fills, then slides
        seg = [(o[8 * k : 8 * k + 8], a_[8 * k : 8 * k + 8], f[8 * k : 8 * k + 8]) for o, a_, f in envs]
        stack = lambda i, seg=seg: jnp.stack([s[i] for s in seg], axis=1)  # noqa: E731  [T, 2, ...]
        batch = losses.SegmentBatch(
            segment=Segment(obs=stack(0), action=stack(1), first=stack(2), carry0=None),
            behaviour_log_prob=None,
            advantages=None,
            targets=None,
            context=history,
        )
        got = losses.segment_log_prob(strat, params, hp, batch).log_prob  # [8, 2]
        for e, (o, a_, f) in enumerate(envs):
            want = reference_segment(strat, params, o, a_, f, 8 * k, 8 * k + 8, beta)
            np.testing.assert_allclose(got[:, e], want, rtol=1e-10, atol=1e-10)
        data = Transition(stack(0), stack(2), stack(1), *([None] * 6))
        history = history.extend(data)


def test_window_start_block_is_the_earliest_episode_start_a_segment_needs():
    """Windows of 24 prefix steps and an 8-step segment, blocks of 8: each window needs the
    block of its latest episode start at or before the segment's first step (index 24);
    a minibatch the earliest of its windows'."""
    first = np.zeros((32, 4), bool)
    first[17, 0] = True  # block 2
    first[[10, 28], 1] = True  # block 1; the reset inside the segment does not count
    first[[5, 24], 2] = True  # the segment's first step starts an episode: block 3
    # env 3: no start in the window (its episode began before it): from the window's start
    starts = [int(window_start_block(first[:, e], 24, 8)) for e in range(4)]
    assert starts == [2, 1, 3, 0]
    assert int(window_start_block(first[:, :3], 24, 8)) == 1
    assert int(window_start_block(first[:, [0, 2]], 24, 8)) == 2
    assert int(window_start_block(first[:24], 24, 8)) == 0  # not a window: nothing skipped


def test_a_sweep_skips_blocks_once_for_all_its_points():
    """Under the sweep's ``vmap`` (axis `POINT_AXIS`) the start block is reduced over the
    points, so each block is a real ``cond`` and skipped blocks cost nothing; under a plain
    ``vmap`` the predicate would differ per point and the cond become a select."""
    strat = make("episode", 0.1)
    params = strat.init(jax.random.PRNGKey(0), OBS)
    width = strat.history_length + 16
    segment = Segment(jnp.zeros((width, 2, OBS)), jnp.zeros((width, 2, P)), jnp.zeros((width, 2), bool))
    points = jax.tree.map(
        lambda v: jnp.stack([v, v]), (CoherentHParams(action_std=None, beta=jnp.asarray(0.1)), segment)
    )

    def log_prob(hp, seg):
        return strat.batch_log_prob(params, hp, seg).log_prob

    assert "cond[" in str(jax.make_jaxpr(vmap_points(log_prob))(*points))
    assert "cond[" not in str(jax.make_jaxpr(jax.vmap(log_prob))(*points))


def test_history_length_reaches_back_to_the_episode_start():
    for episode_length, unroll in ((1000, 64), (40, 16), (48, 16), (1, 8), (1000, 1000), (1000, 50)):
        h = episode_history_length(episode_length, unroll)
        assert h >= episode_length - 1 and h % unroll == 0, (episode_length, unroll, h)
        assert h == 0 or h - unroll < episode_length - 1, (episode_length, unroll, h)


@pytest.mark.parametrize("beta", [0.05, 0.3])
@pytest.mark.slow
def test_exact_without_episode_restart_is_the_thesis_buffer(x64, beta):
    """``coherent.episode_restart=false`` (the protocol's chain): a 32-step segment with an
    env reset at step 12 is scored as ONE chain from the segment's first step, values and
    gradients; with the switch on, as two."""
    hp = CoherentHParams(action_std=None, beta=jnp.asarray(beta))
    through = make("exact", beta, episode_restart=False)
    restarting = make("exact", beta)
    params = params64(through, 6)
    obs, a, _ = trajectory(through, params, beta, 7, [32])  # drawn as one chain
    first = jnp.zeros(32, bool).at[0].set(True).at[12].set(True)  # the env reset at step 12
    carry0 = through.init_carry(jax.random.PRNGKey(0), params, hp, 1)
    carry0 = jax.tree.map(lambda v: v[0], carry0)
    adv = jnp.asarray(np.random.default_rng(8).normal(size=32))
    for strat, ref_first in ((through, jnp.zeros(32, bool)), (restarting, first)):

        def loss(prm, strat=strat):
            return jnp.sum(adv * strat.log_prob(prm, hp, Segment(obs, a, first, carry0)).log_prob)

        def ref_loss(prm, ref_first=ref_first, strat=strat):
            x = strat.layer.features(prm, obs)
            return jnp.sum(adv * reference_log_marginals(x, a, ref_first, *heads(prm), beta))

        np.testing.assert_allclose(loss(params), ref_loss(params), rtol=1e-10)
        for g, r in zip(
            jax.tree.leaves(jax.grad(loss)(params)), jax.tree.leaves(jax.grad(ref_loss)(params)), strict=True
        ):
            np.testing.assert_allclose(g, r, rtol=1e-8, atol=1e-10)
    assert abs(float(loss(params)) - float(ref_loss(params))) < 1e-8


def _lag_correlations(strategy, beta, num_envs=4000, unroll=8, reset_at=4):
    """Collection over two segments with an env reset at step ``reset_at`` of the first;
    the sample correlation of the chain's standardised draws z_t, z_t+1 at every t."""
    hp = CoherentHParams(action_std=None, beta=jnp.asarray(beta, jnp.float32))
    params = strategy.init(jax.random.PRNGKey(0), OBS)
    carry = strategy.init_carry(jax.random.PRNGKey(1), params, hp, num_envs)
    obs = jnp.zeros((num_envs, OBS))
    zs = []
    key = jax.random.PRNGKey(2)
    act = jax.jit(lambda k, c, f: strategy.act(k, params, hp, c, obs, f))
    for segment in range(2):
        carry0, seg_actions, seg_first = carry, [], []
        for t in range(unroll):
            key, sub = jax.random.split(key)
            f = jnp.full((num_envs,), segment == 0 and t == reset_at)
            out = act(sub, carry, f)
            carry = out.carry
            zs.append(np.asarray(carry.z).reshape(num_envs, -1))
            seg_actions.append(out.action)
            seg_first.append(f)
        seg_obs = jnp.broadcast_to(obs, (unroll,) + obs.shape)
        segment = Segment(seg_obs, jnp.stack(seg_actions), jnp.stack(seg_first), carry0)
        _, carry = strategy.score_segment(params, hp, segment, carry, None)
    return [
        float(np.mean(zs[t] * zs[t + 1]) / np.sqrt(np.mean(zs[t] ** 2) * np.mean(zs[t + 1] ** 2)))
        for t in range(2 * unroll - 1)
    ]


@pytest.mark.slow
def test_the_protocols_chain_is_drawn_only_at_buffer_starts():
    """Lag-1 correlations of z under ``exact`` + ``episode_restart=false``: 1 - beta at every
    step, across the env reset too, and 0 across the segment (buffer) boundary; with the
    switch on, 0 across the reset as well."""
    beta = 0.2
    corr = _lag_correlations(make("exact", beta, episode_restart=False), beta)
    for t, c in enumerate(corr):
        want = 0.0 if t == 7 else 1.0 - beta
        assert abs(c - want) < 0.03, (t, c)
    corr_restart = _lag_correlations(make("exact", beta), beta)
    assert abs(corr_restart[3]) < 0.03 and abs(corr_restart[7]) < 0.03
    assert abs(corr_restart[2] - (1.0 - beta)) < 0.03
    # The episode mode's chain runs on across the segment boundary.
    corr_episode = _lag_correlations(make("episode", beta, episode_length=48, unroll=8), beta)
    assert abs(corr_episode[7] - (1.0 - beta)) < 0.03 and abs(corr_episode[3]) < 0.03


@pytest.mark.slow
def test_the_trainer_keeps_the_history_and_its_first_ratio_is_one():
    """coherent.gradient=episode through the trainer's own iteration: the history holds the
    last H steps (padding flagged as episode starts until real steps fill it), the
    behaviour log-probabilities are the loss's at the collection parameters (PPO's first
    ratio is exactly 1), and the prefix changes what the loss scores (exact differs)."""
    from coherent_jax.agents import make_trainer
    from coherent_jax.config import parse_overrides

    base = [
        "env=pointmass", "num_envs=4", "unroll_length=8", "episode_length=20", "ppo.num_epochs=2",
        "ppo.num_minibatches=2", "policy_hidden=[8]", "value_hidden=[8]", "eval_episodes=2",
        "explore=coherent",
    ]  # fmt: skip
    runs = {}
    for gradient in ("episode", "exact"):
        trainer = make_trainer(parse_overrides([*base, f"coherent.gradient={gradient}"]))
        state = jax.jit(trainer.init)(jax.random.PRNGKey(0))
        step = jax.jit(trainer.iteration)
        kls, losses_ = [], []
        for _ in range(4):
            state, metrics = step(state)
            kls.append(float(metrics["train/kl_first_minibatch"]))
            losses_.append(float(metrics["train/policy_loss"]))
        runs[gradient] = (trainer, state, kls, losses_)
    trainer, state, kls, losses_ = runs["episode"]
    assert trainer.strategy.history_length == 24 and runs["exact"][1].history == ()
    assert state.history.obs.shape == (24, 4, trainer.env.observation_size)
    assert kls == [0.0] * 4 and all(np.isfinite(losses_))
    # After 4 x 8 steps the history is real data: its episode starts every 20 steps.
    first = np.asarray(state.history.first)
    assert first.sum(axis=0).tolist() == [1] * 4 and np.abs(np.asarray(state.history.obs)).sum() > 0
    assert losses_[1:] != runs["exact"][3][1:]
