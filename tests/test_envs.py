"""Task registry and the vectorized auto-reset wrapper."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.envs import TASKS, UnknownTaskError, VecEnv, check_task

EXPECTED = {
    "halfcheetah": (17, 6),
    "hopper": (11, 3),
    "walker2d": (17, 6),
    "ant": (27, 8),
    "humanoid": (244, 17),
    "inverted_pendulum": (4, 1),
    "inverted_double_pendulum": (8, 1),
    "reacher": (11, 2),
    "swimmer": (8, 2),
}


def test_registry_has_every_task_of_the_issue():
    assert set(TASKS) == set(EXPECTED)


def test_unknown_task_lists_valid_names():
    with pytest.raises(UnknownTaskError) as err:
        check_task("cheetah")
    msg = str(err.value)
    assert "'cheetah'" in msg
    for name in TASKS:
        assert name in msg


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_task_resets_and_steps_under_jit(name):
    """Registry-wide smoke test: jitted reset and 3 steps, shapes and finite values."""
    env = VecEnv(name, num_envs=2, episode_length=1000)
    obs_size, act_size = EXPECTED[name]
    assert (env.observation_size, env.action_size) == (obs_size, act_size)

    def run(key):
        state = env.reset(key)

        def body(s, k):
            a = jax.random.uniform(k, (2, act_size), minval=-1, maxval=1)
            s, out = env.step(s, a)
            return s, out

        return jax.lax.scan(body, state, jax.random.split(key, 3))

    state, out = jax.jit(run)(jax.random.PRNGKey(0))
    assert state.obs.shape == (2, obs_size)
    assert out.reward.shape == (3, 2)
    assert out.final_obs.shape == (3, 2, obs_size)
    assert bool(jnp.all(jnp.isfinite(state.obs)))
    assert bool(jnp.all(jnp.isfinite(out.reward)))
    assert bool(jnp.all(jnp.isfinite(out.final_obs)))


def test_time_limit_truncates_resets_and_keeps_final_obs():
    """At the limit: truncated (not terminated), final_obs is pre-reset, next obs is fresh."""
    env = VecEnv("inverted_pendulum", num_envs=3, episode_length=5)

    def run(key):
        state = env.reset(key)

        def body(s, _):
            s2, out = env.step(s, jnp.zeros((3, 1)))
            return s2, (out, s2.obs, s2.first, s2.step)

        return jax.lax.scan(body, state, None, length=7)

    _, (out, next_obs, first, step) = jax.jit(run)(jax.random.PRNGKey(1))
    trunc = np.asarray(out.truncated)
    term = np.asarray(out.terminated)
    assert not term.any(), "zero action keeps the pendulum up for 5 steps"
    np.testing.assert_array_equal(trunc[:, 0], [0, 0, 0, 0, 1, 0, 0])
    np.testing.assert_array_equal(np.asarray(first)[:, 0], [0, 0, 0, 0, 1, 0, 0])
    np.testing.assert_array_equal(np.asarray(step)[:, 0], [1, 2, 3, 4, 0, 1, 2])
    # Before the limit final_obs is the next obs; at it the next obs is a fresh reset.
    np.testing.assert_allclose(out.final_obs[:4], next_obs[:4])
    assert not np.allclose(out.final_obs[4], next_obs[4])
    # The completed return is reported once, at the end of the episode.
    ret = np.asarray(out.episode_return)
    np.testing.assert_allclose(ret[4], np.asarray(out.reward)[:5].sum(axis=0), rtol=1e-5)
    assert (ret[[0, 1, 2, 3, 5, 6]] == 0).all()


def test_termination_is_not_truncation():
    """A falling pendulum terminates; its episode ends before the limit with terminated=True."""
    env = VecEnv("inverted_pendulum", num_envs=2, episode_length=1000)

    def run(key):
        state = env.reset(key)

        def body(s, _):
            s, out = env.step(s, jnp.ones((2, 1)))
            return s, out

        return jax.lax.scan(body, state, None, length=200)

    _, out = jax.jit(run)(jax.random.PRNGKey(2))
    assert np.asarray(out.terminated).any()
    assert not np.asarray(out.truncated).any()
    # Each reset starts a fresh episode from a random initial state.
    ends = np.nonzero(np.asarray(out.terminated)[:, 0])[0]
    assert len(ends) >= 2
