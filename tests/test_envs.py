"""Task registry and the vectorized auto-reset wrapper."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import BRAX_SIZES, MJX_SIDE_BY_SIDE

from coherent_jax.envs import TASKS, UnknownTaskError, VecEnv, check_task, env_sizes, make_brax_env
from coherent_jax.envs.gym_v5 import SHORT_NAMES

EXPECTED = BRAX_SIZES
# Gymnasium's v5 tasks on native MuJoCo, by short name (their Gymnasium ids name the same tasks).
EXPECTED_GYM = {
    "halfcheetah": (17, 6),
    "hopper": (11, 3),
    "walker2d": (17, 6),
    "ant": (105, 8),
    "humanoid": (348, 17),
    "inverted_pendulum": (4, 1),
    "inverted_double_pendulum": (9, 1),
    "reacher": (10, 2),
    "swimmer": (8, 2),
}


def test_registry_has_every_family():
    dmc = {name for name in TASKS if name.startswith("dmc-")}  # tests/test_dmc.py checks them
    assert set(TASKS) == set(EXPECTED) | set(EXPECTED_GYM) | set(SHORT_NAMES.values()) | dmc
    assert set(EXPECTED_GYM) == set(SHORT_NAMES)
    for short, gym_id in SHORT_NAMES.items():
        assert check_task(short) == TASKS[gym_id]
        assert f"brax-{short}" in TASKS


def test_brax_env_of_a_gymnasium_task_names_the_brax_recreation():
    with pytest.raises(UnknownTaskError, match="'hopper'.*Hopper-v5.*'brax-hopper'"):
        make_brax_env("hopper")


def test_unknown_task_lists_valid_names():
    with pytest.raises(UnknownTaskError) as err:
        check_task("cheetah")
    msg = str(err.value)
    assert "'cheetah'" in msg
    for name in TASKS:
        assert name in msg


@pytest.mark.parametrize("name", sorted(EXPECTED_GYM))
def test_every_gymnasium_task_resets_and_steps_under_jit(name):
    """Registry-wide smoke test of the standard tasks: the vectorized env under jit, shapes, finite values."""
    env = VecEnv(name, num_envs=2)
    assert (env.observation_size, env.action_size) == EXPECTED_GYM[name]

    @jax.jit
    def reset_and_step(key):
        state = env.reset(key)
        action = jax.random.uniform(key, (2, env.action_size), minval=-1, maxval=1)
        return state, env.step(env.step(state, action)[0], action)

    first, (state, out) = reset_and_step(jax.random.PRNGKey(0))
    assert first.obs.shape == state.obs.shape == (2, EXPECTED_GYM[name][0])
    assert out.reward.shape == (2,)
    assert bool(jnp.all(jnp.isfinite(first.obs))) and bool(jnp.all(jnp.isfinite(state.obs)))
    assert bool(jnp.all(jnp.isfinite(out.reward)))
    assert not bool(jnp.allclose(first.obs, state.obs)), "stepping changes the state"


# MJX compiles these in 10-30 s each (measured in CI): they run in the full suite only.
SLOW_MJX = {
    "brax-ant",
    "brax-hopper",
    "brax-humanoid",
    "brax-inverted_double_pendulum",
    "brax-reacher",
    "brax-walker2d",
}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=pytest.mark.slow) if name in SLOW_MJX else name
        for name in sorted(set(EXPECTED) - set(MJX_SIDE_BY_SIDE))
    ],
)
def test_every_brax_task_resets_and_steps_under_jit(name):
    """Registry-wide smoke test: jitted reset and step of the task, shapes and finite values.
    (The tasks of `helpers.MJX_SIDE_BY_SIDE` get the same checks in
    `test_native_physics.py`, beside native MuJoCo, from the one MJX program compiled there.)

    Compiled for a smoke test, not for speed: the two steps are one loop body (traced and
    compiled once) and XLA's backend optimisation is off: on the quiet 2-core CPU the XLA
    compile of brax-humanoid went from 36.5 s to 22.5 s, and with tracing and the env build
    from 57 s to 40 s."""
    env = make_brax_env(name)
    obs_size, act_size = EXPECTED[name]
    assert env_sizes(env) == (obs_size, act_size)

    def reset_and_step(key):
        state = env.reset(key)
        action = jax.random.uniform(key, (act_size,), minval=-1, maxval=1)
        return state, jax.lax.fori_loop(0, 2, lambda _, s: env.step(s, action), state)

    key = jax.random.PRNGKey(0)
    compiled = jax.jit(reset_and_step).lower(key).compile({"xla_backend_optimization_level": 0})
    first, state = compiled(key)
    assert first.obs.shape == state.obs.shape == (obs_size,)
    assert state.reward.shape == ()
    assert bool(jnp.all(jnp.isfinite(first.obs))) and bool(jnp.all(jnp.isfinite(state.obs)))
    assert bool(jnp.isfinite(state.reward))
    assert not bool(jnp.allclose(first.obs, state.obs)), "stepping changes the state"


def test_vectorized_env_shapes_and_auto_reset_state():
    env = VecEnv("pointmass", num_envs=3, episode_length=4)
    state = env.reset(jax.random.PRNGKey(0))
    assert state.obs.shape == (3, 6) and bool(state.first.all())
    state, out = jax.jit(env.step)(state, jnp.zeros((3, 2)))
    assert out.final_obs.shape == (3, 6) and out.reward.shape == (3,)
    assert not bool(state.first.any())
    with pytest.raises(AssertionError):
        env.step(state, jnp.zeros((2, 2)))


def test_time_limit_truncates_resets_and_keeps_final_obs():
    """At the limit: truncated (not terminated), final_obs is pre-reset, next obs is fresh."""
    env = VecEnv("pointmass", num_envs=3, episode_length=5)

    def run(key):
        state = env.reset(key)

        def body(s, _):
            s2, out = env.step(s, jnp.zeros((3, 2)))
            return s2, (out, s2.obs, s2.first, s2.step)

        return jax.lax.scan(body, state, None, length=7)

    _, (out, next_obs, first, step) = jax.jit(run)(jax.random.PRNGKey(1))
    trunc = np.asarray(out.truncated)
    term = np.asarray(out.terminated)
    assert not term.any(), "the point mass never terminates"
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


def test_registry_names_the_engines_native_tasks():
    """The JAX-free registry's native flag (what the config checks) and the native engine's
    tasks (their formulas) name the same tasks."""
    from coherent_jax.envs import physics, registry

    assert set(registry.NATIVE_TASKS) == set(physics.NATIVE_TASKS)
    assert len(registry.NATIVE_TASKS) == len(physics.NATIVE_TASKS)
