"""The DeepMind Control Suite's tasks through MuJoCo Playground (``dmc-*``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from coherent_jax.envs import TASKS, VecEnv, check_task, make_brax_env
from coherent_jax.envs.registry import DMC_SPARSE_TASKS, dmc_name


def test_dmc_family_is_playgrounds_control_suite():
    """One ``dmc-*`` name per Playground DeepMind Control env, with Playground's time limit."""
    from mujoco_playground import registry

    ids = registry.dm_control_suite.ALL_ENVS
    assert {name for name in TASKS if name.startswith("dmc-")} == {dmc_name(i) for i in ids}
    assert dmc_name("CartpoleSwingupSparse") == "dmc-cartpole_swingup_sparse"
    assert dmc_name("BallInCup") == "dmc-ball_in_cup"
    assert set(DMC_SPARSE_TASKS) >= {
        "dmc-cartpole_swingup_sparse",
        "dmc-acrobot_swingup_sparse",
        "dmc-ball_in_cup",
        "dmc-finger_turn_hard",
    }
    for i in ids:
        spec = check_task(dmc_name(i))
        assert spec.playground_id == i
        cfg = registry.get_default_config(i)
        assert spec.episode_length * cfg.action_repeat == cfg.episode_length, i
        assert spec.backend == "mjx"


def test_dmc_task_under_the_vectorized_wrapper():
    """Playground's env under the vectorized wrapper, jitted: the reset is Playground's
    reset from the wrapper's keys, actions are clipped to [-1, 1], the sparse reward is 0
    or 1, nothing terminates, and the time limit truncates with the pre-reset observation
    kept and a fresh initial state drawn.

    Compiled for a check of the wrapper, not for speed (XLA's backend optimisation off):
    Playground's import, MJX's tracing and the compile are 10-20 s each on this CPU."""
    name, n, limit = "dmc-cartpole_swingup_sparse", 2, 3
    env = VecEnv(name, num_envs=n, episode_length=limit)
    raw = make_brax_env(name)
    assert (env.observation_size, env.action_size, env.dt) == (5, 1, pytest.approx(0.01))
    # Beyond the actuator's range, to see the clipping.
    actions = jnp.array([3.0, -3.0, 0.5, 1.0])[:, None, None] * jnp.ones((1, n, 1))

    def run(key):
        def body(state, a):
            state, out = env.step(state, a)
            return state, (state, out)

        state = env.reset(key)
        return state, *jax.lax.scan(body, state, actions)[1]

    key = jax.random.PRNGKey(0)
    compiled = jax.jit(run).lower(key).compile({"xla_backend_optimization_level": 0})
    state0, states, outcomes = jax.tree.map(np.asarray, compiled(key))
    # Playground's own reset from the keys the wrapper's first reset uses (eval_shape:
    # traced, not compiled again) has the same structure; its first observation is the
    # initial pose's: the cart near 0 and the pole hanging down (cos = -1), within 6 sigma.
    ref = jax.eval_shape(jax.vmap(raw.reset), jax.random.split(jax.random.split(key)[1], n))
    assert jax.tree.structure(ref) == jax.tree.structure(jax.tree.map(jnp.asarray, state0.physics))
    np.testing.assert_allclose(state0.obs[:, :3], [[0.0, -1.0, 0.0]] * n, atol=0.06)  # noise 0.01 N(0, 1)
    # The clipped action moved the cart as +1 and -1 would: the cart velocity (obs 3)
    # after the first two steps has the sign of the clipped action.
    assert (states.obs[0, :, 3] > 0).all() and (states.obs[1, :, 3] < states.obs[0, :, 3]).all()
    assert set(np.unique(outcomes.reward)) <= {0.0, 1.0}
    assert not outcomes.terminated.any()
    np.testing.assert_array_equal(outcomes.truncated[:, 0], [False, False, True, False])
    np.testing.assert_array_equal(outcomes.final_obs[: limit - 1], states.obs[: limit - 1])
    assert states.first[limit - 1].all() and (states.step[limit - 1] == 0).all()
    # The reset after the time limit is a fresh draw, not the first state replayed.
    assert not np.array_equal(states.obs[limit - 1], state0.obs)
    assert not np.array_equal(outcomes.final_obs[limit - 1], states.obs[limit - 1])
