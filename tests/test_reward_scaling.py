"""Reward scaling (``normalize_rewards``): the discounted return against a plain loop,
and the identity that makes it worth having: scaled by any c > 0, the task's rewards
train the same agent."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.agents import losses
from coherent_jax.agents.onpolicy import OnPolicyTrainer
from coherent_jax.config import parse_overrides
from coherent_jax.envs import VecEnv


def returns_loop(running, rewards, done, gamma):
    """Reference: one env at a time, G = gamma G + r, restarting after a done."""
    T, n = rewards.shape
    out = np.zeros((T, n))
    g = np.array(running, dtype=np.float64)
    for e in range(n):
        for t in range(T):
            g[e] = gamma * g[e] + rewards[t, e]
            out[t, e] = g[e]
            if done[t, e]:
                g[e] = 0.0
    return g, out


@pytest.mark.parametrize("gamma", [0.99, 0.5, 0.0])
def test_discounted_returns_match_a_loop_across_episodes_and_segments(gamma):
    rng = np.random.default_rng(1)
    T, n = 40, 6
    rewards = rng.normal(size=(T, n))
    done = rng.random((T, n)) < 0.08
    done[-1, 0] = True  # an episode ends on a segment's last step: the next one starts at 0
    running0 = rng.normal(size=n)
    ref_end, ref = returns_loop(running0, rewards, done, gamma)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    end, got = losses.discounted_returns(f32(running0), f32(rewards), jnp.asarray(done), gamma)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(end, ref_end, rtol=1e-5, atol=1e-5)
    assert end[0] == 0.0
    # Two segments chained through the carried return equal the whole.
    mid = 17
    end1, first = losses.discounted_returns(f32(running0), f32(rewards[:mid]), jnp.asarray(done[:mid]), gamma)
    end2, second = losses.discounted_returns(end1, f32(rewards[mid:]), jnp.asarray(done[mid:]), gamma)
    np.testing.assert_allclose(jnp.concatenate([first, second]), ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(end2, ref_end, rtol=1e-5, atol=1e-5)


class ScaledRewards(VecEnv):
    """The same task with every reward multiplied by ``scale`` (a traced scalar)."""

    def __init__(self, scale, *args):
        super().__init__(*args)
        self.scale = scale

    def step(self, state, action):
        new_state, outcome = super().step(state, action)
        return new_state, outcome.replace(
            reward=outcome.reward * self.scale, episode_return=outcome.episode_return * self.scale
        )


def _train(normalize: bool, scales, iterations: int = 3):
    """Trains from the same seed once per reward scale; one compiled program for all scales."""
    cfg = parse_overrides(
        [
            "env=pointmass",
            "num_envs=8",
            "unroll_length=16",
            "num_minibatches=2",
            "num_epochs=2",
            "episode_length=20",
            f"normalize_rewards={str(normalize).lower()}",
        ]
    )

    @jax.jit
    def run(scale):
        env = ScaledRewards(scale, cfg.env, cfg.num_envs, cfg.episode_length)
        trainer = OnPolicyTrainer(cfg, env=env, eval_env=env)
        state, metrics = jax.lax.scan(
            lambda s, _: trainer.iteration(s), trainer.init(jax.random.PRNGKey(3)), None, length=iterations
        )
        return state, jax.tree.map(lambda m: m[-1], metrics)

    return [run(jnp.float32(c)) for c in scales]


@pytest.mark.slow
def test_scaled_rewards_train_the_same_agent_only_with_reward_scaling():
    """With normalize_rewards the value targets, advantages and every update see r / std(G),
    which does not change when every reward is multiplied by c; the return statistics do,
    by c^2. Without it the value loss (and with it the shared gradient clip) sees c, so the
    same check fails: the identity is the scaling's, not the test's."""
    (base, m_base), (scaled, m_scaled) = _train(True, [1.0, 1000.0])
    for a, b in zip(jax.tree.leaves(base.params), jax.tree.leaves(scaled.params), strict=True):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(scaled.reward_norm.stats.var, 1e6 * base.reward_norm.stats.var, rtol=1e-4)
    np.testing.assert_allclose(m_scaled["train/return_std"], 1000.0 * m_base["train/return_std"], rtol=1e-4)
    assert float(base.reward_norm.stats.count) == 3 * 8 * 16
    # Episode returns are reported in the task's own rewards.
    np.testing.assert_allclose(
        m_scaled["train/episode_return"], 1000.0 * m_base["train/episode_return"], rtol=1e-3
    )

    (plain, _), (plain_scaled, _) = _train(False, [1.0, 1000.0])
    differs = [
        not np.allclose(a, b, rtol=2e-4, atol=2e-5)
        for a, b in zip(jax.tree.leaves(plain.params), jax.tree.leaves(plain_scaled.params), strict=True)
    ]
    assert any(differs)
    # Off, the statistics stay at their initial values.
    assert float(plain.reward_norm.stats.count) == 0.0
